"""The open-road measure and the scatter points (``slam.features.scatter``) on constructed
covariances and clouds."""

from __future__ import annotations

import numpy as np
import pytest

from slam.errors import ConfigError
from slam.features.scatter import (
    OpenRoadGate,
    ScatterConfig,
    horizontal_observability,
    scatter_points,
)


def _plane(n, spread: float = 1.0) -> np.ndarray:
    """Covariance of a surface with unit normal n: 1e-4 m^2 along n, spread m^2 along it."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    return 1e-4 * np.outer(n, n) + spread * (np.eye(3) - np.outer(n, n))


def _line(u) -> np.ndarray:
    u = np.asarray(u, float) / np.linalg.norm(u)
    return 1e-4 * np.eye(3) + np.outer(u, u)


def test_walls_facing_both_ways_observe_every_horizontal_direction():
    covs = np.array([_plane([1, 0, 0])] * 50 + [_plane([0, 1, 0])] * 50)
    assert horizontal_observability(covs) == pytest.approx(1.0, abs=1e-6)


def test_a_road_of_walls_rails_and_ground_observes_nothing_along_it():
    """Barriers (normal y), the ground (normal z) and rails (lines along x): nothing
    observes x; a pole (a vertical line) observes x and y alike."""
    road = [_plane([0, 1, 0])] * 40 + [_plane([0, 0, 1])] * 40 + [_line([1, 0, 0])] * 20
    assert horizontal_observability(np.array(road)) < 1e-6
    pole = [_line([0, 0, 1])] * 10
    assert horizontal_observability(np.array(road + pole)) == pytest.approx(10 / 70, rel=1e-3)


def test_the_measure_does_not_depend_on_the_road_heading():
    yaw = np.radians(37.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    covs = np.array([_plane([0, 1, 0])] * 30 + [_plane([1, 0, 0])] * 10)
    turned = np.einsum("ij,njk,lk->nil", R, covs, R)
    assert horizontal_observability(turned) == pytest.approx(1 / 3, rel=1e-6)
    assert horizontal_observability(covs) == pytest.approx(1 / 3, rel=1e-6)


def test_isotropic_covariances_judge_nothing():
    assert horizontal_observability(np.array([np.eye(3)] * 5)) == 1.0
    with pytest.raises(ValueError):
        horizontal_observability(np.zeros((4, 3)))


def test_scatter_points_are_the_non_candidates_off_the_ground_one_per_voxel():
    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-10, 10, (400, 2)), np.full(400, -1.8)])
    bush = rng.normal([5.0, 3.0, -1.0], 0.3, (300, 3))  # a bush, 0.8 m above the ground
    wall = np.column_stack([np.full(200, 8.0), rng.uniform(-5, 5, 200), rng.uniform(-1.8, 1, 200)])
    xyz = np.vstack([ground, bush, wall])
    candidates = np.zeros(len(xyz), dtype=bool)
    candidates[700:] = True  # the wall was picked as plane features
    plane = (np.array([0.0, 0.0, 1.0]), 1.8)
    cfg = ScatterConfig(voxel=0.5, min_height=0.3)
    idx = scatter_points(xyz, candidates, plane, cfg)
    assert np.all((idx >= 400) & (idx < 700))  # neither the ground nor the features
    keys = np.floor(xyz[idx] / 0.5).astype(int)
    assert len(np.unique(keys, axis=0)) == len(idx)  # one per voxel
    assert len(idx) >= 8  # the bush spans several voxels
    everything = scatter_points(xyz, candidates, None, cfg)  # no ground known: no height test
    assert np.any(everything < 400)


def test_scatter_settings_are_checked():
    with pytest.raises(ConfigError):
        ScatterConfig(voxel=0.0)
    with pytest.raises(ConfigError):
        ScatterConfig(min_height=-1.0)
    with pytest.raises(ConfigError, match="never, always, auto"):
        ScatterConfig(mode="on")
    with pytest.raises(ConfigError):
        ScatterConfig(on_share=0.2, off_share=0.5)


def _gate_run(flags, **kw) -> list[bool]:
    """The gate's mode for each scan, decided before that scan's flag is known."""
    gate, out = OpenRoadGate(ScatterConfig(**kw)), []
    for f in flags:
        out.append(gate.on)
        gate.update(f)
    return out


def test_the_open_road_mode_follows_the_stretch_not_the_scan():
    """On from the scan after the first along-road scan of a run (a motorway from the
    start); held through 40 scans whose features look observable (a simulated motorway's
    woods and junctions, where LOAM features alone still stall); off once fewer than 20 of
    the last 100 scans ran along the road; never on a city drive whose along-road scans
    come singly."""
    motorway = [True] * 30 + [False] * 40 + [True] * 30 + [False] * 200
    modes = _gate_run(motorway)
    assert modes[0] is False and all(modes[1:181])
    assert not any(modes[181:])  # at scan 180, 19 of the last 100 ran along the road
    assert not all(_gate_run(motorway, hold=20)[1:70])  # a short memory drops it in the wood
    city = [k % 50 == 7 for k in range(500)]  # one along-road scan in 50
    assert not any(_gate_run(city)[10:])
    starts_along = _gate_run([True] + [False] * 20)  # the first scan is all the gate knows
    assert starts_along[1] is True and not any(starts_along[7:])
    assert not any(_gate_run(motorway, mode="never"))


def test_a_scan_registered_from_several_starts_counts_once():
    """The start search registers one scan from several starts: the front end restores the
    gate before each (``state`` / ``restore``), so the scan's flag is recorded once."""
    gate = OpenRoadGate(ScatterConfig())
    assert gate.unjudged
    gate.update(False)
    saved = gate.state()
    for _ in range(9):
        gate.restore(saved)
        gate.update(True)
    assert gate.state() == ((False, True), True) and not gate.unjudged
    assert not OpenRoadGate(ScatterConfig(mode="always")).unjudged
    assert all(_gate_run([False] * 10, mode="always"))


def test_slam_run_suggests_the_open_road_recipe_only_when_it_applies():
    from slam.cli.run import along_road_warning

    road = {"frontend_means": {"along_road": 0.88, "scatter_points": 0.0}}
    assert "--config improved_floam_open_road" in along_road_warning(road)
    assert "88 %" in along_road_warning(road)
    city = {"frontend_means": {"along_road": 0.03, "scatter_points": 0.0}}
    assert along_road_warning(city) is None
    recipe = {"frontend_means": {"along_road": 0.88, "scatter_points": 2400.0}}
    assert along_road_warning(recipe) is None  # it runs the recipe already
    assert along_road_warning({}) is None  # other front ends report no such measure


def test_slam_run_says_when_the_open_road_mode_was_on():
    from slam.cli.run import open_road_line

    assert "52 % of the scans" in open_road_line({"frontend_means": {"open_road": 0.52}})
    assert open_road_line({"frontend_means": {"open_road": 0.0}}) is None
    assert open_road_line({}) is None
    # improved_floam without the beams' calibration: most scans in the mode name the recipe
    road = {"frontend_means": {"open_road": 0.9}}
    assert "improved_floam_open_road" in open_road_line(road, recipe_hint=True)
    assert "improved_floam_open_road" not in open_road_line(road)
    city = {"frontend_means": {"open_road": 0.12}}
    assert "improved_floam_open_road" not in open_road_line(city, recipe_hint=True)
