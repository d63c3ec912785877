"""Evaluation plots saved as PNG files, drawn by ``evo.tools.plot``.

evo draws what it knows: trajectories against ground truth (``plot.traj``,
``plot.trajectories``), the estimate colour-mapped by its APE (``plot.traj_colormap``),
x/y/z and roll/pitch/yaw over time (``plot.traj_xyz``/``plot.traj_rpy``), speed
(``plot.speeds``), APE over time with its statistics (``plot.error_array``) and the
loop-closure edges (``plot.draw_correspondence_edges``). This module only adds titles, the
loop legend and the file names.

evo's plot module reads its settings from ``~/.evo/settings.json`` (and creates them on
first import, which is why the tests give every process its own ``HOME``); the plots follow
those settings (colour map, seaborn style, Euler sequence) except the backend, which is
always the non-interactive Agg: no window ever opens. Figures are closed once written.
Lengths in metres, angles in degrees, time in seconds from the first matched pose.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import ModuleType

import numpy as np

from slam.errors import InputError
from slam.eval.metrics import EvalResult

DPI = 100
TRAJ_SIZE = (8.0, 7.0)  # inches: 800 x 700 px
TIME_SIZE = (9.0, 4.5)  # 900 x 450 px
STACK_SIZE = (9.0, 7.5)  # three stacked time plots, 900 x 750 px
GT_LABEL, EST_LABEL = "ground truth", "estimate"
GT_STYLE = {"style": "--", "color": "gray"}
EST_COLOR = "tab:blue"
APE_STATS = ("rmse", "mean", "median", "std")
PLANES = ("xy", "xz")


def evo_plot() -> ModuleType:
    """``evo.tools.plot``, imported on first use with the Agg backend.

    evo applies its settings (``mpl.use(plot_backend)``, seaborn style) when the module is
    imported; the backend is set to Agg before that, and switched to Agg if evo was
    imported elsewhere with another one. evo's "Initialized new ~/.evo" line is swallowed.
    """
    if "evo.tools.plot" not in sys.modules:
        with contextlib.redirect_stdout(io.StringIO()):
            from evo.tools.settings import SETTINGS

            SETTINGS.plot_backend = "agg"
            from evo.tools import plot  # noqa: F401  (applies SETTINGS once)
    import matplotlib
    import matplotlib.pyplot as plt
    from evo.tools import plot

    if matplotlib.get_backend().lower() != "agg":
        plt.switch_backend("agg")
    return plot


def _figure(size: tuple[float, float]):
    import matplotlib.pyplot as plt

    return plt.figure(figsize=size, dpi=DPI)


def save_png(fig, path: Path) -> Path:
    """Write ``fig`` as a PNG of exactly its size (figsize x DPI pixels), then close it."""
    import matplotlib
    import matplotlib.pyplot as plt

    try:  # evo sets savefig.bbox=tight, which would crop to a data-dependent size
        with matplotlib.rc_context({"savefig.bbox": "standard"}):
            fig.savefig(path, format="png", dpi=DPI)
    finally:
        plt.close(fig)
    return path


def _traj(stamps: np.ndarray, poses: np.ndarray, name: str = ""):
    from evo.core.trajectory import PoseTrajectory3D

    return PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps, name=name)


def _gt_est(result: EvalResult):
    return _traj(result.stamps, result.gt_poses, GT_LABEL), _traj(
        result.stamps, result.est_poses, EST_LABEL
    )


def _mode(plane: str):
    plot = evo_plot()
    if plane not in plot.PlotMode.__members__:
        raise InputError(
            f"plot plane must be one of {list(plot.PlotMode.__members__)}, got {plane!r}"
        )
    return plot.PlotMode[plane]


def _fit_box(ax, plane: str) -> None:
    """Fill the axes box: true proportions in the ground plane (the limits grow, as
    ``adjustable="datalim"``), stretched heights in vertical planes, where evo's equal
    aspect would squash a drive's few metres of height into a line."""
    if "z" in plane:
        ax.set_aspect("auto")
        ax.set_title(f"{ax.get_title()} (height stretched)")
    else:
        ax.set_aspect("equal", adjustable="datalim")


def trajectory_figure(result: EvalResult, plane: str = "xy"):
    """Aligned estimate (with start/end markers) over the dashed ground truth."""
    plot, mode = evo_plot(), _mode(plane)
    fig = _figure(TRAJ_SIZE)
    ax = plot.prepare_axis(fig, mode)
    gt, est = _gt_est(result)
    plot.traj(ax, mode, gt, label=GT_LABEL, **GT_STYLE)
    plot.traj(ax, mode, est, "-", EST_COLOR, EST_LABEL, plot_start_end_markers=True)
    ax.set_title(f"Trajectory ({plane}), {result.options.align} alignment")
    _fit_box(ax, plane)
    return fig


def ape_colormap_figure(result: EvalResult, plane: str = "xy"):
    """Estimate coloured by its translational APE (m) per pose, ground truth dashed."""
    plot, mode = evo_plot(), _mode(plane)
    fig = _figure(TRAJ_SIZE)
    ax = plot.prepare_axis(fig, mode)
    gt, est = _gt_est(result)
    plot.traj(ax, mode, gt, label=GT_LABEL, **GT_STYLE)
    err = result.ape_errors
    lo, hi = float(err.min()), float(err.max())
    plot.traj_colormap(ax, est, err, mode, min_map=lo, max_map=max(hi, lo + 1e-9),
                       title="Estimate coloured by APE (translation, m)", fig=fig)  # fmt: skip
    _fit_box(ax, plane)
    return fig


def ape_figure(result: EvalResult):
    """Translational APE per pose with its RMSE, mean, median and std (evo's band)."""
    plot = evo_plot()
    fig = _figure(TIME_SIZE)
    ax = fig.add_subplot(111)
    stats = {k: result.ape_trans[k] for k in APE_STATS}
    plot.error_array(ax, result.ape_errors, x_array=result.stamps - result.stamps[0],
                     statistics=stats, name="APE", title="Absolute pose error over time",
                     xlabel="$t$ (s)", ylabel="APE (translation, m)")  # fmt: skip
    ax.set_ylim(0.0, 1.25 * float(result.ape_errors.max()) or 1.0)  # headroom for the legend
    ax.legend(loc="upper center", ncol=len(APE_STATS) + 1, frameon=True)
    return fig


def _stacked(result: EvalResult, draw: Callable, title: str):
    fig = _figure(STACK_SIZE)
    axes = fig.subplots(3, 1, sharex=True)
    gt, est = _gt_est(result)
    t0 = float(result.stamps[0])
    draw(axes, gt, label=GT_LABEL, start_timestamp=t0, **GT_STYLE)
    draw(axes, est, "-", EST_COLOR, EST_LABEL, start_timestamp=t0)
    axes[0].set_title(title)
    return fig


def xyz_figure(result: EvalResult):
    """x, y, z (m) of estimate and ground truth over time."""
    return _stacked(result, evo_plot().traj_xyz, "Position over time")


def rpy_figure(result: EvalResult):
    """Roll, pitch, yaw (deg, evo's ``euler_angle_sequence``) of both over time.

    evo draws the angles wrapped to (-180, 180]; a drive that heads near +-180 deg then
    flickers between the two ends. Each angle is unwrapped after drawing, the estimate on
    the ground truth's branch (the nearest multiple of 360 deg per pose).
    """
    fig = _stacked(result, evo_plot().traj_rpy, "Orientation over time (unwrapped)")
    for ax in fig.axes:
        lines = {line.get_label(): line for line in ax.get_lines()}
        gt, est = lines[GT_LABEL], lines[EST_LABEL]
        gt_deg = np.degrees(np.unwrap(np.radians(gt.get_ydata())))
        est_deg = np.asarray(est.get_ydata(), dtype=float)
        gt.set_ydata(gt_deg)
        est.set_ydata(est_deg + 360.0 * np.round((gt_deg - est_deg) / 360.0))
        ax.relim()
        ax.autoscale_view()
    return fig


def speed_figure(result: EvalResult):
    """Speed (m/s) between consecutive matched poses of estimate and ground truth."""
    plot = evo_plot()
    fig = _figure(TIME_SIZE)
    ax = fig.add_subplot(111)
    gt, est = _gt_est(result)
    t0 = float(result.stamps[0])
    plot.speeds(ax, gt, label=GT_LABEL, start_timestamp=t0, **GT_STYLE)
    plot.speeds(ax, est, "-", EST_COLOR, EST_LABEL, start_timestamp=t0)
    ax.set_title("Speed over time")
    return fig


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


def loops_figure(result: EvalResult, segments: np.ndarray, plane: str = "xy"):
    """Whole aligned estimate over the ground truth with the loop-closure edges (red)."""
    from evo.core.trajectory import PosePath3D

    plot, mode = evo_plot(), _mode(plane)
    fig = _figure(TRAJ_SIZE)
    ax = plot.prepare_axis(fig, mode)
    gt = _traj(result.stamps, result.gt_poses)
    plot.traj(ax, mode, gt, label=GT_LABEL, **GT_STYLE)
    plot.traj(ax, mode, PosePath3D(poses_se3=list(result.est_full)), "-", EST_COLOR, EST_LABEL)
    if len(segments):
        quat = np.tile([1.0, 0.0, 0.0, 0.0], (len(segments), 1))
        ends = [PosePath3D(segments[:, k], quat) for k in (0, 1)]
        plot.draw_correspondence_edges(ax, *ends, mode, color="tab:red")
        ax.collections[-1].set_label(f"loop closures ({len(segments)})")
        ax.collections[-1].set_linewidth(1.5)
        ax.legend(frameon=True)
    ax.set_title("Loop closures")
    _fit_box(ax, plane)
    return fig


def _length(metres: float) -> str:
    """A length for a legend: centimetres below 0.1 m (1.2 cm, not 0.01 m), else metres."""
    return f"{100 * metres:.1f} cm" if abs(metres) < 0.1 else f"{metres:.2f} m"


def overlay_figure(results: Mapping[str, EvalResult], plane: str = "xy"):
    """Several aligned estimates (labelled with their APE RMSE) over the first ground truth."""
    plot, mode = evo_plot(), _mode(plane)
    fig = _figure(TRAJ_SIZE)
    ax = plot.prepare_axis(fig, mode)
    first = next(iter(results.values()))
    plot.traj(ax, mode, _traj(first.stamps, first.gt_poses), label=GT_LABEL, **GT_STYLE)
    named = {
        f"{name} (RMSE {res.ape_trans['rmse']:.3f} m)": _traj(res.stamps, res.est_poses)
        for name, res in results.items()
    }
    plot.trajectories(ax, named, mode, title=f"Trajectories ({plane})")
    _fit_box(ax, plane)
    return fig


def ape_overlay_figure(results: Mapping[str, EvalResult]):
    """Translational APE over time of several estimates, one colour each."""
    plot = evo_plot()
    fig = _figure(TIME_SIZE)
    ax = fig.add_subplot(111)
    for (name, res), color in zip(
        results.items(), itertools.cycle(plot.color_cycle()), strict=False
    ):
        plot.error_array(ax, res.ape_errors, x_array=res.stamps - res.stamps[0], color=color,
                         name=name, title="Absolute pose error over time", xlabel="$t$ (s)",
                         ylabel="APE (translation, m)")  # fmt: skip
    return fig


ODOM_COLOR, LOOP_EDGE_COLOR = "tab:orange", "tab:red"
TRIPLE_SIZE = (19.0, 6.5)  # three panels, 1900 x 650 px
RUNS = (("odometry only", ODOM_COLOR), ("loop closed", EST_COLOR))


def _pair_traj_axes(ax, odom: EvalResult, closed: EvalResult, segments: np.ndarray) -> None:
    """Ground truth (dashed), both aligned estimates and the loop edges on ``ax`` (xy)."""
    from matplotlib.collections import LineCollection

    gt = closed.gt_poses[:, :2, 3]
    ax.plot(gt[:, 0], gt[:, 1], "--", color="gray", label=GT_LABEL)
    for res, (name, color) in zip((odom, closed), RUNS, strict=True):
        xy = res.est_poses[:, :2, 3]
        ax.plot(xy[:, 0], xy[:, 1], "-", color=color,
                label=f"{name} (APE RMSE {_length(res.ape_trans['rmse'])})")  # fmt: skip
    if len(segments):
        edges = LineCollection(segments[:, :, :2], colors=LOOP_EDGE_COLOR, linewidths=1.5)
        edges.set_label(f"loop closures ({len(segments)})")
        ax.add_collection(edges)
    ax.set_xlabel("$x$ (m)")
    ax.set_ylabel("$y$ (m)")
    ax.grid(True, alpha=0.4)


def _travelled(res: EvalResult) -> np.ndarray:
    """Distance (m) along the ground truth at each matched pose."""
    step = np.linalg.norm(np.diff(res.gt_poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def _zoom_pose(odom: EvalResult, closed: EvalResult, segments: np.ndarray) -> tuple[int, str]:
    """The matched pose to zoom on: of the poses nearest the loop edges' midpoints, the one
    where the odometry is worst (a revisit: both passes in view); without loops the worst
    odometry pose."""
    n = min(odom.n_matched, closed.n_matched)
    if len(segments) and n:
        mids = segments[:, :, :2].mean(axis=1)
        xy = closed.est_poses[:n, :2, 3]
        near = np.linalg.norm(xy[None, :, :] - mids[:, None, :], axis=2).argmin(axis=1)
        return int(near[np.argmax(odom.ape_errors[near])]), "a revisit closed by a loop"
    return int(np.argmax(odom.ape_errors)), "the worst odometry pose"


def odometry_vs_loop_figure(
    odom: EvalResult, closed: EvalResult, loop_positions: Sequence[np.ndarray] | None = None
):
    """What loop closure did, in three panels: the odometry-only and the loop-closed
    estimates (each SE(3)-aligned to the ground truth on its own) over the dashed ground
    truth with the accepted loop edges (red, between loop-closed keyframe positions); the
    same zoomed on the pose where the odometry is worst (drift of a metre is invisible on a
    kilometre's drive); the translational APE of both along the distance travelled (m)."""
    import matplotlib.pyplot as plt

    evo_plot()  # the Agg backend and evo's style, as every figure here
    segments = _loop_segments(closed, None, loop_positions)
    fig = plt.figure(figsize=TRIPLE_SIZE, dpi=DPI, layout="constrained")
    axes = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.3, 1.0, 1.3]})
    for ax in axes[:2]:
        _pair_traj_axes(ax, odom, closed, segments)
    axes[0].legend(frameon=True, loc="best")
    axes[0].set_title("Odometry only vs loop closed over the ground truth")
    axes[0].set_aspect("equal", adjustable="datalim")
    worst, what = _zoom_pose(odom, closed, segments)
    centre = odom.gt_poses[worst, :2, 3]
    half = max(6.0, 3.0 * float(odom.ape_errors[worst]))
    axes[1].set_xlim(centre[0] - half, centre[0] + half)
    axes[1].set_ylim(centre[1] - half, centre[1] + half)
    axes[1].set_aspect("equal", adjustable="box")
    axes[1].set_title(f"Zoom: {2 * half:.0f} m around {what}")
    axes[1].plot(*centre, "o", color=ODOM_COLOR, mfc="none", ms=14)
    axes[2].axvline(_travelled(odom)[worst], color=ODOM_COLOR, lw=0.8, ls=":")
    for res, (name, color) in zip((odom, closed), RUNS, strict=True):
        axes[2].plot(_travelled(res), res.ape_errors, color=color, label=name)
    axes[2].set_xlabel("distance travelled (m)")
    axes[2].set_ylabel("APE (translation, m)")
    axes[2].set_ylim(bottom=0.0)
    axes[2].grid(True, alpha=0.4)
    axes[2].legend(frameon=True)
    axes[2].set_title("Absolute pose error along the drive")
    return fig


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "run"


def _plot_one(result, out: Path, prefix: str, loops, loop_positions) -> list[Path]:
    segments = _loop_segments(result, loops, loop_positions)  # validate before drawing
    figures = [(f"trajectory_{p}", lambda p=p: trajectory_figure(result, p)) for p in PLANES]
    figures += [
        ("ape_over_time", lambda: ape_figure(result)),
        ("ape_heatmap", lambda: ape_colormap_figure(result)),
        ("xyz", lambda: xyz_figure(result)),
        ("rpy", lambda: rpy_figure(result)),
        ("speed", lambda: speed_figure(result)),
    ]
    if loops is not None or loop_positions is not None:
        figures.append(("loops", lambda: loops_figure(result, segments)))
    return [save_png(make(), out / f"{prefix}{name}.png") for name, make in figures]


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
    ``xyz``, ``rpy``, ``speed`` and, when loops are given, ``loops`` (``.png``). ``loops``
    are (i, j) row indices of the input estimate (one pose per scan); ``loop_positions``
    are (2,3) end points in the estimate's frame (the result's alignment is applied). For a
    dict of results files are prefixed with the name, loops may be a dict by name, and
    ``overlay_xy.png``/``overlay_xz.png``/``ape_overlay.png`` are added
    (``per_result=False``: only those overlays).
    Returns the written paths in that order.
    """
    out = Path(out_dir)
    if isinstance(result, EvalResult):
        if isinstance(loops, Mapping) or isinstance(loop_positions, Mapping):
            raise InputError("loops by name need a dict of results")
        _loop_segments(result, loops, loop_positions)
        out.mkdir(parents=True, exist_ok=True)
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
    out.mkdir(parents=True, exist_ok=True)
    files = [save_png(overlay_figure(result, p), out / f"{prefix}overlay_{p}.png") for p in PLANES]
    files.append(save_png(ape_overlay_figure(result), out / f"{prefix}ape_overlay.png"))
    for name, res in result.items() if per_result else ():
        lp = loops.get(name) if isinstance(loops, Mapping) else None
        pp = loop_positions.get(name) if isinstance(loop_positions, Mapping) else None
        files += _plot_one(res, out, f"{prefix}{_safe(name)}_", lp, pp)
    return files
