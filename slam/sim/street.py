"""The ``street`` scene: a car drives 880 m along one straight street at 14-15 m/s.

Made to test front ends on a route nobody tuned them for (``benchmarks/unseen_sweep.py``):
the first 110 m are a city street as in :mod:`slam.sim.urban` (20 m between facades,
parked cars, poles, trees), then a wide avenue of 440 m (40 m between plain facades of
long buildings with one window pitch, three lanes each way, a median with a lamp pole
every 40 m, no parked cars, no trees: few features across the road and a repeating
pattern along it), then a city street again. Cross streets every 150-220 m open the
facades (junctions, with buildings down the cross street). The car starts standing,
accelerates to 15 m/s, stops at the junction at 300 m (3 s) and at the one at 660 m (4 s);
oncoming cars on the other side of the road, pedestrians on the sidewalks. Realistic sensor
errors (:meth:`LidarModel.realistic`), like the urban drive.

Timeline of the drive (first 300 frames at 10 Hz): 0-10 s accelerating in the city street,
~10-21 s at 15 m/s (the avenue from 110 m), braking to the stop at 300 m (~27 s), 3 s
standing, then off again.
"""

from __future__ import annotations

import numpy as np

from slam.sim import geometry as g
from slam.sim.registry import scene_sensor
from slam.sim.scene import Pedestrian, Scene
from slam.sim.scenes import _facade, _to_world
from slam.sim.trajectory import Trajectory, route_trajectory
from slam.sim.urban import CAR_SENSOR_HEIGHT, _block_side, _street_furniture

LENGTH = 880.0  # m of the street driven (x from 0)
AVENUE = (110.0, 550.0)  # x range (m) of the wide avenue
JUNCTIONS = (110.0, 300.0, 450.0, 660.0, 810.0)  # x of the cross streets' centres (m)
STOPS = ((300.0, 3.0), (660.0, 4.0))  # (x of the junction centre, dwell s)
STOP_BEFORE = 14.0  # m before the junction centre the car stops
CROSS_HALF = 10.0  # m: half the width of a cross street (facade to facade)
STREET = {"facade": 10.0, "curb": 6.5, "lane": 2.2}  # city street (m from the centre line)
WIDE = {"facade": 20.0, "curb": 14.0, "lane": 6.75}  # avenue: 3 x 3.5 m lanes, middle one
SPEED = (15.0, 15.0, 14.0)  # m/s: street, avenue, street again


def _pieces(x0: float, x1: float) -> list[tuple[float, float]]:
    """The stretches of [x0, x1] between cross streets (facades open at junctions)."""
    cuts = [x for x in JUNCTIONS if x0 < x < x1]
    edges = [x0] + [c for x in cuts for c in (x - CROSS_HALF, x + CROSS_HALF)] + [x1]
    return [(a, b) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a > 2.0]


def _plain_side(b: g.MeshBuilder, p0, p1, rng: np.random.Generator) -> None:
    """Long plain buildings along p0 -> p1 (the avenue on the left): 60-110 m each, one
    window pitch for the whole avenue, heights 12-18 m."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.hypot(*(p1 - p0)))
    u_dir = (p1 - p0) / length
    yaw = float(np.arctan2(u_dir[1], u_dir[0]))
    u = 0.0
    while u < length - 1.0:
        w = min(rng.uniform(60.0, 110.0), length - u)
        if length - u - w < 20.0:
            w = length - u
        a, c = p0 + u * u_dir, p0 + (u + w) * u_dir
        h = float(rng.choice([12.0, 15.0, 18.0]))
        b.add(_facade(a, c, h, pitch=3.0, win_w=1.6))
        b.add(_to_world([g.box_minmax((0.0, -12.0, 0.0), (w, -2.3, h), g.CONCRETE)], a, yaw))
        u += w


def _cross_street(b: g.MeshBuilder, x: float, half_road: float, rng: np.random.Generator) -> None:
    """A cross street at x: facades along it on both sides from the main street's
    facades (``half_road`` m from its centre line) out to 45 m, a building across its end
    (every facade walked with the cross street on its left)."""
    w, e, h = x - CROSS_HALF, x + CROSS_HALF, half_road
    for p, q in (
        ((w, 45.0), (w, h)),
        ((e, h), (e, 45.0)),
        ((w, -h), (w, -45.0)),
        ((e, -45.0), (e, -h)),
    ):
        _block_side(b, p, q, rng)
    b.add(_facade((e, 53.0), (w, 53.0), 14.0))
    b.add(_facade((w, -53.0), (e, -53.0), 14.0))


_SECTIONS = ((-40.0, AVENUE[0], STREET), (*AVENUE, WIDE), (AVENUE[1], LENGTH + 40.0, STREET))


def _sections(b: g.MeshBuilder, rng: np.random.Generator) -> None:
    """Each section (street, wide avenue, street): raised sidewalks, facades on both sides,
    street furniture along the streets and the avenue's median with its lamp poles."""
    for x0, x1, dims in _SECTIONS:
        f, curb = dims["facade"], dims["curb"]
        for a, c in _pieces(x0, x1):
            for side in (-1.0, 1.0):  # raised sidewalks from the curb to the facades
                lo, hi = sorted((side * curb, side * (f + 2.0)))
                b.add(g.box_minmax((a, lo, 0.0), (c, hi, 0.15), g.CONCRETE))
            # facades walked with the street on their left: south side east-going
            if dims is WIDE:
                _plain_side(b, (a, -f), (c, -f), rng)
                _plain_side(b, (c, f), (a, f), rng)
            else:
                _block_side(b, (a, -f), (c, -f), rng)
                _block_side(b, (c, f), (a, f), rng)
            if dims is STREET and c - a > 20.0:
                for q0, q1 in (((a + 4.0, 0.0), (c - 4.0, 0.0)), ((c - 4.0, 0.0), (a + 4.0, 0.0))):
                    _street_furniture(b, q0, q1, rng, trees=True, parked=rng.uniform(0.3, 0.6))
            if dims is WIDE:  # the median: a raised strip with a lamp pole every 40 m
                b.add(g.box_minmax((a + 2.0, -1.5, 0.0), (c - 2.0, 1.5, 0.15), g.CONCRETE))
                for u in np.arange(a + 8.0, c - 4.0, 40.0):
                    b.add(g.cylinder((u, 0.0), 0.1, 9.0, 0.15, g.METAL, 8))


def _ends(b: g.MeshBuilder, rng: np.random.Generator) -> None:
    """The cross streets at the junctions and the buildings across both ends of the street."""
    for x in JUNCTIONS:
        half = (WIDE if AVENUE[0] <= x <= AVENUE[1] else STREET)["facade"]
        _cross_street(b, x, half, rng)
    # buildings across both ends of the street, facing it
    b.add(_facade((-48.0, 12.0), (-48.0, -12.0), 16.0))
    b.add(_facade((LENGTH + 48.0, -12.0), (LENGTH + 48.0, 12.0), 16.0))


def _movers(rng: np.random.Generator) -> list[Pedestrian]:
    """Walkers on both sidewalks of every section, and oncoming traffic (9-13 m/s) on the
    other half of the road (the avenue's lanes at 3.25 and 6.75 m from its centre line)."""
    peds: list[Pedestrian] = []
    for x0, x1, dims in _SECTIONS:
        for side in (-1.0, 1.0):
            y = side * (dims["curb"] + 1.5)
            peds.append(
                Pedestrian(
                    (x0 + 5.0, y), (x1 - 5.0, y), rng.uniform(1.0, 1.5),
                    phase=rng.uniform(0.0, 2.0 * (x1 - x0)), z=(0.15, 0.15),
                )
            )  # fmt: skip
    # oncoming traffic on the other half of the road (the avenue's lanes at 3.25 and
    # 6.75 m from its centre line)
    lanes = [(x0, x1, 2.2) for x0, x1, d in _SECTIONS if d is STREET]
    lanes += [(*AVENUE, 3.25), (*AVENUE, 6.75)]
    for x0, x1, lane in lanes:
        peds.append(
            Pedestrian(
                (x1, lane), (x0, lane), rng.uniform(9.0, 13.0), size=(4.4, 1.8, 1.5),
                phase=rng.uniform(0.0, 2.0 * (x1 - x0)),
            )
        )  # fmt: skip
    return peds


def _drive(rng: np.random.Generator) -> Trajectory:
    """The path on the right lane (y < 0), moving to the avenue's middle lane and back, at
    the sections' speeds with the junction stops."""
    x = np.arange(0.0, LENGTH + 1e-9, 0.05)
    ramp = lambda x0, x1: np.clip((x - x0) / (x1 - x0), 0.0, 1.0)  # noqa: E731
    s_ramp = lambda u: u * u * (3.0 - 2.0 * u)  # noqa: E731
    wide_share = s_ramp(ramp(AVENUE[0] - 50.0, AVENUE[0] + 10.0)) - s_ramp(
        ramp(AVENUE[1] - 10.0, AVENUE[1] + 50.0)
    )
    y = -(STREET["lane"] + (WIDE["lane"] - STREET["lane"]) * wide_share)
    xy = np.column_stack([x, y])
    v_limit = np.where(x < AVENUE[0], SPEED[0], np.where(x < AVENUE[1], SPEED[1], SPEED[2]))
    stops = [(0.0, 1.0)] + [(xj - STOP_BEFORE, dw) for xj, dw in STOPS]
    return route_trajectory(xy, speed_limit=v_limit, stops=stops, height=CAR_SENSOR_HEIGHT, rng=rng)


def street(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """The straight street drive (see the module docstring); deterministic for a seed."""
    rng = np.random.default_rng([seed, 2027])
    b = g.MeshBuilder()
    b.add(g.ground((-60.0, LENGTH + 60.0), (-70.0, 70.0), 0.0, g.ASPHALT))
    _sections(b, rng)
    _ends(b, rng)
    peds = _movers(rng) if pedestrians else []
    traj = _drive(rng)
    return Scene.from_builder(
        "street",
        b,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=80.0,
        revisit_radius=8.0,
        sensor=scene_sensor("street"),
        description=(
            f"straight street drive {traj.length:.0f} m at up to {max(SPEED):g} m/s, a "
            f"{AVENUE[1] - AVENUE[0]:.0f} m wide avenue with few features, {len(STOPS)} "
            "junction stops"
        ),
    )
