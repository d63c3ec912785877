"""The ``highway`` scene: a car drives 2 km along a straight motorway at up to 25 m/s.

Made to test front ends where a drive is least constrained along its direction
(``benchmarks/unseen_sweep.py``, ``slam run --start N`` for a recording that starts at
speed): three lanes each way and a hard shoulder, a concrete median barrier, guard rails
with a post every 2 m (about a frame's step at 20 m/s), a delineator post every 50 m, grass
verges rising into cuttings or falling to embankments, groups of trees with open fields
between them, a 350 m noise wall, two overpasses and three sign gantries. Traffic: trucks
in the right lane at 21-24 m/s, faster cars in the left lane at 29-36 m/s, oncoming traffic
on the other carriageway. Realistic sensor errors (:meth:`LidarModel.realistic`).

Timeline at 10 Hz: 1 s standing, 0 -> 25 m/s in about 17 s (frame 70: ~9 m/s, frame 180:
25 m/s), 25 m/s to about frame 850, braking to a stop at the end.
"""

from __future__ import annotations

import numpy as np

from slam.sim import geometry as g
from slam.sim.registry import scene_sensor
from slam.sim.scene import Pedestrian, Scene
from slam.sim.trajectory import Trajectory, route_trajectory
from slam.sim.urban import CAR_SENSOR_HEIGHT

LENGTH = 2000.0  # m of motorway driven (x from 0)
SPEED = 25.0  # m/s
LANES = (2.0, 5.5, 9.0)  # m: left, middle, right lane centres from the median's centre
CAR_LANE = LANES[1]  # the car drives the middle lane of the carriageway at y < 0
RAIL = 13.0  # m: outer guard rails from the median's centre (past a 2.5 m hard shoulder)
POST_PITCH = 2.0  # m between guard-rail posts
OVERPASSES = (620.0, 1480.0)  # x of the bridges' centres (m)
GANTRIES = (350.0, 1100.0, 1790.0)  # x of the sign gantries (m)
NOISE_WALL = (900.0, 1250.0)  # x range of the noise wall on the right (m)


def _verge_height(rng: np.random.Generator):
    """z(x, |y|) of the verges (m): a cutting (up to +4 m) or an embankment (down to -2.5 m)
    drawn per 150 m and blended, ramping in from 1.5 m past the guard rail over 8 m."""
    knots = np.arange(-200.0, LENGTH + 350.0, 150.0)
    level = rng.uniform(-2.5, 4.0, (2, len(knots)))

    def z(x: np.ndarray, ay: np.ndarray, side: int) -> np.ndarray:
        top = np.interp(x, knots, level[side])
        return top * np.clip((ay - RAIL - 1.5) / 8.0, 0.0, 1.0)

    return z


def _terrain(b: g.MeshBuilder, rng: np.random.Generator, z) -> None:
    """The paved carriageways, and grass verges as height fields (2 m cells, ~8 cm
    roughness)."""
    b.add(g.ground((-80.0, LENGTH + 80.0), (-RAIL - 1.0, RAIL + 1.0), 0.0, g.ASPHALT))
    gx = np.arange(-80.0, LENGTH + 80.01, 2.0)
    for side, sign in ((0, -1.0), (1, 1.0)):
        ay = np.arange(RAIL + 1.0, 90.01, 2.0)
        xx, yy = np.meshgrid(gx, ay)
        zz = z(xx, yy, side) + rng.normal(0.0, 0.08, xx.shape)
        gy = sign * ay
        order = np.argsort(gy)
        b.add(g.height_field(gx, gy[order], zz[order], g.GRASS))


def _barriers(b: g.MeshBuilder) -> None:
    """The median's concrete barrier, the outer guard rails (W-beam 0.5-0.85 m, posts every
    2 m) and the delineator posts every 50 m."""
    b.add(g.box_minmax((-80.0, -0.3, 0.0), (LENGTH + 80.0, 0.3, 0.9), g.CONCRETE))
    for sign in (-1.0, 1.0):
        y = sign * RAIL
        for x0 in np.arange(-80.0, LENGTH + 80.0, 400.0):
            b.add(g.box_minmax((x0, y - 0.03, 0.5), (x0 + 400.0, y + 0.03, 0.85), g.METAL))
        for x in np.arange(-80.0, LENGTH + 80.0, POST_PITCH):
            yc = y + sign * 0.12
            b.add(g.box((x, yc, 0.375), (0.1, 0.15, 0.75), 0.0, g.METAL))
        for x in np.arange(-50.0, LENGTH + 80.0, 50.0):
            b.add(g.box((x, y + sign * 0.5, 0.55), (0.12, 0.12, 1.1), 0.0, g.PAINT))


def _tree(b: g.MeshBuilder, rng: np.random.Generator, xy, z0: float) -> None:
    """A broadleaf tree at xy standing on z0 (m): bark trunk and a porous crown."""
    trunk_h, rxy, rz = rng.uniform(2.0, 3.5), rng.uniform(2.0, 4.0), rng.uniform(1.8, 3.2)
    centre = (xy[0], xy[1], z0 + trunk_h + 0.8 * rz)
    b.add(g.cylinder(xy, rng.uniform(0.15, 0.4), trunk_h + rz, z0, g.BARK, 10))
    b.add(g.porous(g.ellipsoid(centre, (rxy, rxy * rng.uniform(0.8, 1.1), rz), g.FOLIAGE, 8)))


def _vegetation(b: g.MeshBuilder, rng: np.random.Generator, z) -> None:
    """Groups of 3-15 trees 17-60 m from the median, 20-120 m apart, bushes along the
    verges and a road sign every 80-200 m."""
    for side, sign in ((0, -1.0), (1, 1.0)):
        x = rng.uniform(-60.0, 60.0)
        while x < LENGTH + 60.0:
            for _ in range(int(rng.integers(3, 16))):
                ay = rng.uniform(RAIL + 4.0, 60.0)
                xt = x + rng.uniform(-25.0, 25.0)
                zt = float(z(np.array([xt]), np.array([ay]), side)[0]) - 0.2
                _tree(b, rng, (xt, sign * ay), zt)
            x += rng.uniform(20.0, 120.0)
        for xb in np.arange(-60.0, LENGTH + 60.0, 9.0):
            if rng.random() < 0.5:
                ay = RAIL + rng.uniform(2.5, 5.0)
                zb = float(z(np.array([xb]), np.array([ay]), side)[0])
                r = rng.uniform(0.6, 1.4)
                b.add(g.porous(g.ellipsoid((xb, sign * ay, zb + 0.5 * r), (r, r, 0.7 * r)), 2.0))
        x = rng.uniform(0.0, 100.0)
        while x < LENGTH + 60.0:
            y = sign * (RAIL + 1.2)
            b.add(g.cylinder((x, y), 0.05, 2.6, 0.0, g.METAL, 8))
            w, h = rng.uniform(1.0, 2.5), rng.uniform(0.8, 2.0)
            b.add(g.box((x, y, 2.6 + 0.5 * h), (0.05, w, h), 0.0, g.PAINT))
            x += rng.uniform(80.0, 200.0)


def _structures(b: g.MeshBuilder) -> None:
    """The overpasses (deck 5.5-6.7 m over the road, piers at the rails and the median),
    the sign gantries and the noise wall on the right."""
    for x in OVERPASSES:
        b.add(g.box_minmax((x - 6.0, -60.0, 5.5), (x + 6.0, 60.0, 6.7), g.CONCRETE))
        b.add(g.box_minmax((x - 6.0, -60.0, 6.7), (x - 5.8, 60.0, 7.7), g.METAL))
        b.add(g.box_minmax((x + 5.8, -60.0, 6.7), (x + 6.0, 60.0, 7.7), g.METAL))
        for y in (-RAIL - 2.5, 0.0, RAIL + 2.5):
            b.add(g.box((x, y, 2.75), (1.2, 0.9 if y else 0.8, 5.5), 0.0, g.CONCRETE))
    for x in GANTRIES:
        for y in (-RAIL - 1.0, RAIL + 1.0):
            b.add(g.cylinder((x, y), 0.25, 7.2, 0.0, g.METAL, 12))
        b.add(g.box_minmax((x - 0.3, -RAIL - 1.0, 6.6), (x + 0.3, RAIL + 1.0, 7.2), g.METAL))
        for y in (-9.0, -4.0, 4.0, 9.0):
            b.add(g.box((x - 0.4, y, 5.8), (0.15, 3.6, 2.2), 0.0, g.PAINT))
    x0, x1 = NOISE_WALL
    b.add(g.wall((x0, -RAIL - 2.5), (x1, -RAIL - 2.5), 4.5, 0.3))
    for x in np.arange(x0, x1 + 0.1, 5.0):  # the wall's steel posts on its road side
        b.add(g.box((x, -RAIL - 2.3, 2.3), (0.2, 0.15, 4.6), 0.0, g.METAL))


def _traffic(rng: np.random.Generator) -> list[Pedestrian]:
    """Vehicles (boxes) driving the lanes back and forth over the whole length: trucks in
    the right lane, faster cars in the left lane, oncoming cars and trucks on the other
    carriageway."""
    span = (-60.0, LENGTH + 60.0)
    out: list[Pedestrian] = []

    def add(y: float, speed: tuple[float, float], size, oncoming: bool, n: int) -> None:
        for _ in range(n):
            p0, p1 = ((span[1], y), (span[0], y)) if oncoming else ((span[0], y), (span[1], y))
            out.append(
                Pedestrian(p0, p1, rng.uniform(*speed), size=size,
                           phase=rng.uniform(0.0, 2.0 * (span[1] - span[0])))
            )  # fmt: skip

    add(-LANES[2], (21.0, 24.0), (12.0, 2.5, 3.6), False, 6)
    add(-LANES[0], (29.0, 36.0), (4.6, 1.8, 1.5), False, 6)
    add(LANES[1], (24.0, 33.0), (4.6, 1.8, 1.5), True, 8)
    add(LANES[2], (21.0, 24.0), (12.0, 2.5, 3.6), True, 5)
    return out


def _drive(rng: np.random.Generator) -> Trajectory:
    """The straight path in the middle lane of the carriageway at y < 0: from standstill
    up to 25 m/s and back to a stop at the end."""
    x = np.arange(0.0, LENGTH + 1e-9, 0.05)
    xy = np.column_stack([x, np.full_like(x, -CAR_LANE)])
    v_limit = np.full_like(x, SPEED)
    return route_trajectory(
        xy, speed_limit=v_limit, stops=[(0.0, 1.0)], height=CAR_SENSOR_HEIGHT, rng=rng
    )


def highway(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """The motorway drive (see the module docstring); deterministic for a seed.
    ``pedestrians``: the traffic."""
    rng = np.random.default_rng([seed, 2028])
    b = g.MeshBuilder()
    z = _verge_height(rng)
    _terrain(b, rng, z)
    _barriers(b)
    _vegetation(b, rng, z)
    _structures(b)
    movers = _traffic(rng) if pedestrians else []
    traj = _drive(rng)
    return Scene.from_builder(
        "highway",
        b,
        trajectory=traj,
        pedestrians=movers,
        loop_max_radius=80.0,
        revisit_radius=8.0,
        sensor=scene_sensor("highway"),
        description=(
            f"straight motorway drive {traj.length:.0f} m at up to {SPEED:g} m/s: guard "
            "rails, open verges, tree groups, overpasses, traffic"
        ),
    )
