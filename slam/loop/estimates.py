"""What the loop closure reads of the graph: pose estimates and keyframe clouds."""

from __future__ import annotations

import numpy as np

from slam.errors import InputError
from slam.factors import GraphView
from slam.types import Keyframe


def estimate_of(graph: GraphView, kf_id: int) -> np.ndarray:
    """T_world_sensor (4x4) of keyframe ``kf_id`` from the back end."""
    return np.asarray(graph.estimate(kf_id), dtype=np.float64)


def current_estimate(graph: GraphView, kf: Keyframe) -> np.ndarray:
    """T_world_sensor of the current keyframe: the back end's estimate if it has one,
    else the previous keyframe's estimate composed with the odometry relative motion."""
    try:
        return estimate_of(graph, kf.id)
    except (KeyError, IndexError, RuntimeError):
        if kf.id == 0:
            return np.asarray(kf.pose_odom, dtype=np.float64)
        return estimate_of(graph, kf.id - 1) @ np.asarray(kf.relative, dtype=float)


def keyframe_cloud(graph: GraphView, kf_id: int) -> np.ndarray:
    """Sensor-frame cloud of keyframe ``kf_id``: the pipeline's copy, never one of our own
    (verification voxelises it itself)."""
    kfs = graph.keyframes
    if not 0 <= kf_id < len(kfs) or kfs[kf_id].id != kf_id:
        raise InputError(
            f"loop closure: keyframe {kf_id} is not in the graph view "
            f"({len(kfs)} keyframes): the view must list keyframes by id"
        )
    return kfs[kf_id].cloud


def local_cloud(graph: GraphView, kf_id: int, T_w_center: np.ndarray, n: int) -> np.ndarray:
    """The keyframe's stored cloud merged with its +-``n`` neighbours (those already seen),
    transformed into its sensor frame by the current estimates."""
    parts = [np.asarray(keyframe_cloud(graph, kf_id), dtype=np.float64)[:, :3]]
    if n > 0:
        T_c_w = np.linalg.inv(T_w_center)
        for j in range(max(kf_id - n, 0), min(kf_id + n + 1, len(graph.keyframes))):
            if j == kf_id:
                continue
            T = T_c_w @ estimate_of(graph, j)
            cloud = np.asarray(keyframe_cloud(graph, j), dtype=np.float64)[:, :3]
            parts.append(cloud @ T[:3, :3].T + T[:3, 3])
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)
