"""Along-track slips of odometry runs on the building floor, per window of frames.

For every window [i, i + W) of frames the odometry's relative motion (``odometry.tum``,
the front end's own poses) is compared with the truth's over the same frames: the error
of the relative translation, expressed in the true frame at i, projected on the true
direction of travel (m; negative = the estimate moved less than the truth, the slip of a
corridor without features). Windows with at least ``min_plain`` (15 %) of their frames
within 2 m of a plain corridor stretch (``slam.sim.building.PLAIN``) are marked ``plain``
(a slip there straddles two windows); the sums over
the plain windows and over all the others separate the corridor slips from the error
elsewhere (docs/paper001.md).

    .venv/bin/python benchmarks/slip_windows.py GT.tum label=RUN_DIR [label=RUN_DIR ...] \\
        [--window 100] [--show 0.8] [--json OUT.json] [--figure OUT.png]

``--figure``: the along-track error per window of every run (plain windows shaded) over
the z error of its optimised trajectory (``trajectory.tum``, SE(3)-aligned as in the
tables) against time.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from slam.bench.slip import windows


def figure(res: dict, runs: dict[str, Path], gt: Path, window: int, path: Path) -> Path:
    """Along-track error per window (top) and aligned z error over time (bottom)."""
    from slam.eval.metrics import evaluate
    from slam.eval.plots import evo_plot, save_png

    evo_plot()  # Agg backend, evo's style
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10.0, 6.4), dpi=90, sharex=False)
    first = next(iter(res.values()))
    for s, p in zip(first["starts"], first["plain"], strict=True):
        if p:
            top.axvspan(s, s + window, color="0.85", lw=0)
    for label, r in res.items():
        top.plot(np.array(r["starts"]) + window / 2, r["along"], ".-", lw=1, label=label)
        ev = evaluate(runs[label] / "trajectory.tum", gt)
        dz = ev.est_poses[:, 2, 3] - ev.gt_poses[:, 2, 3]
        bottom.plot(ev.stamps - ev.stamps[0], dz, lw=1, label=label)
    top.axhline(0.0, color="k", lw=0.5)
    top.set_xlabel(f"frame (window of {window}; grey: plain corridor stretch)")
    top.set_ylabel("along-track error (m)")
    top.legend(fontsize=7, ncol=4)
    bottom.axhline(0.0, color="k", lw=0.5)
    bottom.set_xlabel("t (s)")
    bottom.set_ylabel("z error, aligned (m)")
    fig.tight_layout()
    return save_png(fig, path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("gt", type=Path)
    ap.add_argument("runs", nargs="+", help="label=RUN_DIR (odometry.tum inside)")
    ap.add_argument("--window", type=int, default=100)
    ap.add_argument("--show", type=float, default=0.8, help="list windows with |error| above")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--figure", type=Path, help="PNG: slips per window and z over time")
    args = ap.parse_args(argv)
    res, runs = {}, {}
    for spec in args.runs:
        label, _, run = spec.partition("=")
        runs[label] = Path(run)
        res[label] = windows(runs[label] / "odometry.tum", args.gt, args.window)
    print("| run | sum \\|along\\| plain (m) | sum \\|along\\| elsewhere (m) | max elsewhere (m) |")
    print("|:---|---:|---:|---:|")
    for label, r in res.items():
        print(f"| {label} | {r['sum_abs_plain']:.2f} | {r['sum_abs_elsewhere']:.2f} | "
              f"{r['max_abs_elsewhere']:.2f} |")  # fmt: skip
    print()
    for label, r in res.items():
        big = [f"{s}{'p' if p else ''}:{e:+.2f}"
               for s, e, p in zip(r["starts"], r["along"], r["plain"], strict=True)
               if abs(e) > args.show]  # fmt: skip
        print(f"{label}: {' '.join(big)}")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    if args.figure:
        print(f"figure: {figure(res, runs, args.gt, args.window, args.figure)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
