"""Loop-closure experiments without re-running the front end: record once, replay many.

The front end never sees the back end (DESIGN.md), so a run's odometry and keyframe clouds
do not depend on the loop closure: ``record`` runs a recipe's front end once over a bag and
stores every frame's Odometry (pose, relative motion, information, keyframe flag, the
keyframes' clouds and scalar extras) in one .npz; ``replay`` feeds those to a Pipeline
with any factor / back-end settings (``--set factors.loop_closure.x=...``), writes the
usual run outputs (trajectory.tum, graph.g2o, loops.csv, ...) and prints APE of odometry and
optimised trajectory and the false loops against the ground truth (loop_audit.py). The
recorder and the replay are ``slam.bench.loop_replay``.
A replay gives the same trajectory as ``slam run`` of the same recipe (the loop plugin reads
only keyframes and estimates).

    .venv/bin/python benchmarks/loop_replay.py record BAG --config lego_lpb_loop OUT.npz
    .venv/bin/python benchmarks/loop_replay.py replay OUT.npz --config lego_lpb_loop \
        --gt GT.tum --out runs/replay/x [--set factors.loop_closure.robust=cauchy ...]
    .venv/bin/python benchmarks/loop_replay.py figures GT.tum lpb=runs/replay/x \\
        loam=runs/replay/y --out docs/lego_lpb/return --prefix building_return
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from slam.bench.loop_replay import load_recording, record, replay


def figures(runs: list[str], gt: Path, out: Path, prefix: str) -> list[Path]:
    """Figures in paper 001's style for replayed loop runs (``name=RUN_DIR``): the
    odometry of the first and every run's optimised trajectory over the truth (xy), their
    APE over time, and per run the trajectory coloured by its APE and its APE over time."""
    from slam.eval.metrics import evaluate
    from slam.eval.plots import (
        ape_colormap_figure,
        ape_figure,
        ape_overlay_figure,
        overlay_figure,
        save_png,
    )

    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for k, spec in enumerate(runs):
        name, _, run = spec.partition("=")
        if k == 0:
            results[f"{name} odometry"] = evaluate(Path(run) / "odometry.tum", gt)
        results[name] = evaluate(Path(run) / "trajectory.tum", gt)
    files = [save_png(overlay_figure(results, "xy"), out / f"{prefix}_overlay_xy.png")]
    files.append(save_png(ape_overlay_figure(results), out / f"{prefix}_ape_overlay.png"))
    for name, res in results.items():
        safe = name.replace(" ", "_")
        files.append(save_png(ape_colormap_figure(res), out / f"{prefix}_{safe}_heatmap.png"))
        files.append(save_png(ape_figure(res), out / f"{prefix}_{safe}_ape_time.png"))
    return files


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("bag", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--config", required=True)
    r.add_argument("--set", dest="overrides", action="append", default=[])
    r.add_argument("--max-frames", type=int)
    p = sub.add_parser("replay")
    p.add_argument("recording", type=Path)
    p.add_argument("--config", required=True)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--gt", type=Path)
    f = sub.add_parser("figures", help="paper-style figures of replayed runs")
    f.add_argument("gt", type=Path)
    f.add_argument("runs", nargs="+", help="name=RUN_DIR (the first one's odometry is drawn too)")
    f.add_argument("--out", type=Path, required=True)
    f.add_argument("--prefix", default="replay")
    a = ap.parse_args(argv)
    if a.cmd == "record":
        record(a.bag, a.config, a.out, a.overrides, a.max_frames)
    elif a.cmd == "figures":
        for path in figures(a.runs, a.gt, a.out, a.prefix):
            print(path)
    else:
        res = replay(load_recording(a.recording), a.config, a.overrides, a.out, a.gt)
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
