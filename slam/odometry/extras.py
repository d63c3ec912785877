"""The flat ``Odometry.extras`` dict the pipeline reads, made from the typed diagnostics."""

from __future__ import annotations

from typing import Any

import numpy as np

from slam.types import OdometryDiagnostics


def legacy_extras(
    d: OdometryDiagnostics,
    ground_plane: np.ndarray | None = None,
    info_before_ambiguity: np.ndarray | None = None,
    ambiguity_ms: float | None = None,
) -> dict[str, Any]:
    """``d`` as the flat dict of earlier versions: the 0/1 counters as ints, the reasons
    under ``lost`` / ``skipped``, the front end's counts, the timings last."""
    out: dict[str, Any] = {
        "n_points": d.n_points,
        "rejected": int(d.rejected),
        "recovered": int(d.recovered),
        "map_skipped": int(d.map_skipped),
        "reinitialised": int(d.reinitialised),
        "n_after_crop": d.n_after_crop,
    }
    if d.gap_hypotheses:
        out["gap_hypotheses"] = d.gap_hypotheses
    if d.start_hypotheses:
        out["start_hypotheses"] = d.start_hypotheses
    out.update(d.counts)
    if ground_plane is not None:
        out["ground_plane"] = ground_plane
    if d.registration is not None:
        r = d.registration
        out.update(
            iterations=r.iterations,
            fitness=r.fitness,
            converged=r.converged,
            inliers=r.inliers,
            inlier_ratio=r.inlier_ratio,
        )
    if d.lost is not None:
        out["lost"] = d.lost
    out["tracking_lost"] = int(d.tracking_lost)
    out["map_points"] = d.map_points
    if d.min_info_eigenvalue is not None:
        out["min_info_eigenvalue"] = d.min_info_eigenvalue
    out["ambiguous"] = int(d.ambiguous)
    if d.ambiguity is not None:
        out["ambiguity"] = d.ambiguity
        out["ambiguity_axis_x"], out["ambiguity_axis_y"] = d.ambiguity_axis
        if info_before_ambiguity is not None:
            out["_info_before_ambiguity"] = info_before_ambiguity
        out["ambiguity_ms"] = ambiguity_ms
    out["degenerate"] = bool(d.degenerate)
    if d.skipped is not None:
        out["skipped"] = d.skipped
    out.update(d.timings_ms)
    return out
