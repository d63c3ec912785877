"""``Odometry.extras`` of the scan-to-map front ends: a flat copy of the typed diagnostics
for scripts written against earlier versions. The framework reads the typed fields."""

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
    """``d.flat()`` with the ground plane and the information before the slide test.

    Also completes ``d`` with the slide test's wall time ``ambiguity_ms`` when the test
    ran (``d.ambiguity_ms``), so that the typed diagnostics hold every number.
    """
    if d.ambiguity is not None and ambiguity_ms is not None:
        d.ambiguity_ms = ambiguity_ms
    out = d.flat()
    if ground_plane is not None:
        out["ground_plane"] = ground_plane
    if info_before_ambiguity is not None and d.ambiguity is not None:
        out["_info_before_ambiguity"] = info_before_ambiguity
    return out
