"""Local line features of raw 2D points: each reference point carries the line of its own
neighbourhood (total least squares over the points within a few cm), not a grid cell's
place on a long fitted wall. Point-to-line PLICP (``slam.registration.plicp``) on such a
reference is Censi's PLICP with a denoised local line: it follows a wall as the recent
scans saw it, bends and all, where a split-and-merge line over 5 cm cells (tolerance
6 cm) leaves a few cm of bias along a curved or cluttered wall.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError
from slam.registration.plicp import LineReference


@dataclass
class LocalLineConfig:
    """voxel (m): one point per cell of this size and scan (0: all); radius (m): the
    neighbourhood a point's line is fitted to; neighbours: at most this many points in
    it (the nearest); min_neighbours: fewer leave the point without a line
    (point-to-point); max_thickness (m): a neighbourhood whose RMS spread across its line
    exceeds this is a corner or clutter (no line)."""

    voxel: float = 0.05
    radius: float = 0.15
    neighbours: int = 8
    min_neighbours: int = 3
    max_thickness: float = 0.02

    def __post_init__(self) -> None:
        if not (self.radius > 0 and self.max_thickness > 0 and self.voxel >= 0):
            raise ConfigError("local lines: radius, max_thickness > 0 and voxel >= 0 required")
        if not 2 <= self.min_neighbours <= self.neighbours:
            raise ConfigError("local lines: 2 <= min_neighbours <= neighbours required")


def thin(xy: np.ndarray, voxel: float) -> np.ndarray:
    """One point per ``voxel`` cell (the first in scan order), (N, 2) m."""
    if voxel <= 0 or len(xy) == 0:
        return xy
    cells = np.floor(xy / voxel).astype(np.int64)
    key = (cells[:, 0] << 32) + (cells[:, 1] & 0xFFFFFFFF)  # one int64 per cell
    _, keep = np.unique(key, return_index=True)
    return xy[np.sort(keep)]


def local_lines(
    query: np.ndarray, cloud: np.ndarray, tree: cKDTree, cfg: LocalLineConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Each ``query`` point's (M, 2) local line among the ``cloud`` points (their
    ``tree``): (directions (M, 2) unit, the principal axis of its neighbourhood, NaN where
    the neighbourhood is too small or thick; anchors (M, 2), the neighbourhood's mean, the
    point itself where it has no line)."""
    directions = np.full_like(query, np.nan)
    anchors = query.copy()
    k = min(cfg.neighbours, len(cloud))
    if k < cfg.min_neighbours or not len(query):
        return directions, anchors
    dist, j = tree.query(query, k=k, distance_upper_bound=cfg.radius)
    dist, j = dist.reshape(len(query), k), j.reshape(len(query), k)
    valid = np.isfinite(dist)
    count = valid.sum(axis=1)
    nb = cloud[np.where(valid, j, 0)]  # (M, k, 2)
    w = valid[..., None].astype(np.float64)
    n = np.maximum(count, 1)
    mean = (nb * w).sum(axis=1) / n[:, None]
    dev = (nb - mean[:, None, :]) * w
    a = np.einsum("mk,mk->m", dev[..., 0], dev[..., 0]) / n
    b = np.einsum("mk,mk->m", dev[..., 0], dev[..., 1]) / n
    c = np.einsum("mk,mk->m", dev[..., 1], dev[..., 1]) / n
    spread = np.sqrt(0.25 * (a - c) ** 2 + b**2)
    across = 0.5 * (a + c) - spread  # the smaller eigenvalue: variance across the line
    angle = 0.5 * np.arctan2(2.0 * b, a - c)  # the principal axis
    line = (count >= cfg.min_neighbours) & (across <= cfg.max_thickness**2)
    directions[line] = np.column_stack([np.cos(angle[line]), np.sin(angle[line])])
    anchors[line] = mean[line]
    return directions, anchors


def local_line_reference(points: np.ndarray, cfg: LocalLineConfig | None = None) -> LineReference:
    """The :class:`LineReference` of ``points`` (M, 2), each with its local line
    (:func:`local_lines` among the points themselves)."""
    cfg = cfg or LocalLineConfig()
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    tree = cKDTree(points)
    directions, anchors = local_lines(points, points, tree, cfg)
    return LineReference(points, directions, anchors, tree)
