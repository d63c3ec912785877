"""Lines of a 2D cloud's cell means as a PLICP reference (the visit graph's loop search and
its final refinement register against them)."""

from __future__ import annotations

import numpy as np

from slam.features.lines2d import LineConfig, extract_lines
from slam.registration.plicp import LineReference


def line_reference(pts: np.ndarray, resolution: float) -> tuple[LineReference | None, np.ndarray]:
    """Lines of a cloud's cell means (``resolution``) as a PLICP reference (None when too
    small), and for each of its points (one per cell) the index of a point of ``pts`` in
    that cell."""
    if len(pts) < 20:
        return None, np.zeros(0, dtype=np.int64)
    cells = np.floor(pts / resolution).astype(np.int64)
    _, first, inverse = np.unique(cells, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    count = np.bincount(inverse)
    mean = np.column_stack([np.bincount(inverse, pts[:, d]) / count for d in range(2)])
    lines = extract_lines(mean, resolution, LineConfig(), count.astype(float))
    return LineReference.from_lines(lines), first
