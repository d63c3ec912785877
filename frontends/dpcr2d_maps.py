"""The regional maps of the DPCR-SLAM front end (``frontends.dpcr2d``) and the map of
the visit graph re-fused from its visits at their optimised poses."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from slam.mapping.grid2d import (
    GridConfig,
    OccupancyGrid,
    compose2d,
    inverse2d,
    matrix_to_pose2,
    transform2d,
)
from slam.registration.plicp import LineReference


@dataclass
class Region:
    grid: OccupancyGrid
    ref: LineReference | None = None
    refreshed_at: int = -(10**9)
    left_at: float | None = None  # path length (m) when the robot last left the region
    owner: int = 0  # the keyframe that opened the region (its pose places the grid)
    # where the grid lies in the current map frame: map = offset o grid (x, y, theta)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def to_grid(self, pose: np.ndarray) -> np.ndarray:
        return compose2d(inverse2d(self.offset), pose)

    def in_map(self, correction: np.ndarray) -> np.ndarray:
        """A correction of the grid's frame expressed in the map frame."""
        return compose2d(compose2d(self.offset, correction), inverse2d(self.offset))


def fuse_visits(
    visit_scans: list[list[tuple[np.ndarray, np.ndarray]]],
    visit_points: list[np.ndarray],
    estimates: dict[int, np.ndarray],
    grid: GridConfig,
    free_space: bool = True,
) -> OccupancyGrid:
    """The visits re-fused at their optimised poses (4x4, by keyframe id). ``free_space``:
    every scan of each visit (pose relative to the visit, points) with hits and misses
    along its beams (``slam.mapping.carve2d``, no sub-cell means), the map as map_server
    reads it; False: each visit's cloud (``visit_points``), hits only."""
    if free_space:
        from slam.mapping.carve2d import carve_scans

        poses, scans = [], []
        for kf_id, visit in enumerate(visit_scans):
            T = estimates.get(kf_id)
            if T is None:
                continue
            pose = matrix_to_pose2(T)
            for rel, pts in visit:
                poses.append(compose2d(pose, rel))
                scans.append(pts.astype(np.float64))
        out = OccupancyGrid(replace(grid, subcell=False))
        if poses:
            carve_scans(out, np.array(poses), scans)
        return out
    out = OccupancyGrid(grid)
    for kf_id, pts in enumerate(visit_points):
        T = estimates.get(kf_id)
        if T is not None and len(pts):
            pose = matrix_to_pose2(T)
            out.add_scan(transform2d(pose, pts), pose[:2], free_space=False)
    return out
