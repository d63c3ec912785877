"""What loop closure could do at best on a sequence: loops whose constraints are the truth.

A factor plugin (:class:`OracleLoops`) adds BetweenFactorPose3 loops with the true
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
import sys
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from slam.factors import FactorConfig, GraphView, key, pose3  # noqa: E402
from slam.io.trajectory import read_tum  # noqa: E402
from slam.types import Keyframe  # noqa: E402


def run_pairs(run_dir: Path) -> set[tuple[float, float]]:
    """(stamp_target, stamp_source) of the loops in a run's pose graph (its graph.g2o loop
    edges, stamps from its loops.csv): the loops it kept, unconfirmed ones excluded."""
    from loop_audit import keyframe_stamps, loop_edges, loop_pairs

    stamps = keyframe_stamps(run_dir / "loops.csv")
    edges = loop_edges(run_dir / "graph.g2o", loop_pairs(run_dir / "loops.csv"))
    return {(round(stamps[a], 6), round(stamps[b], 6)) for a, b, _, _ in edges}


class OracleLoops:
    """True loops (see the module doc)."""

    is_loop = True

    @dataclass
    class Config(FactorConfig):
        gt: str = ""
        pairs: str = ""  # a run's folder: the loops of its graph.g2o only
        radius: float = 3.0
        min_gap: int = 30
        all_pairs: bool = False
        sigma_trans: float = 0.05
        sigma_rot_deg: float = 0.5

    def __init__(self, config: Config):
        self.config = config
        self._stamps, self._poses = read_tum(Path(config.gt))
        self._pairs = run_pairs(Path(config.pairs)) if config.pairs else None
        self._kf_true: list[np.ndarray] = []
        self._kf_stamp: list[float] = []
        s = np.radians(config.sigma_rot_deg)
        t = config.sigma_trans
        self._noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([s, s, s, t, t, t]))
        self.added: list[tuple[int, int]] = []

    def _true(self, stamp: float) -> np.ndarray:
        i = int(np.clip(np.searchsorted(self._stamps, stamp), 1, len(self._stamps) - 1))
        j = i if abs(self._stamps[i] - stamp) < abs(self._stamps[i - 1] - stamp) else i - 1
        return self._poses[j]

    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.NonlinearFactor]:
        T = self._true(kf.stamp)
        self._kf_true.append(T)
        self._kf_stamp.append(float(kf.stamp))
        c = self.config
        targets: list[int] = []
        if self._pairs is not None:
            me = round(float(kf.stamp), 6)
            targets = [
                j for j, st in enumerate(self._kf_stamp[:-1]) if (round(st, 6), me) in self._pairs
            ]
        elif kf.id >= c.min_gap:
            old = np.array([P[:3, 3] for P in self._kf_true[: kf.id - c.min_gap + 1]])
            d = np.linalg.norm(old - T[:3, 3], axis=1)
            near = np.flatnonzero(d < c.radius)
            if len(near):
                targets = list(near) if c.all_pairs else [int(near[np.argmin(d[near])])]
        out = []
        for j in targets:
            rel = np.linalg.inv(self._kf_true[j]) @ T
            out.append(gtsam.BetweenFactorPose3(key(j), key(kf.id), pose3(rel), self._noise))
            self.added.append((int(j), int(kf.id)))
        return out


def loosen_plain(rec: dict, gt: Path, sigma: float) -> int:
    """In place: the odometry information of the recording's keyframes that truly lie in a
    plain corridor stretch of the building floor (slam.sim.building.PLAIN, within 2 m of
    the corridor's centre line) loses its along-track part, replaced by 1 / sigma^2 (m):
    what a degeneracy-aware front end would report there, located by the truth (an
    oracle). Returns the number of keyframes changed."""
    from slam.sim.building import LANES, PLAIN

    tg, G = read_tum(gt)
    info = rec["info"].copy()
    n = 0
    for i in np.flatnonzero(rec["is_kf"]):
        j = min(int(np.searchsorted(tg, rec["stamps"][i] - 1e-6)), len(tg) - 1)
        x, y = G[j][0, 3], G[j][1, 3]
        if not any(abs(y - LANES[k]) < 2.0 and x0 <= x <= x1 for k, x0, x1 in PLAIN):
            continue
        t = rec["relative"][i][:3, 3]
        if np.linalg.norm(t) < 1e-3:
            continue
        u = t / np.linalg.norm(t)
        lam = np.trace(info[i][3:, 3:]) / 3.0
        info[i][3:, 3:] = lam * (np.eye(3) - np.outer(u, u)) + np.outer(u, u) / sigma**2
        n += 1
    rec["info"] = info
    return n


def reloosen(rec: dict, ratio: float, sigma: float) -> int:
    """In place: the recording's keyframe odometry information as the front end's
    ``odometry_ambiguity`` would have given it with another ``ratio`` / ``sigma`` (the slide
    test's ratio and axis of every keyframe are in the recording's extras, the information
    before loosening in ``info_raw``): exact, not an oracle. Returns the keyframes loosened."""
    from slam.registration.ambiguity import loosened_information

    extras = json.loads(str(rec["extras"]))
    info = rec["info_raw"].copy()
    n = 0
    for i, e in enumerate(extras):
        if "ambiguity" in e and e["ambiguity"] >= ratio:
            axis = np.array([e["ambiguity_axis_x"], e["ambiguity_axis_y"], 0.0])
            info[i] = loosened_information(info[i], axis, sigma)
            n += 1
    rec["info"] = info
    return n


def main(argv: list[str] | None = None) -> int:
    from loop_replay import load_recording, replay

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
        "factors.oracle.plugin=loop_oracle:OracleLoops",
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
