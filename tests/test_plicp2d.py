"""2D building blocks of DPCR-SLAM (paper 003): occupancy grid, regional division
(eqs. (3)-(5)), line features and the improved PLICP, on simulated floor plans."""

from __future__ import annotations

import numpy as np
import pytest

from slam.features.lines2d import extract_lines
from slam.mapping.grid2d import (
    GridConfig,
    OccupancyGrid,
    RegionDivision,
    compose2d,
    inverse2d,
    transform2d,
)
from slam.registration.plicp import LineReference, PlicpConfig, plicp
from slam.sim.floorplan2d import Scanner2D, simulate2d


@pytest.fixture(scope="module")
def rooms_seq():
    return simulate2d("rooms2d", frames=120, seed=1)


def _map_of(seq, frames) -> OccupancyGrid:
    grid = OccupancyGrid(GridConfig(resolution=0.05))
    for k in frames:
        grid.add_scan(transform2d(seq.poses[k], seq.points(k)), seq.poses[k][:2])
    return grid


def test_region_index_matches_eq5_by_hand():
    div = RegionDivision(grid_width=0.05, rows=400, cols=600, cells_per_region=80)  # S = 4 m
    assert div.region_width == pytest.approx(4.0)
    # (x, y) = (0, 0): i = round(0 + 200) = 200, j = round(0 + 300) = 300
    # R = fix(200 / 80) * (600 / 80) + fix(300 / 80) = 2 * 7 + 3 = 17  (600 // 80 = 7)
    assert div.grid_coords(np.array([[0.0, 0.0]])) == (200, 300)
    assert div.region_of(np.array([[0.0, 0.0]]))[0] == 17
    # (x, y) = (-11.2, 6.1): j = round(-224 + 300) = 76, i = round(122 + 200) = 322
    # R = fix(322 / 80) * 7 + fix(76 / 80) = 4 * 7 + 0 = 28
    assert div.region_of(np.array([[-11.2, 6.1]]))[0] == 28
    # the centre of a region lies in it
    for r in (17, 28, 3):
        assert div.region_of(div.centre(r)[None])[0] == r


def test_grid_marks_walls_and_clears_free_space(rooms_seq):
    grid = _map_of(rooms_seq, range(0, 40))
    occ = grid.obstacles()
    segs = rooms_seq.plan.segments
    # every obstacle cell lies within 2 cells of a wall segment (or furniture edge)
    a, b = segs[:, 0], segs[:, 1]
    e = b - a
    t = np.clip(np.einsum("nkd,kd->nk", occ[:, None] - a[None], e) / (e**2).sum(1), 0, 1)
    dist = np.linalg.norm(occ[:, None] - (a[None] + t[..., None] * e[None]), axis=2).min(1)
    assert np.quantile(dist, 0.99) < 0.1 and len(occ) > 500
    # the robot's own positions are free (log-odds < 0)
    p = grid.probability()
    rc = grid.cells_of(rooms_seq.poses[:40, :2])
    assert np.all(p[rc[:, 0], rc[:, 1]] < 0.5)
    assert grid.nbytes == grid.data.size * 2  # 2 bytes per cell (paper's unit)


def test_removing_a_scan_undoes_it(rooms_seq):
    grid = OccupancyGrid(GridConfig(clamp=300.0))  # a sliding submap: no clamping
    for k in range(5):
        grid.add_scan(transform2d(rooms_seq.poses[k], rooms_seq.points(k)), rooms_seq.poses[k][:2])
    before = grid.data.copy()
    pts = transform2d(rooms_seq.poses[7], rooms_seq.points(7))
    grid.add_scan(pts, rooms_seq.poses[7][:2])
    grid.add_scan(pts, rooms_seq.poses[7][:2], weight=-1.0)
    assert np.abs(grid.data[: before.shape[0], : before.shape[1]] - before).max() <= 1


def test_line_features_follow_the_walls(rooms_seq):
    grid = _map_of(rooms_seq, range(0, 40))
    lines = extract_lines(grid.obstacles(), grid.cfg.resolution)
    assert len(lines) >= 8 and (lines.label >= 0).mean() > 0.7
    # the long walls of the plan are axis-aligned: long lines are within 1 deg of an axis
    long = (np.linalg.norm(lines.ends[:, 1] - lines.ends[:, 0], axis=1)) > 1.5
    ang = np.degrees(np.arctan2(lines.direction[long, 1], lines.direction[long, 0])) % 90
    assert np.all(np.minimum(ang, 90 - ang) < 1.0)


def _wall_reference(plan, spacing: float = 0.05) -> LineReference:
    """The plan's walls sampled every ``spacing`` m, each sample with its wall's direction."""
    pts, dirs = [], []
    for a, b in plan.segments:
        length = np.linalg.norm(b - a)
        t = np.linspace(0.0, 1.0, max(int(length / spacing), 2))[:, None]
        pts.append(a + t * (b - a))
        dirs.append(np.repeat(((b - a) / length)[None], len(t), axis=0))
    return LineReference.build(np.vstack(pts), np.vstack(dirs))


@pytest.mark.parametrize("k", [45, 60, 80])
def test_plicp_recovers_a_known_transform_against_the_walls(rooms_seq, k):
    """The algorithm itself: a noisy room scan (1 cm range noise) against the true walls,
    started 18 cm / 3 deg off, lands within 2 mm / 0.02 deg."""
    truth = rooms_seq.poses[k]
    start = compose2d(truth, np.array([0.15, -0.10, np.radians(3.0)]))
    res = plicp(rooms_seq.points(k), _wall_reference(rooms_seq.plan), start, PlicpConfig())
    err = compose2d(inverse2d(truth), res.pose)
    assert res.converged and res.iterations < 20
    assert np.linalg.norm(err[:2]) < 0.002 and abs(np.degrees(err[2])) < 0.02
    assert res.rmse < 0.015 and np.all(np.linalg.eigvalsh(res.info) > 0)


@pytest.mark.parametrize("k", [45, 60, 80])
def test_plicp_recovers_a_known_transform_against_a_grid_map(rooms_seq, k):
    """Against the line features of a 5 cm occupancy grid of 40 earlier scans (the
    paper's w_g): < 1 cm and < 0.3 deg. (The 5 cm cells, two thick along a wall and worn
    by grazing rays, tilt short lines by 0.1-0.3 deg: at 2 cm cells the same run gives
    0.01 deg.)"""
    grid = _map_of(rooms_seq, range(0, 40))
    ref = LineReference.from_lines(extract_lines(grid.obstacles(), grid.cfg.resolution))
    truth = rooms_seq.poses[k]
    start = compose2d(truth, np.array([0.15, -0.10, np.radians(3.0)]))
    res = plicp(rooms_seq.points(k), ref, start, PlicpConfig())
    err = compose2d(inverse2d(truth), res.pose)
    assert res.converged
    assert np.linalg.norm(err[:2]) < 0.01 and abs(np.degrees(err[2])) < 0.3
    assert res.rmse < 0.04


def test_plicp_line_matches_beat_point_matches_with_coarse_cells():
    """Against 10 cm cells the line features (fitted lines) beat matching the cell centres
    themselves (PLICP without lines degenerates to point-to-point ICP on the cells)."""
    seq = simulate2d("office2d", frames=80, seed=2, scanner=Scanner2D(sigma=0.02))
    grid = OccupancyGrid(GridConfig(resolution=0.1))
    for k in range(30):
        grid.add_scan(transform2d(seq.poses[k], seq.points(k)), seq.poses[k][:2])
    lines = extract_lines(grid.obstacles(), 0.1)
    with_lines = LineReference.from_lines(lines)
    cells_only = LineReference.build(lines.points)
    errs = {"lines": [], "cells": []}
    for k in range(35, 75, 5):
        start = compose2d(seq.poses[k], np.array([0.1, 0.05, np.radians(2.0)]))
        for name, ref in (("lines", with_lines), ("cells", cells_only)):
            res = plicp(seq.points(k), ref, start)
            errs[name].append(np.linalg.norm(res.pose[:2] - seq.poses[k][:2]))
    assert np.mean(errs["lines"]) < 0.6 * np.mean(errs["cells"])
    assert np.mean(errs["lines"]) < 0.03
