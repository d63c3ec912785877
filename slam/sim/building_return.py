"""The ``building_return`` scene: the floor of :mod:`slam.sim.building` driven out and back
along the same corridors, for loop closure that can see the drift.

``building_loop`` meets itself only at its start, where the along-corridor slips of its
two long corridors (driven east, then west) have largely cancelled: no loop closure
halves its APE (the true relative poses of its loops give 4.20 of 5.55 m). This route
comes back over its own path in the opposite direction, so that every stretch of the way
back can be tied to the way out:

- out: east along the first corridor (y = 8 m) from x = 24 m, through its plain stretch
  (x = 36-62 m) and the first hall, up the middle spine, east along the second corridor
  (y = 50 m) into the hall on it (x = 196-236 m);
- a turnaround loop in that hall (three left turns and a right one, tighter than the
  corridor corners: 4 m of arc per 90 deg, in the 16 m free band between the column
  rows, 2.6 m from the cart's lane), crossing its own path at x = 213 m;
- back: west along the second corridor, down the middle spine, west along the first
  corridor, 8 m past the start.

``building_loop_return``: ``building_loop``'s rectangle and back (~0.91 km): east along the
first corridor, up the middle spine, west along the second corridor through its plain
stretch (x = 60-90 m), down the west spine, east along the first corridor into the first
hall (x = 70-110 m), a turnaround loop there (3.5 m of arc per 90 deg, east of the
workers' lane in that hall), then the whole way back: west along the first corridor, up
the west spine, east along the second corridor, down the middle spine and west along the
first corridor, 8 m past the start. Every corridor of it is driven in both directions.

Same floor, workers and machinery as the other building routes (the same seeds), the
same robot (:func:`slam.sim.building.robot_trajectory`'s limits) and sensor. The module
only adds: the other routes' sequences (and their cache keys, which cover building.py
but not this file) are unchanged.
"""

from __future__ import annotations

import numpy as np

from slam.sim.building import (
    FLOOR_X,
    FLOOR_Y,
    LANES,
    MAX_SPEED,
    SENSOR_HEIGHT,
    SPINE_M,
    SPINE_W,
    _floor,
    _walkers,
    route_path,
)
from slam.sim.registry import scene_sensor
from slam.sim.scene import Scene
from slam.sim.trajectory import Trajectory, lane_route, route_trajectory

UTURN_TURN_LENGTH = 4.0  # m of arc per 90-degree turn in the hall (minimum radius 1.3 m)
OUT_NODES = ((24.0, LANES[0]), (SPINE_M, LANES[0]), (SPINE_M, LANES[1]), (210.0, LANES[1]))
UTURN_NODES = (
    (210.0, LANES[1]),
    (226.0, LANES[1]),
    (226.0, LANES[1] + 5.0),
    (213.0, LANES[1] + 5.0),
    (213.0, LANES[1]),
    (200.0, LANES[1]),
)
BACK_NODES = ((200.0, LANES[1]), (SPINE_M, LANES[1]), (SPINE_M, LANES[0]), (16.0, LANES[0]))


# building_loop_return: building_loop's rectangle, a turnaround in the first hall (east of
# the workers crossing it at y = 14 m, x = 80-100 m), and the rectangle back.
LOOP_UTURN_TURN_LENGTH = 3.5  # m of arc per 90 deg (minimum radius 1.1 m)
LOOP_OUT_NODES = (
    (24.0, LANES[0]),
    (SPINE_M, LANES[0]),
    (SPINE_M, LANES[1]),
    (SPINE_W, LANES[1]),
    (SPINE_W, LANES[0]),
    (100.0, LANES[0]),
)
LOOP_UTURN_NODES = (
    (100.0, LANES[0]),
    (108.0, LANES[0]),
    (108.0, LANES[0] + 4.5),
    (101.0, LANES[0] + 4.5),
    (101.0, LANES[0]),
    (90.0, LANES[0]),
)
LOOP_BACK_NODES = (
    (90.0, LANES[0]),
    (SPINE_W, LANES[0]),
    (SPINE_W, LANES[1]),
    (SPINE_M, LANES[1]),
    (SPINE_M, LANES[0]),
    (16.0, LANES[0]),
)


def turnaround_path(
    out_nodes, uturn_nodes, back_nodes, uturn_turn_length: float, ds: float = 0.05
) -> np.ndarray:
    """Path (K,2) m: ``out_nodes`` and ``back_nodes`` with the corridor corners of the other
    building routes, ``uturn_nodes`` (a loop in a hall) with tighter turns. The pieces meet
    on straight stretches, so the path is curvature-continuous."""
    out = route_path(out_nodes, ds)
    uturn = lane_route(
        np.asarray(uturn_nodes),
        lane_offset=0.0,
        left_turn_length=uturn_turn_length,
        right_turn_length=uturn_turn_length,
        ds=ds,
    )
    back = route_path(back_nodes, ds)
    return np.vstack([out, uturn[1:], back[1:]])


def return_path(ds: float = 0.05) -> np.ndarray:
    """``building_return``'s path (K,2): out, the hall turnaround, back (m)."""
    return turnaround_path(OUT_NODES, UTURN_NODES, BACK_NODES, UTURN_TURN_LENGTH, ds)


def loop_return_path(ds: float = 0.05) -> np.ndarray:
    """``building_loop_return``'s path (K,2): the rectangle, the turnaround, back (m)."""
    return turnaround_path(
        LOOP_OUT_NODES, LOOP_UTURN_NODES, LOOP_BACK_NODES, LOOP_UTURN_TURN_LENGTH, ds
    )


def return_trajectory(rng: np.random.Generator, xy: np.ndarray | None = None) -> Trajectory:
    """The ground robot of the other building routes (:func:`slam.sim.building.robot_trajectory`:
    at most 3 m/s, 0.8 / 1 m/s^2, 1 m/s^2 lateral, the same body sway) on ``xy`` (default
    :func:`return_path`), no stops."""
    xy = return_path() if xy is None else xy
    return route_trajectory(
        xy,
        speed_limit=np.full(len(xy), MAX_SPEED),
        stops=[],
        height=SENSOR_HEIGHT,
        rng=rng,
        lateral_accel=1.0,
        accel=0.8,
        decel=1.0,
        wobble_deg=0.3,
        vibration_deg=0.15,
        pitch_per_accel_deg=0.4,
        roll_per_accel_deg=0.4,
        sway_speed=1.0,
    )


def _scene(name: str, seed: int, xy: np.ndarray, pedestrians: bool, what: str) -> Scene:
    b = _floor(np.random.default_rng([seed, 13]))  # the same floor for every route
    rng = np.random.default_rng([seed, 14])
    peds = _walkers(rng) if pedestrians else []
    traj = return_trajectory(np.random.default_rng([seed, 15]), xy)
    return Scene.from_builder(
        name,
        b,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=40.0,
        revisit_radius=3.0,
        sensor=scene_sensor(name),
        description=(
            f"building under construction {FLOOR_X:g}x{FLOOR_Y:g} m, {what}, "
            f"{traj.length:.0f} m at up to {MAX_SPEED:g} m/s"
        ),
    )


def building_return(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """The building floor, out along two corridors and back along them (loop closure)."""
    return _scene(
        "building_return", seed, return_path(), pedestrians, "out and back along two corridors"
    )


def building_loop_return(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """building_loop's rectangle driven and driven back (loop closure)."""
    return _scene(
        "building_loop_return",
        seed,
        loop_return_path(),
        pedestrians,
        "the loop route there and back",
    )
