"""Writing the files of a run (names fixed by DESIGN.md; scripts rely on them)."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from slam.io.trajectory import write_kitti, write_tum
from slam.state import peak_memory_mb
from slam.system import SlamSystem

log = logging.getLogger(__name__)

TRAJECTORY_TUM = "trajectory.tum"
TRAJECTORY_KITTI = "trajectory.kitti"
ODOMETRY_TUM = "odometry.tum"
MAP_PCD = "map.pcd"
GRAPH_G2O = "graph.g2o"
METRICS_JSON = "metrics.json"
CONFIG_YAML = "config.yaml"
LOOPS_CSV = "loops.csv"
REPORT_HTML = "report.html"
APE_JSON = "ape.json"
# 0/1 per-frame flags of the scan-to-map front ends (frontends/common.py)
TRACKING_COUNTERS = ("rejected", "tracking_lost", "recovered", "reinitialised")


def build_map(system: SlamSystem, voxel: float | None = None) -> np.ndarray:
    """The map (M, 3) m in the world frame: voxel centroids (cell ``voxel`` m, default
    ``output.map_voxel``; <= 0 keeps every point) of the keyframe clouds placed by their
    optimised poses, streamed keyframe by keyframe into a :class:`VoxelCentroidMap` (memory
    bounded by the occupied voxels, not by the sum of the clouds)."""
    return map_accumulator(system, voxel).centroids()


def map_accumulator(system: SlamSystem, voxel: float | None = None) -> Any:
    """The :class:`slam.io.maps.VoxelCentroidMap` of the run (see :func:`build_map`)."""
    from slam.io.maps import VoxelCentroidMap

    st = system.state
    acc = VoxelCentroidMap(system.config.output.map_voxel if voxel is None else voxel)
    for kf in st.keyframes:
        if kf.cloud is not None and len(kf.cloud):
            acc.add_transformed(kf.cloud, st.estimates.get(kf.id, kf.pose_odom))
    if acc.dropped:
        log.warning("map: %d points beyond the voxel key range dropped", acc.dropped)
    return acc


def _window_mean_ms(seconds: Any, first: bool, n: int = 100) -> float | None:
    """Mean (ms) of the first or last ``n`` entries of a per-frame time series."""
    values = np.asarray(seconds, dtype=float)
    if len(values) == 0:
        return None
    part = values[:n] if first else values[-n:]
    return round(1e3 * float(part.mean()), 3)


def stage_window_ms(
    system: SlamSystem, first: bool, n: int = 100, cpu: bool = False
) -> dict[str, float]:
    """Mean ms per frame of every stage over the first or last ``n`` frames (a stage that did
    not run on a frame counts 0 there), plus ``other``: the rest of the frame's step (the
    system's own bookkeeping). Compared start vs end, it shows which stage grows.
    ``cpu``: CPU ms of this process instead of wall ms."""
    st = system.state
    out: dict[str, float] = {}
    frames = np.asarray(st.frame_cpu_seconds if cpu else st.frame_seconds, dtype=float)
    if len(frames) == 0:
        return out
    rest = frames.copy()
    stages = st.stage_frame_cpu_seconds if cpu else st.stage_frame_seconds
    for stage, series in stages.items():
        values = np.asarray(series, dtype=float)
        out[stage] = _window_mean_ms(values, first, n)
        m = min(len(values), len(rest))
        rest[:m] -= values[:m]
    out["other"] = _window_mean_ms(rest, first, n)
    return out


def plugin_stats(system: SlamSystem) -> dict[str, Any]:
    """``stats()`` of every factor plugin that has one (a failing one is left out)."""
    out: dict[str, Any] = {}
    for source in system.factor_sources:
        stats = getattr(source.plugin, "stats", None)
        if callable(stats):
            try:
                out[source.name] = {
                    k: round(float(v), 4) if isinstance(v, (float, np.floating)) else v
                    for k, v in dict(stats()).items()
                }
            except Exception as exc:  # noqa: BLE001 - diagnostics must not lose the run
                log.warning("factor plugin %s: stats() failed: %s", source.name, exc)
    return out


def memory_per_km(system: SlamSystem) -> float | None:
    """Growth of the peak memory (MiB) per km travelled since the reference frame (100):
    what a longer drive adds; None before 100 m beyond it."""
    st = system.state
    if st.memory_reference is None:
        return None
    peak0, path0 = st.memory_reference
    km = (st.path_length - path0) / 1000.0
    return round((peak_memory_mb() - peak0) / km, 1) if km >= 0.1 else None


def keyframe_cloud_mb(system: SlamSystem) -> float:
    """MiB held by the stored keyframe clouds."""
    return sum(kf.cloud.nbytes for kf in system.state.keyframes) / 2**20


def write_trajectories(
    system: SlamSystem,
    out: Path,
    to_output: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> list[Path]:
    """trajectory.tum / .kitti and odometry.tum. ``to_output(stamps, poses)``: the input's
    convention for the files (a CARMEN log: the robot's poses at the log's own stamps,
    ``CarmenSource.output_trajectory``); None: the run's stamps and sensor poses."""
    st = system.state
    if st.frames == 0:
        return []
    stamps = np.asarray(st.stamps)
    traj, odom = st.trajectory(), np.stack(st.odom_poses)
    if to_output is not None:
        _, odom = to_output(stamps, odom)
        stamps, traj = to_output(stamps, traj)
    write_tum(out / TRAJECTORY_TUM, stamps, traj)
    write_kitti(out / TRAJECTORY_KITTI, traj)
    write_tum(out / ODOMETRY_TUM, stamps, odom)
    return [out / TRAJECTORY_TUM, out / TRAJECTORY_KITTI, out / ODOMETRY_TUM]


def metrics(system: SlamSystem, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Counts, timings and memory of a run (metrics.json)."""
    st = system.state
    fe = st.stage_seconds.get("frontend", 0.0)
    return {
        "frames": st.frames,
        "keyframes": len(st.keyframes),
        "skipped_frames": st.skipped_frames,
        "skipped_messages": dict(sorted(st.skipped_messages.items())),
        "messages_skipped": st.messages_skipped,
        # frames (counts) with each per-frame tracking flag the front end reports
        "frontend_counts": {
            k: int(round(st.diagnostic_sums.get(k, 0.0))) for k in TRACKING_COUNTERS
        },
        "degenerate_frames": st.degenerate_frames,
        "loops_closed": st.loops_closed,
        "factors": dict(st.factor_counts),
        "seconds": {k: round(v, 4) for k, v in st.stage_seconds.items()},
        # the slowest single call per stage (ms): front end per frame, each factor plugin
        # and the back end per keyframe
        "stage_ms_max": {k: round(1e3 * v, 3) for k, v in st.stage_max_seconds.items()},
        # per-frame wall time of the whole system step, start vs end of the run (ms)
        "frame_ms_first100": _window_mean_ms(st.frame_seconds, first=True),
        "frame_ms_last100": _window_mean_ms(st.frame_seconds, first=False),
        "frame_ms_max": round(1e3 * max(st.frame_seconds), 3) if st.frame_seconds else None,
        # CPU ms of this process per frame (start vs end): independent of the machine's load
        "frame_cpu_ms_first100": _window_mean_ms(st.frame_cpu_seconds, first=True),
        "frame_cpu_ms_last100": _window_mean_ms(st.frame_cpu_seconds, first=False),
        # the same split by stage (ms per frame; "other": the system's own bookkeeping)
        "stage_ms_first100": stage_window_ms(system, first=True),
        "stage_ms_last100": stage_window_ms(system, first=False),
        "stage_cpu_ms_first100": stage_window_ms(system, first=True, cpu=True),
        "stage_cpu_ms_last100": stage_window_ms(system, first=False, cpu=True),
        # back-end update per keyframe (ms): mean over the first / last 100 keyframes, max
        "backend_ms_first100": _window_mean_ms(st.backend_seconds, first=True),
        "backend_ms_last100": _window_mean_ms(st.backend_seconds, first=False),
        "backend_ms_max": (round(1e3 * max(st.backend_seconds), 3) if st.backend_seconds else None),
        "path_length_m": round(st.path_length, 2),
        "keyframe_cloud_mb": round(keyframe_cloud_mb(system), 2),
        "wall_seconds": round(st.wall_seconds, 3),
        "frames_per_second": round(st.frames / st.wall_seconds, 2) if st.wall_seconds else None,
        "frontend_frames_per_second": round(st.frames / fe, 2) if fe else None,
        "peak_memory_mb": round(peak_memory_mb(), 1),
        "memory_mb_per_km": memory_per_km(system),
        "frontend_means": {k: round(v, 4) for k, v in sorted(st.diagnostic_means().items())},
        "stopped_by": st.stopped_by,
        "sensor": st.sensor,
        # each factor plugin's own counts and timings (``stats()``, e.g. the loop plugin's
        # detect/verify ms), by the name it was configured under
        "factor_stats": plugin_stats(system),
        # the back end's own (e.g. the region graph's optimisations and their ms)
        "backend_stats": (
            system.backend.stats() if callable(getattr(system.backend, "stats", None)) else {}
        ),
        **(extra or {}),
    }


def write_outputs(
    system: SlamSystem,
    out: Path,
    *,
    resolved_config: dict[str, Any],
    extra_metrics: dict[str, Any] | None = None,
    to_output: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> dict[str, Path]:
    """Write every output of a run; each file is attempted even if another fails.
    ``to_output``: see :func:`write_trajectories`."""
    import yaml

    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    (out / CONFIG_YAML).write_text(yaml.safe_dump(resolved_config, sort_keys=False))
    written["config"] = out / CONFIG_YAML
    for path in write_trajectories(system, out, to_output):
        written[path.name] = path
    st = system.state
    if system.config.output.write_map and st.keyframes:
        try:
            name = MAP_PCD if system.config.output.map_format == "pcd" else "map.ply"
            with st.timer("map"):
                n_map = map_accumulator(system).write(out / name)
            written["map"] = out / name
            extra_metrics = {**(extra_metrics or {}), "map_points": n_map}
        except Exception as exc:  # noqa: BLE001 - a failed map must not lose the trajectories
            log.warning("map not written: %s", exc)
    if st.keyframes:
        try:
            from slam.factors import pose3
            from slam.pose_graph import values_from_poses, write_g2o

            optimised = {k: pose3(T) for k, T in st.estimates.items()}
            write_g2o(out / GRAPH_G2O, system.backend.graph(), values_from_poses(optimised))
            written["graph"] = out / GRAPH_G2O
        except Exception as exc:  # noqa: BLE001
            log.warning("pose graph not written: %s", exc)
    for source in system.factor_sources:
        if hasattr(source.plugin, "write_csv"):
            source.plugin.write_csv(out / LOOPS_CSV)
            written["loops"] = out / LOOPS_CSV
    (out / METRICS_JSON).write_text(json.dumps(metrics(system, extra_metrics), indent=2))
    written["metrics"] = out / METRICS_JSON
    return written
