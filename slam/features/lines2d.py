"""Line features of a 2D occupancy grid (paper 003 uses RM-Line; this is a split-and-merge
over the grid's obstacle cells): connected obstacle cells are split recursively at the
cell farthest from their total-least-squares line until every piece is straight within a
tolerance; pieces too short or with too few cells carry no line.

Each obstacle point then knows the direction of the line feature it lies on, which is
what the improved PLICP (``slam.registration.plicp``) matches against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from slam.errors import ConfigError


@dataclass
class LineConfig:
    """tolerance: largest distance (m) of a cell centre from its line; min_cells: fewest
    cells of a line; min_length: shortest line (m); gap: cells farther apart than this
    along a line (m) split it (doorways, pillars)."""

    tolerance: float = 0.06
    min_cells: int = 6
    min_length: float = 0.25
    gap: float = 0.3

    def __post_init__(self) -> None:
        if not (self.tolerance > 0 and self.min_cells >= 2 and self.gap > 0):
            raise ConfigError("lines: tolerance and gap must be > 0, min_cells >= 2")


@dataclass
class LineSet:
    """points (M, 2): the obstacle points; label (M,): line index or -1; centre (L, 2),
    direction (L, 2) unit, normal (L, 2) unit, ends (L, 2, 2), count (L,)."""

    points: np.ndarray
    label: np.ndarray
    centre: np.ndarray
    direction: np.ndarray
    ends: np.ndarray
    count: np.ndarray

    def __len__(self) -> int:
        return len(self.centre)

    def point_directions(self) -> np.ndarray:
        """(M, 2) unit direction of each point's line; NaN for points on no line."""
        out = np.full((len(self.points), 2), np.nan)
        on = self.label >= 0
        out[on] = self.direction[self.label[on]]
        return out


def fit_line(
    xy: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Weighted) total least squares: centre (2,), unit direction (2,), |distances| (N,)
    of ``xy``."""
    w = np.ones(len(xy)) if weights is None else weights
    c = (w[:, None] * xy).sum(axis=0) / w.sum()
    d = xy - c
    _, v = np.linalg.eigh((w[:, None] * d).T @ d)
    direction = v[:, 1]
    normal = np.array([-direction[1], direction[0]])
    return c, direction, np.abs(d @ normal)


def _split(xy: np.ndarray, idx: np.ndarray, cfg: LineConfig, out: list[np.ndarray]) -> None:
    """Split the points ``xy[idx]`` until each piece is one straight, gap-free line."""
    stack = [idx]
    while stack:
        part = stack.pop()
        if len(part) < cfg.min_cells:
            continue
        c, direction, dist = fit_line(xy[part])
        t = (xy[part] - c) @ direction
        order = np.argsort(t, kind="stable")
        part, t, dist = part[order], t[order], dist[order]
        gaps = np.flatnonzero(np.diff(t) > cfg.gap)
        if len(gaps):
            stack.extend(np.split(part, gaps + 1))
            continue
        worst = int(np.argmax(dist))
        if dist[worst] <= cfg.tolerance:
            out.append(part)
            continue
        cut = min(max(worst, 1), len(part) - 1)  # the corner goes to the first piece's end
        stack.append(part[: cut + 1] if cut + 1 < len(part) else part[:cut])
        stack.append(part[cut + 1 :] if cut + 1 < len(part) else part[cut:])


def extract_lines(
    points: np.ndarray,
    resolution: float,
    cfg: LineConfig | None = None,
    weights: np.ndarray | None = None,
) -> LineSet:
    """Line features of obstacle cell centres ``points`` (M, 2) on a grid of cell size
    ``resolution`` (m): 8-connected components of cells, each split into straight lines.
    ``weights`` (M,): confidence of each cell (e.g. its log-odds) for the final line fits:
    a wall two cells thick leans towards the cells it was seen in most."""
    cfg = cfg or LineConfig()
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    label = np.full(len(points), -1, dtype=np.int64)
    empty = np.zeros((0, 2))
    if len(points) < cfg.min_cells:
        return LineSet(points, label, empty, empty, np.zeros((0, 2, 2)), np.zeros(0, int))
    rc = np.floor((points - points.min(axis=0)) / resolution + 0.5).astype(np.int64)
    image = np.zeros(rc.max(axis=0) + 1, dtype=bool)
    image[rc[:, 0], rc[:, 1]] = True
    # dilate once so that a line broken by one missing cell stays one component
    comp, _ = ndimage.label(ndimage.binary_dilation(image), structure=np.ones((3, 3)))
    comp_of = comp[rc[:, 0], rc[:, 1]]
    order = np.argsort(comp_of, kind="stable")
    bounds = np.flatnonzero(np.diff(comp_of[order])) + 1
    pieces: list[np.ndarray] = []
    for group in np.split(order, bounds):
        _split(points, group, cfg, pieces)
    centres, dirs, ends, counts = [], [], [], []
    for part in pieces:
        c, direction, _ = fit_line(points[part], None if weights is None else weights[part])
        t = (points[part] - c) @ direction
        if t.max() - t.min() < cfg.min_length:
            continue
        label[part] = len(centres)
        centres.append(c)
        dirs.append(direction)
        ends.append([c + t.min() * direction, c + t.max() * direction])
        counts.append(len(part))
    if not centres:
        return LineSet(points, label, empty, empty, np.zeros((0, 2, 2)), np.zeros(0, int))
    return LineSet(
        points,
        label,
        np.array(centres),
        np.array(dirs),
        np.array(ends),
        np.array(counts),
    )
