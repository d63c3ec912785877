"""What loop closure could do at best on a sequence: loops whose constraints are the truth.

A factor plugin (``slam.bench.oracle.OracleLoops``) adds BetweenFactorPose3 loops with the true
relative pose of two keyframes (from the ground truth, nearest stamp) and a tight noise
(5 cm / 0.5 deg), either

- ``pairs``: exactly the loops of a run (its graph.g2o loop edges): the bound of that run's loop
  closure if every one of its loops had been exact, or
- ``radius``: every pair of keyframes truly within ``radius`` m of each other and at least
  ``min_gap`` keyframes apart (one per new keyframe: its nearest such older keyframe, or
  all of them with ``all_pairs``): what a perfect place recogniser could add.

The front end's odometry comes from a loop_replay.py recording (the same odometry factors
as the real run), so the difference to the real loop closure is the loops alone.

    .venv/bin/python benchmarks/loop_oracle.py REC.npz GT.tum --config lego_lpb_loop \
        --out runs/oracle/x [--pairs RUN_DIR | --radius 3 --min-gap 30]
    # a recording with frontend.odometry_ambiguity, replayed with another ratio / sigma
    .venv/bin/python benchmarks/loop_oracle.py REC.npz GT.tum --config lego_lpb_loop \\
        --out runs/oracle/z --real-loops --reloosen 0.8 0.3
    # the run's own loops, odometry loosened along the plain corridor stretches
    .venv/bin/python benchmarks/loop_oracle.py REC.npz GT.tum --config lego_lpb_loop \\
        --out runs/oracle/y --real-loops --loosen-plain 0.3
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from slam.bench.loop_replay import load_recording, replay
from slam.bench.oracle import loosen_plain, reloosen


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("--config", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--pairs", type=Path, help="a run's folder: true constraints for its loops")
    ap.add_argument("--radius", type=float, default=3.0)
    ap.add_argument("--min-gap", type=int, default=30)
    ap.add_argument("--all-pairs", action="store_true")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument(
        "--loosen-plain",
        type=float,
        metavar="SIGMA",
        help="building scenes: along-track odometry sigma (m) of keyframes in plain corridor "
        "stretches (an oracle of degeneracy-aware odometry information)",
    )
    ap.add_argument(
        "--real-loops",
        action="store_true",
        help="keep the config's own loop closure instead of true loops (with --loosen-plain)",
    )
    ap.add_argument(
        "--reloosen",
        type=float,
        nargs=2,
        metavar=("RATIO", "SIGMA"),
        help="a recording made with frontend.odometry_ambiguity: its information as that "
        "test would give it with this ratio and sigma (m) instead (exact, no oracle)",
    )
    a = ap.parse_args(argv)
    rec = load_recording(a.recording)
    loosened = reloosen(rec, *a.reloosen) if a.reloosen else 0
    if a.loosen_plain:  # on top of --reloosen (99 1: the information before the test)
        loosened = loosen_plain(rec, a.gt, a.loosen_plain)
    if a.real_loops:
        res = replay(rec, a.config, a.overrides, a.out, a.gt)
        res["loosened_keyframes"] = loosened
        print(json.dumps(res))
        (a.out / "oracle.json").write_text(json.dumps(res, indent=2))
        return 0
    over = [
        *a.overrides,
        "factors.loop_closure.enabled=false",
        "factors.oracle.plugin=slam.bench.oracle:OracleLoops",
        f"factors.oracle.gt={a.gt.resolve()}",
        f"factors.oracle.radius={a.radius}",
        f"factors.oracle.min_gap={a.min_gap}",
        f"factors.oracle.all_pairs={str(a.all_pairs).lower()}",
    ]
    if a.pairs:
        over.append(f"factors.oracle.pairs={a.pairs.resolve()}")
    res = replay(rec, a.config, over, a.out, a.gt)
    res = {k: v for k, v in res.items() if k in ("ape_odometry", "ape_loop", "loops_closed")}
    res["mode"] = f"pairs of {a.pairs}" if a.pairs else f"radius {a.radius} m, gap {a.min_gap}"
    res["loosened_keyframes"] = loosened
    print(json.dumps(res))
    (a.out / "oracle.json").write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
