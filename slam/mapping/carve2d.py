"""Many scans fused into one probabilistic occupancy grid with free-space carving (hits
and misses along every beam), compiled: the grid a whole log's map is when read the way
``map_server`` reads it (the wall measure on the probabilistic map).

``carve_scans(grid, poses, scans)`` equals ``grid.add_scan(transform2d(pose, pts),
pose[:2])`` for every scan in turn (``slam.mapping.grid2d.OccupancyGrid.add_scan``, the
numpy reference: the same ray samples, one update per cell and scan, a cell holding an
end point of the scan not cleared by it, misses before hits, clamped after each) once the
grid has been grown to hold every scan: the compiled loop visits each ray cell once
instead of sorting every scan's cells (``np.unique``) in numpy.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from slam.errors import InputError
from slam.mapping.grid2d import LOG_ODDS_SCALE, OccupancyGrid, transform2d


@njit(cache=True)
def _carve(data, origin, res, starts, sensors, ends, miss, hit, lim):
    rows, cols = data.shape
    stamp_hit = np.full(data.size, -1, dtype=np.int64)  # scan whose end point is here
    stamp_free = np.full(data.size, -1, dtype=np.int64)  # scan that cleared it already
    stamp_done = np.full(data.size, -1, dtype=np.int64)  # scan that hit it already
    flat = data.reshape(-1)
    for s in range(len(starts) - 1):
        lo, hi = starts[s], starts[s + 1]
        ox, oy = sensors[s, 0], sensors[s, 1]
        for n in range(lo, hi):
            r = np.int64(np.floor((ends[n, 1] - origin[1]) / res))
            c = np.int64(np.floor((ends[n, 0] - origin[0]) / res))
            stamp_hit[r * cols + c] = s
        for n in range(lo, hi):
            dx, dy = ends[n, 0] - ox, ends[n, 1] - oy
            length = np.sqrt(dx * dx + dy * dy)
            steps = max(np.int64(length / res), 0)
            shrink = max(1.0 - res / max(length, res), 0.0)
            for k in range(steps):
                frac = k / max(steps, 1) * shrink
                px, py = ox + dx * frac, oy + dy * frac
                r = np.int64(np.floor((py - origin[1]) / res))
                c = np.int64(np.floor((px - origin[0]) / res))
                f = r * cols + c
                if stamp_hit[f] == s or stamp_free[f] == s:
                    continue
                stamp_free[f] = s
                v = np.int32(flat[f]) + miss
                flat[f] = min(max(v, -lim), lim)
        for n in range(lo, hi):
            r = np.int64(np.floor((ends[n, 1] - origin[1]) / res))
            c = np.int64(np.floor((ends[n, 0] - origin[0]) / res))
            f = r * cols + c
            if stamp_done[f] == s:
                continue
            stamp_done[f] = s
            v = np.int32(flat[f]) + hit
            flat[f] = min(max(v, -lim), lim)


def carve_scans(grid: OccupancyGrid, poses: np.ndarray, scans: list[np.ndarray]) -> None:
    """Fuse ``scans`` (each (N, 2), sensor frame) at ``poses`` (K, 3) into ``grid`` with
    hits and misses (weight 1), in place; the grid is grown first to hold them all.
    The grid's sub-cell hit means (``subcell``) are not kept: use a grid without them."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(poses) != len(scans):
        raise InputError(f"carve_scans: {len(poses)} poses for {len(scans)} scans")
    if grid.hits is not None:
        raise InputError("carve_scans: keeps no sub-cell hit means (GridConfig(subcell=False))")
    world = [
        transform2d(p, np.asarray(s, dtype=np.float64).reshape(-1, 2))
        for p, s in zip(poses, scans, strict=True)
    ]
    counts = np.array([len(w) for w in world], dtype=np.int64)
    if counts.sum() == 0:
        return
    ends = np.vstack(world)
    sensors = np.ascontiguousarray(poses[:, :2])
    grid._ensure(np.vstack([ends, sensors]))
    starts = np.r_[0, np.cumsum(counts)].astype(np.int64)
    cfg = grid.cfg
    miss, hit = (np.int32(round(v * LOG_ODDS_SCALE)) for v in (cfg.miss, cfg.hit))
    lim = np.int32(int(cfg.clamp * LOG_ODDS_SCALE))
    origin = np.asarray(grid.origin, dtype=np.float64)
    _carve(grid.data, origin, float(cfg.resolution), starts, sensors, ends, miss, hit, lim)


__all__ = ["carve_scans"]
