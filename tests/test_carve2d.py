"""The compiled free-space carving (``slam.mapping.carve2d``) against its numpy reference
(``OccupancyGrid.add_scan``), and the wall measure on the probabilistic map the way
``map_server`` reads it (``slam.eval.map2d.map_server_grid``)."""

from __future__ import annotations

import numpy as np
import pytest

from slam.errors import InputError
from slam.eval.map2d import fuse_scans, map_server_grid, wall_thickness, windowed_floor
from slam.io.grid_map import OCCUPIED_THRESH, map_image
from slam.mapping.carve2d import carve_scans
from slam.mapping.grid2d import GridConfig, OccupancyGrid, transform2d
from slam.sim.floorplan2d import simulate2d


@pytest.fixture(scope="module")
def rooms():
    seq = simulate2d("rooms2d", frames=120, speed=1.5, seed=3)
    scans = [seq.points(k)[:, :2].astype(np.float64) for k in range(0, 120, 2)]
    return np.asarray(seq.poses[0:120:2], dtype=np.float64), scans


def test_carving_kernel_equals_the_numpy_reference(rooms):
    """60 scans of the rooms (and the same scans 7 cm / 2 deg off, so that later beams
    cross earlier hits), clamp low enough to be reached: every cell's log-odds equal."""
    poses, scans = rooms
    off = poses + [0.07, -0.05, np.radians(2.0)]
    poses, scans = np.vstack([poses, off]), scans + scans
    cfg = GridConfig(subcell=False, clamp=1.5)
    fast, ref = OccupancyGrid(cfg), OccupancyGrid(cfg)
    world = [transform2d(p, s) for p, s in zip(poses, scans, strict=True)]
    ref._ensure(np.vstack([*world, poses[:, :2]]))  # the same array and origin
    for p, w in zip(poses, world, strict=True):
        ref.add_scan(w, p[:2])
    carve_scans(fast, poses, scans)
    assert fast.data.shape == ref.data.shape
    np.testing.assert_array_equal(fast.origin, ref.origin)
    assert (ref.data < 0).sum() > 10000 and (ref.data == -150).sum() > 1000  # carved, clamped
    np.testing.assert_array_equal(fast.data, ref.data)
    with pytest.raises(InputError):
        carve_scans(OccupancyGrid(GridConfig()), poses, scans)  # sub-cell means not kept


def test_map_server_grid_carves_stray_returns(rooms):
    """Stray returns 10 - 40 cm in front of the walls (1 beam in 20, each scan its own)
    thicken the hits-only map's walls; the probabilistic map carves them with the beams
    of the other scans (measured medians: clean 0.050, strays hits-only 0.147, carved
    0.050 m; walls > 15 cm 5 / 48 / 7 %). Its obstacles are the map image's occupied
    pixels (p > occupied_thresh)."""
    poses, scans = rooms
    rng = np.random.default_rng(1)
    noisy = []
    for s in scans:
        s = s.copy()
        k = rng.random(len(s)) < 0.05
        r = np.linalg.norm(s[k], axis=1, keepdims=True)
        s[k] *= 1.0 - rng.uniform(0.1, 0.4, (k.sum(), 1)) / r
        noisy.append(s)
    clean = wall_thickness(fuse_scans(poses, scans)).median
    hits = wall_thickness(fuse_scans(poses, noisy)).median
    grid = map_server_grid(poses, noisy)
    carved = wall_thickness(grid).median
    assert clean < 0.06 and hits > clean + 0.025 and carved < clean + 0.01
    img = map_image(grid)[::-1]
    np.testing.assert_array_equal(img == 0, grid.occupied_mask())
    assert grid.probability()[grid.occupied_mask()].min() > OCCUPIED_THRESH
    floor = windowed_floor(poses, noisy, window=30, every=1, carve=True)
    assert floor.median < clean + 0.01 and floor.cells > 1000
