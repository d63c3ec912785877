"""Along-track slips of odometry on the building floor, per window of frames: the error of
the relative translation over each window, projected on the true direction of travel (m;
negative = the estimate moved less than the truth, the slip of a corridor without
features), and which windows lie on the floor's plain corridor stretches."""

from __future__ import annotations

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
