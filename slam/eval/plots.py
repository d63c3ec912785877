"""Evaluation plots saved as PNG files.

Figures are built with ``matplotlib.figure.Figure`` and the Agg canvas, never pyplot: no
window opens, no global backend is switched, and evo's plot settings (``~/.evo``) are not
touched. Lengths in metres, angles in degrees, time in seconds from the first matched pose.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from scipy.spatial.transform import Rotation

from slam.errors import InputError
from slam.eval.metrics import EvalResult

DPI = 110
GT_STYLE = {"color": "0.35", "linestyle": "--", "linewidth": 1.2, "label": "ground truth"}
EST_STYLE = {"color": "tab:blue", "linewidth": 1.4, "label": "estimate"}


def _figure(rows: int = 1, cols: int = 1, size: tuple[float, float] = (8.0, 6.0), **kw):
    fig = Figure(figsize=size, dpi=DPI, layout=None)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False, **kw)
    return fig, axes


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, format="png", dpi=DPI)
    return path


def _seconds(result: EvalResult) -> np.ndarray:
    return result.stamps - result.stamps[0]


def _view(ax, plane: str) -> tuple[int, int]:
    i, j = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}[plane]
    ax.set_xlabel(f"{plane[0]} [m]")
    ax.set_ylabel(f"{plane[1]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    return i, j


def plot_trajectory(result: EvalResult, path: Path, plane: str = "xy") -> Path:
    """Estimate (aligned) against ground truth projected on ``plane``."""
    fig, ax = _figure()
    ax = ax[0, 0]
    i, j = _view(ax, plane)
    gt, est = result.gt_poses[:, :3, 3], result.est_poses[:, :3, 3]
    ax.plot(gt[:, i], gt[:, j], **GT_STYLE)
    ax.plot(est[:, i], est[:, j], **EST_STYLE)
    ax.plot(gt[0, i], gt[0, j], "o", color="tab:green", label="start")
    ax.set_title(f"Trajectory ({plane.upper()}), {result.options.align} alignment")
    ax.legend(loc="best")
    return _save(fig, path)


def plot_ape_over_time(result: EvalResult, path: Path) -> Path:
    """Translational APE per pose with mean, median, RMSE lines and the mean +- std band."""
    fig, ax = _figure(size=(9.0, 4.5))
    ax = ax[0, 0]
    t, e, s = _seconds(result), result.ape_errors, result.ape_trans
    ax.plot(t, e, color="tab:blue", linewidth=1.2, label="APE")
    ax.axhspan(s["mean"] - s["std"], s["mean"] + s["std"], color="tab:orange", alpha=0.2,
               label="mean ± std")  # fmt: skip
    ax.axhline(s["mean"], color="tab:orange", label=f"mean {s['mean']:.3f} m")
    ax.axhline(s["median"], color="tab:green", linestyle="--", label=f"median {s['median']:.3f} m")
    ax.axhline(s["rmse"], color="tab:red", linestyle=":", label=f"RMSE {s['rmse']:.3f} m")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("APE (translation) [m]")
    ax.set_title("Absolute pose error over time")
    ax.grid(True, alpha=0.3)
    top = float(max(e.max(), s["mean"] + s["std"]))
    ax.set_ylim(0.0, 1.3 * top if top > 0 else 1.0)  # headroom for the legend row
    ax.legend(loc="upper center", ncol=5, fontsize="small")
    return _save(fig, path)


def plot_error_heatmap(result: EvalResult, path: Path, plane: str = "xy") -> Path:
    """Estimated path coloured by its translational APE, ground truth dashed."""
    fig, ax = _figure()
    ax = ax[0, 0]
    i, j = _view(ax, plane)
    gt, est = result.gt_poses[:, :3, 3], result.est_poses[:, :3, 3]
    ax.plot(gt[:, i], gt[:, j], **GT_STYLE)
    xy = est[:, [i, j]]
    segs = np.stack([xy[:-1], xy[1:]], axis=1)
    err = result.ape_errors
    seg_err = 0.5 * (err[:-1] + err[1:]) if err.size > 1 else err
    lc = LineCollection(segs, cmap="jet", linewidth=2.5)
    lc.set_array(seg_err)
    lc.set_clim(float(err.min()), float(err.max()) if err.max() > err.min() else err.min() + 1e-9)
    ax.add_collection(lc)
    ax.autoscale_view()
    fig.colorbar(lc, ax=ax, label="APE (translation) [m]")
    ax.set_title("Estimate coloured by APE")
    ax.legend(loc="best")
    return _save(fig, path)


def _rpy_deg(poses: np.ndarray) -> np.ndarray:
    """(N,3) roll, pitch, yaw in degrees (ZYX Euler), yaw unwrapped."""
    ypr = Rotation.from_matrix(poses[:, :3, :3]).as_euler("ZYX")
    rpy = np.unwrap(ypr[:, ::-1], axis=0)
    return np.degrees(rpy)


def plot_rpy(result: EvalResult, path: Path) -> Path:
    """Roll, pitch and yaw of estimate and ground truth over time."""
    fig, axes = _figure(3, 1, size=(9.0, 7.5), sharex=True)
    t = _seconds(result)
    gt, est = _rpy_deg(result.gt_poses), _rpy_deg(result.est_poses)
    est += 360.0 * np.round((gt - est) / 360.0)  # same branch as the ground truth
    for k, name in enumerate(("roll", "pitch", "yaw")):
        ax = axes[k, 0]
        ax.plot(t, gt[:, k], **GT_STYLE)
        ax.plot(t, est[:, k], **EST_STYLE)
        ax.set_ylabel(f"{name} [deg]")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(loc="best")
    axes[0, 0].set_title("Orientation over time")
    axes[-1, 0].set_xlabel("time [s]")
    return _save(fig, path)


def _speed(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dt = np.diff(stamps)
    dp = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    ok = dt > 0
    return stamps[1:][ok] - stamps[0], dp[ok] / dt[ok]


def plot_speed(result: EvalResult, path: Path) -> Path:
    """Speed (m/s) from consecutive matched poses of estimate and ground truth."""
    fig, ax = _figure(size=(9.0, 4.5))
    ax = ax[0, 0]
    t, v = _speed(result.stamps, result.gt_poses)
    ax.plot(t, v, **GT_STYLE)
    t, v = _speed(result.stamps, result.est_poses)
    ax.plot(t, v, **EST_STYLE)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("speed [m/s]")
    ax.set_title("Speed over time")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    return _save(fig, path)


def _loop_segments(
    result: EvalResult,
    loops: Sequence[tuple[int, int]] | None,
    loop_positions: Sequence[np.ndarray] | None,
) -> np.ndarray:
    """(M,2,3) aligned loop edge end points from index pairs and/or position pairs."""
    segs = []
    n = result.est_full.shape[0]
    for a, b in loops or ():
        if not (0 <= a < n and 0 <= b < n):
            raise InputError(f"loop ({a}, {b}) indexes outside the {n} estimate poses")
        segs.append(result.est_full[[a, b], :3, 3])
    A = result.alignment
    for pair in loop_positions or ():
        p = np.asarray(pair, dtype=float)
        if p.shape != (2, 3):
            raise InputError(f"loop positions must be (2,3) arrays, got {p.shape}")
        segs.append(p @ A[:3, :3].T + A[:3, 3])
    return np.asarray(segs, dtype=float).reshape(-1, 2, 3)


def plot_loops(result: EvalResult, path: Path, segments: np.ndarray, plane: str = "xy") -> Path:
    """Estimated trajectory with loop-closure edges (red)."""
    fig, ax = _figure()
    ax = ax[0, 0]
    i, j = _view(ax, plane)
    gt, est = result.gt_poses[:, :3, 3], result.est_full[:, :3, 3]
    ax.plot(gt[:, i], gt[:, j], **GT_STYLE)
    ax.plot(est[:, i], est[:, j], **EST_STYLE)
    lc = LineCollection(segments[:, :, [i, j]], colors="tab:red", linewidths=1.5,
                        label=f"loop closures ({len(segments)})")  # fmt: skip
    ax.add_collection(lc)
    ax.plot(segments[:, :, i].ravel(), segments[:, :, j].ravel(), ".", color="tab:red")
    ax.set_title("Loop closures")
    ax.legend(loc="best")
    return _save(fig, path)


def plot_overlay(results: Mapping[str, EvalResult], path: Path, plane: str = "xy") -> Path:
    """Several estimates (aligned) over the ground truth of the first one."""
    fig, ax = _figure()
    ax = ax[0, 0]
    i, j = _view(ax, plane)
    first = next(iter(results.values()))
    gt = first.gt_poses[:, :3, 3]
    ax.plot(gt[:, i], gt[:, j], **GT_STYLE)
    for name, res in results.items():
        est = res.est_poses[:, :3, 3]
        rmse = res.ape_trans["rmse"]
        ax.plot(est[:, i], est[:, j], linewidth=1.3, label=f"{name} (RMSE {rmse:.3f} m)")
    ax.set_title(f"Trajectories ({plane.upper()})")
    ax.legend(loc="best", fontsize="small")
    return _save(fig, path)


def plot_ape_overlay(results: Mapping[str, EvalResult], path: Path) -> Path:
    """APE over time of several estimates."""
    fig, ax = _figure(size=(9.0, 4.5))
    ax = ax[0, 0]
    for name, res in results.items():
        ax.plot(_seconds(res), res.ape_errors, linewidth=1.2, label=name)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("APE (translation) [m]")
    ax.set_title("Absolute pose error over time")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return _save(fig, path)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "run"


def _plot_one(result, out: Path, prefix: str, loops, loop_positions) -> list[Path]:
    segments = _loop_segments(result, loops, loop_positions)  # validate before drawing
    files = [
        plot_trajectory(result, out / f"{prefix}trajectory_xy.png", "xy"),
        plot_trajectory(result, out / f"{prefix}trajectory_xz.png", "xz"),
        plot_ape_over_time(result, out / f"{prefix}ape_over_time.png"),
        plot_error_heatmap(result, out / f"{prefix}ape_heatmap.png"),
        plot_rpy(result, out / f"{prefix}rpy.png"),
        plot_speed(result, out / f"{prefix}speed.png"),
    ]
    if loops is not None or loop_positions is not None:
        files.append(plot_loops(result, out / f"{prefix}loops.png", segments))
    return files


def plot_all(
    result: EvalResult | Mapping[str, EvalResult],
    out_dir: str | Path,
    *,
    loops: Sequence[tuple[int, int]] | Mapping[str, Sequence[tuple[int, int]]] | None = None,
    loop_positions: Sequence[np.ndarray] | Mapping[str, Sequence[np.ndarray]] | None = None,
    prefix: str = "",
    per_result: bool = True,
) -> list[Path]:
    """Write every plot of one result (or of several, plus overlays) into ``out_dir``.

    Per result: ``trajectory_xy``, ``trajectory_xz``, ``ape_over_time``, ``ape_heatmap``,
    ``rpy``, ``speed`` and, when loops are given, ``loops`` (``.png``). ``loops`` are
    (i, j) row indices of the input estimate (one pose per scan); ``loop_positions`` are
    (2,3) end points in the estimate's frame (the result's alignment is applied). For a
    dict of results files are prefixed with the name, loops may be a dict by name, and
    ``overlay_xy.png``/``overlay_xz.png``/``ape_overlay.png`` are added
    (``per_result=False``: only those overlays).
    Returns the written paths in that order.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(result, EvalResult):
        if isinstance(loops, Mapping) or isinstance(loop_positions, Mapping):
            raise InputError("loops by name need a dict of results")
        return _plot_one(result, out, prefix, loops, loop_positions)
    if not isinstance(result, Mapping) or not result:
        raise InputError("plot_all needs an EvalResult or a non-empty dict of them")
    if (loops is not None and not isinstance(loops, Mapping)) or (
        loop_positions is not None and not isinstance(loop_positions, Mapping)
    ):
        raise InputError("for a dict of results give loops as a dict {name: loops}")
    for name, res in result.items():
        if not isinstance(res, EvalResult):
            raise InputError(f"result {name!r} is {type(res).__name__}, not an EvalResult")
    if per_result:  # validate every loop list before the first (slow) drawing
        for name, res in result.items():
            lp = loops.get(name) if isinstance(loops, Mapping) else None
            pp = loop_positions.get(name) if isinstance(loop_positions, Mapping) else None
            _loop_segments(res, lp, pp)
    files = [
        plot_overlay(result, out / f"{prefix}overlay_xy.png", "xy"),
        plot_overlay(result, out / f"{prefix}overlay_xz.png", "xz"),
        plot_ape_overlay(result, out / f"{prefix}ape_overlay.png"),
    ]
    for name, res in result.items() if per_result else ():
        lp = loops.get(name) if isinstance(loops, Mapping) else None
        pp = loop_positions.get(name) if isinstance(loop_positions, Mapping) else None
        files += _plot_one(res, out, f"{prefix}{_safe(name)}_", lp, pp)
    return files
