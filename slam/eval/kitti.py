"""KITTI odometry devkit metric: relative translation (%) and rotation (deg/100 m) drift.

evo does not compute it (evo issues #144, #516), so this follows the devkit's
``evaluate_odometry.cpp``: cumulative path distances of the ground truth; for every
``first`` in ``range(0, N, step)`` and every segment length L, ``last`` is the first index
with ``dist[last] > dist[first] + L``; the segment error is
``E = inv(inv(gt_first) gt_last) @ (inv(est_first) est_last)``, ``t_err = |trans(E)| / L``,
``r_err = angle(E) / L``; both are averaged over all segments of all lengths.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from slam.errors import InputError

KITTI_LENGTHS: tuple[float, ...] = (100, 200, 300, 400, 500, 600, 700, 800)


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """(N,) cumulative path length in metres of (N,4,4) poses, starting at 0."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def _check(gt_poses: np.ndarray, est_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt = np.asarray(gt_poses, dtype=float)
    est = np.asarray(est_poses, dtype=float)
    if gt.ndim != 3 or gt.shape[1:] != (4, 4) or est.shape != gt.shape:
        raise InputError(
            f"KITTI metric needs two (N,4,4) pose arrays of equal length, got {gt.shape} "
            f"and {est.shape}; associate the trajectories first"
        )
    if gt.shape[0] < 2:
        raise InputError("KITTI metric needs at least 2 poses")
    return gt, est


def _rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) of (M,3,3) matrices, clipped like the devkit's acos."""
    d = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    return np.arccos(np.clip(d, -1.0, 1.0))


def _relative(poses: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    return np.linalg.inv(poses[first]) @ poses[last]


def kitti_metric(
    gt_poses: np.ndarray,
    est_poses: np.ndarray,
    lengths: Sequence[float] = KITTI_LENGTHS,
    step: int = 10,
) -> dict:
    """KITTI devkit drift of ``est_poses`` against ``gt_poses`` (both (N,4,4), associated).

    Returns ``{"t_rel_pct", "r_rel_deg_per_100m", "segments", "lengths", "per_length"}``;
    ``per_length`` is a list of ``{"length", "segments", "t_rel_pct", "r_rel_deg_per_100m"}``.
    When no segment fits (path shorter than the smallest length) the rates are ``None``:
    use :func:`kitti_metric_scaled` for short runs.
    """
    gt, est = _check(gt_poses, est_poses)
    if step < 1:
        raise InputError(f"KITTI step must be >= 1 frame, got {step}")
    dist = trajectory_distances(gt)
    firsts = np.arange(0, gt.shape[0], step)
    t_all: list[np.ndarray] = []
    r_all: list[np.ndarray] = []
    per_length = []
    for length in lengths:
        length = float(length)
        if length <= 0:
            raise InputError(f"KITTI segment lengths must be > 0 m, got {length}")
        # first index whose distance exceeds dist[first] + L (strictly), as in the devkit
        last = np.searchsorted(dist, dist[firsts] + length, side="right")
        ok = last < gt.shape[0]
        f, l_ = firsts[ok], last[ok]
        if f.size:
            err = np.linalg.inv(_relative(gt, f, l_)) @ _relative(est, f, l_)
            t_err = np.linalg.norm(err[:, :3, 3], axis=1) / length
            r_err = _rotation_angle(err[:, :3, :3]) / length
            t_all.append(t_err)
            r_all.append(r_err)
        per_length.append(_summary(t_err if f.size else None, r_err if f.size else None, length))
    t_cat = np.concatenate(t_all) if t_all else np.empty(0)
    r_cat = np.concatenate(r_all) if r_all else np.empty(0)
    out = _summary(t_cat if t_cat.size else None, r_cat if r_cat.size else None, None)
    out["lengths"] = [float(x) for x in lengths]
    out["step"] = int(step)
    out["path_length"] = float(dist[-1])
    out["per_length"] = per_length
    return out


def _summary(t_err: np.ndarray | None, r_err: np.ndarray | None, length: float | None) -> dict:
    row: dict = {} if length is None else {"length": float(length)}
    if t_err is None or r_err is None:
        row.update(segments=0, t_rel_pct=None, r_rel_deg_per_100m=None)
    else:
        row.update(
            segments=int(t_err.size),
            t_rel_pct=float(np.mean(t_err) * 100.0),
            r_rel_deg_per_100m=float(np.degrees(np.mean(r_err)) * 100.0),
        )
    return row


def scaled_lengths(path_length: float, count: int = 8) -> tuple[float, ...]:
    """``count`` evenly spaced segment lengths for a short run: ``k * u`` for k = 1..count.

    ``u`` is the largest 1-2-5 step with ``count * u`` at most 80 % of ``path_length``
    (the devkit's 800 m longest segment on ~1 km sequences), e.g. 105 m -> 10, 20, ..., 80 m.
    """
    if not path_length > 0:
        raise InputError(f"cannot scale KITTI segments to a path of {path_length} m")
    target = 0.8 * path_length / count
    exp = math.floor(math.log10(target))
    unit = 10.0**exp
    for mult in (5.0, 2.0, 1.0):
        if mult * 10.0**exp <= target:
            unit = mult * 10.0**exp
            break
    return tuple(round(k * unit, 10) for k in range(1, count + 1))


def kitti_metric_scaled(
    gt_poses: np.ndarray,
    est_poses: np.ndarray,
    lengths: Sequence[float] | None = None,
    step: int = 10,
) -> dict:
    """The devkit metric with segment lengths fitting a short (e.g. indoor) run.

    ``lengths=None`` picks :func:`scaled_lengths` of the ground-truth path length. Same
    output as :func:`kitti_metric`; percentages stay per metre travelled, so they compare
    with, but are not identical to, the 100..800 m KITTI numbers.
    """
    gt, est = _check(gt_poses, est_poses)
    if lengths is None:
        lengths = scaled_lengths(float(trajectory_distances(gt)[-1]))
    out = kitti_metric(gt, est, lengths=lengths, step=step)
    out["scaled"] = True
    return out
