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


def plain_mask(xy: np.ndarray, margin: float = 2.0) -> np.ndarray:
    """(N,) bool: points (N, 2) within ``margin`` m of a plain corridor stretch's centre
    line (the building floor's PLAIN stretches on their LANES)."""
    from slam.sim.building import LANES, PLAIN

    mask = np.zeros(len(xy), dtype=bool)
    for k, x0, x1 in PLAIN:
        mask |= (np.abs(xy[:, 1] - LANES[k]) < margin) & (xy[:, 0] >= x0) & (xy[:, 0] <= x1)
    return mask


def along_track(est: np.ndarray, gt: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Window starts (M,) and the along-track error (M,) of the relative translation of
    ``est`` against ``gt`` (both (N, 4, 4), the same frames) over [i, i + window]."""
    starts = np.arange(0, len(est) - 1, window)
    ends = np.minimum(starts + window, len(est) - 1)
    out = np.empty(len(starts))
    for k, (i, j) in enumerate(zip(starts, ends, strict=True)):  # M windows, not points
        rel_e = np.linalg.inv(est[i]) @ est[j]
        rel_g = np.linalg.inv(gt[i]) @ gt[j]
        d = rel_g[:3, 3]
        n = np.linalg.norm(d)
        u = d / n if n > 1e-6 else np.zeros(3)
        out[k] = float((rel_e[:3, 3] - d) @ u)
    return starts, out


def matched(est_path: Path, gt_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Estimate and true poses at the estimate's stamps (nearest true stamp within 5 ms)."""
    from slam.io.trajectory import read_tum

    te, est = read_tum(est_path)
    tg, gt = read_tum(gt_path)
    j = np.clip(np.searchsorted(tg, te), 1, len(tg) - 1)
    j = np.where(np.abs(tg[j - 1] - te) < np.abs(tg[j] - te), j - 1, j)
    ok = np.abs(tg[j] - te) < 5e-3
    if not ok.all():
        raise ValueError(f"{est_path}: {int((~ok).sum())} stamps without a true pose")
    return est, gt[j]


def windows(est_path: Path, gt_path: Path, window: int = 100, min_plain: float = 0.15) -> dict:
    """Per-window along-track error and the plain / elsewhere sums of one run."""
    est, gt = matched(est_path, gt_path)
    starts, err = along_track(est, gt, window)
    ends = np.minimum(starts + window, len(est) - 1)
    plain = plain_mask(gt[:, :2, 3])
    frac = [plain[i : j + 1].mean() for i, j in zip(starts, ends, strict=True)]
    is_plain = np.array(frac) >= min_plain
    return {
        "starts": starts.tolist(),
        "along": err.tolist(),
        "plain": is_plain.tolist(),
        "sum_abs_plain": float(np.abs(err[is_plain]).sum()),
        "sum_abs_elsewhere": float(np.abs(err[~is_plain]).sum()),
        "max_abs_elsewhere": float(np.abs(err[~is_plain]).max()) if (~is_plain).any() else 0.0,
        "rms_elsewhere": float(np.sqrt(np.mean(err[~is_plain] ** 2))) if (~is_plain).any() else 0.0,
        "windows": len(starts),
    }


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
