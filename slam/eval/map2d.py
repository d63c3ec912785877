"""Map consistency of a 2D laser run without ground truth (paper 003, section 5: "walls
single, not doubled"): every scan fused into one occupancy grid at the final trajectory,
then around every wall cell the spread of the obstacle cells across the local wall line
(a total-least-squares line of its neighbours; corners and clutter left out).

A wall seen consistently is one or two cells thick (p90 - p10 of the perpendicular
distances ~ one cell); a trajectory that drifted between two visits draws the wall twice
and the spread grows to the offset between the copies.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import InputError
from slam.mapping.grid2d import LOG_ODDS_SCALE, GridConfig, OccupancyGrid, transform2d


@dataclass
class WallThickness:
    """median / p90 (m) over the wall cells of the local wall thickness (p90 - p10 of the
    distances of a cell's k nearest obstacle cells across their principal direction);
    doubled: share of wall cells thicker than ``doubled_at``; cells: wall cells measured
    (line-like neighbourhoods), of ``obstacles`` obstacle cells."""

    median: float
    p90: float
    doubled: float
    cells: int
    obstacles: int


def fuse_scans(
    poses: np.ndarray,
    scans: list[np.ndarray],
    cfg: GridConfig | None = None,
    free_space: bool = False,
) -> OccupancyGrid:
    """One occupancy grid of ``scans`` (each (N, 2), sensor frame, m) at ``poses`` (K, 3)
    (x, y, theta). ``free_space`` False (default) fuses the hits only: a ray of a later
    visit must not clear the first copy of a doubled wall and hide the inconsistency."""
    if len(poses) != len(scans):
        raise InputError(f"fuse_scans: {len(poses)} poses for {len(scans)} scans")
    grid = OccupancyGrid(cfg or GridConfig(subcell=False))  # cell centres: the measure
    for pose, pts in zip(poses, scans, strict=True):
        if len(pts):
            grid.add_scan(transform2d(pose, pts), pose[:2], free_space=free_space)
    return grid


def map_server_grid(poses: np.ndarray, scans: list[np.ndarray]) -> OccupancyGrid:
    """The probabilistic map of ``scans`` at ``poses`` as ``map_server`` reads it: log-odds
    with hits and misses along every beam (the grid defaults: +0.85 / -0.4 nats, clamp
    3.5; ``slam.mapping.carve2d``, compiled), a cell an obstacle when its probability is
    above the ``occupied_thresh`` the map's YAML is written with (``slam.io.grid_map``).
    A stray return beside a wall, crossed by later beams, is carved away; in the hits-only
    grid of ``fuse_scans`` one hit makes it an obstacle for good."""
    from slam.io.grid_map import OCCUPIED_THRESH
    from slam.mapping.carve2d import carve_scans

    logit = float(np.log(OCCUPIED_THRESH / (1.0 - OCCUPIED_THRESH)))
    # the image is thresholded on p > occupied_thresh: the int16 log-odds strictly above
    occupied = (np.floor(logit * LOG_ODDS_SCALE) + 0.5) / LOG_ODDS_SCALE
    grid = OccupancyGrid(GridConfig(subcell=False, occupied=occupied))
    carve_scans(grid, poses, scans)
    return grid


def view_directions(grid: OccupancyGrid, poses: np.ndarray, scans: list[np.ndarray]) -> np.ndarray:
    """(M, 2) mean unit direction sensor -> hit of the hits in each obstacle cell of
    ``grid`` (the order of ``grid.obstacles()``; zero where none), from the same
    ``poses`` / ``scans`` as ``fuse_scans``: the side a wall face was seen from."""
    acc = np.zeros((*grid.data.shape, 2))
    for pose, pts in zip(poses, scans, strict=True):
        if not len(pts):
            continue
        world = transform2d(pose, pts)
        d = world - pose[:2]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        rc = grid.cells_of(world)
        ok = np.all((rc >= 0) & (rc < np.array(grid.data.shape)), axis=1)
        np.add.at(acc, (rc[ok, 0], rc[ok, 1]), d[ok])
    rc = np.argwhere(grid.occupied_mask())
    v = acc[rc[:, 0], rc[:, 1]]
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)


def wall_thickness(
    grid: OccupancyGrid,
    k: int = 40,
    linearity: float = 0.15,
    doubled_at: float = 0.15,
    views: np.ndarray | None = None,
    min_side: int = 10,
) -> WallThickness:
    """Local thickness (m) of the grid's walls: for every obstacle cell its ``k`` nearest
    obstacle cells (k = 40 at 5 cm cells: about 1 m of a single wall), their principal
    (total least squares) direction, and p90 - p10 of their offsets across it. Cells whose
    neighbourhood is not line-like (minor / major eigenvalue >= ``linearity``: corners,
    clutter) are not walls and are left out. A wall seen once is ~1 cell thick; a wall
    drawn twice 10 cm apart measures ~10 cm over the whole stretch where the copies
    overlap (a line fit across the copies would see one fat wall, not two).

    ``views`` (``view_directions``): measure one face at a time - of a cell's neighbours
    only those seen from the same side of the local wall as the cell (at least
    ``min_side`` of them, else the cell is left out). The two faces of a thin partition
    wall, seen from both sides, are two surfaces 10 - 20 cm apart, not a wall drawn twice;
    a wall drawn twice from the same side still measures its offset."""
    obstacles = grid.obstacles()
    if len(obstacles) <= k:
        raise InputError(f"wall_thickness: {len(obstacles)} obstacle cells, need > {k}")
    _, idx = cKDTree(obstacles).query(obstacles, k=k)
    nb = obstacles[idx]  # (M, k, 2)
    rel = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("mki,mkj->mij", rel, rel) / k
    evals, evecs = np.linalg.eigh(cov)  # ascending
    wall = evals[:, 0] < linearity * evals[:, 1]
    minor = evecs[wall, :, 0]  # (W, 2) normal of the local wall
    across = np.einsum("mki,mi->mk", rel[wall], minor)
    if views is not None:
        side = np.einsum("mki,mi->mk", views[idx[wall]], minor)  # (W, k), cell itself first
        same = np.sign(side) == np.sign(side[:, :1])
        across = np.where(same, across, np.nan)
        keep = same.sum(axis=1) >= min_side
        across = across[keep]
    p10, p90 = np.nanpercentile(across, [10, 90], axis=1) if len(across) else ([], [])
    thick = np.asarray(p90) - np.asarray(p10)
    if len(thick) == 0:
        raise InputError("wall_thickness: no line-like neighbourhood in the grid")
    return WallThickness(
        float(np.median(thick)),
        float(np.percentile(thick, 90)),
        float(np.mean(thick > doubled_at)),
        int(len(thick)),
        int(len(obstacles)),
    )


def windowed_floor(
    poses: np.ndarray,
    scans: list[np.ndarray],
    window: int = 100,
    every: int = 2,
    carve: bool = False,
    **kwargs,
) -> WallThickness:
    """The single-visit floor of ``wall_thickness`` over the whole run: the scans cut
    into consecutive windows of ``window`` scans (every ``every``-th fused, as the map),
    each window's map measured on its own (a stretch of a few metres, no revisit inside),
    and the cell-weighted mean of the windows' median / p90 / doubled share. The floor
    at the start alone (the first 50 scans) says little about a building whose corridors
    are longer, more cluttered or seen from farther than its first room. ``carve``: each
    window's map is the probabilistic one (``map_server_grid``) instead of hits only."""
    meds, p90s, doubled, cells, obstacles = [], [], [], [], 0
    for lo in range(0, len(poses) - window + 1, window):
        p, s = poses[lo : lo + window : every], scans[lo : lo + window : every]
        grid = map_server_grid(p, s) if carve else fuse_scans(p, s)
        try:
            w = wall_thickness(grid, **kwargs)
        except InputError:  # too few walls in this window
            continue
        meds.append(w.median)
        p90s.append(w.p90)
        doubled.append(w.doubled)
        cells.append(w.cells)
        obstacles += w.obstacles
    if not cells:
        raise InputError(f"windowed_floor: no window of {window} scans with walls")
    return WallThickness(
        float(np.average(meds, weights=cells)),
        float(np.average(p90s, weights=cells)),
        float(np.average(doubled, weights=cells)),
        int(sum(cells)),
        obstacles,
    )
