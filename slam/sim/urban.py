"""The ``urban`` scene: a car drives ~1.26 km through a grid of city streets at up to 15 m/s.

Streets (20 m between facades: two 4.5 m driving lanes, 2 m parking lanes, 3.5 m raised
sidewalks) form a 2 x 1 grid of blocks (150 x 120 m) with stub streets leading out of
it. Blocks are lined with buildings of different heights with recessed windows, separated
by driveways that open onto courtyard walls; parked cars, lamp poles, street trees with
porous crowns, signs, pedestrians on the sidewalks and moving cars on lanes the route
does not use. The car (sensor on the roof, 1.8 m) starts at the south-west junction,
drives east through two junctions, loops around the east block, comes back west on the
first street (opposite direction, the other lane 4.4 m away), loops around the west
block and drives east on the north street it drove westwards before. It stops at red
lights and before turns (speed 0 for 3-6 s), brakes to ~4-5 m/s in turns, pitches when
braking and rolls in turns. Realistic sensor errors (:meth:`LidarModel.realistic`).
"""

from __future__ import annotations

import numpy as np

from slam.sim import geometry as g
from slam.sim.registry import scene_sensor
from slam.sim.scene import Pedestrian, Scene
from slam.sim.scenes import _facade, _to_world
from slam.sim.trajectory import Trajectory, lane_route, route_trajectory

CAR_SENSOR_HEIGHT = 1.8  # m: roof-mounted LiDAR (KITTI's HDL-64 is at 1.73 m)
BLOCK_X, BLOCK_Y = 150.0, 120.0  # m between street centre lines
LANE = 2.2  # m right of the centre line
CURB, FACADE = 6.5, 10.0  # m from the centre line: sidewalk edge, building faces
PARKING = 5.4  # m: centre of the parking lane
STUB = 45.0  # m: streets leaving the grid end with a building across this far out

# Junctions (street centres) and the route through them.
_X = (0.0, BLOCK_X, 2 * BLOCK_X)
_Y = (0.0, BLOCK_Y)
A, B, C = (0.0, 0.0), (BLOCK_X, 0.0), (2 * BLOCK_X, 0.0)
F, E, D = (0.0, BLOCK_Y), (BLOCK_X, BLOCK_Y), (2 * BLOCK_X, BLOCK_Y)
ROUTE = (A, B, C, D, E, B, A, F, E, D)  # 1260 m between junction centres
# Speed limit (m/s) of each leg of ROUTE.
LEG_SPEED = (15.0, 15.0, 12.0, 14.0, 11.0, 15.0, 12.0, 14.0, 15.0)
# Stops: (index of the junction in ROUTE, metres before its centre, dwell s); a stop at
# node 0 waits at the start.
STOPS = ((0, 0.0, 1.0), (1, 16.0, 6.0), (4, 18.0, 4.0), (6, 18.0, 5.0), (8, 16.0, 3.0))


def urban_path(ds: float = 0.05) -> np.ndarray:
    """The car's path (K,2) on the right lane through :data:`ROUTE`, turns rounded."""
    return lane_route(np.asarray(ROUTE), lane_offset=LANE, ds=ds)


def _leg_index(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length (K,) of the path and the ROUTE leg (K,) each sample belongs to."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    nodes = np.asarray(ROUTE)
    # Distance along the route between junction centres, matched by arc length.
    leg_len = np.hypot(*np.diff(nodes, axis=0).T)
    bounds = np.concatenate([[0.0], np.cumsum(leg_len)]) * (s[-1] / leg_len.sum())
    return s, np.clip(np.searchsorted(bounds, s, side="right") - 1, 0, len(leg_len) - 1)


def _node_arclength(xy: np.ndarray, s: np.ndarray, k: int) -> float:
    """Arc length (m) of the path point nearest to ROUTE node k, searched in order."""
    nodes = np.asarray(ROUTE)
    leg_len = np.hypot(*np.diff(nodes, axis=0).T)
    guess = np.concatenate([[0.0], np.cumsum(leg_len)])[k] * (s[-1] / leg_len.sum())
    near = np.flatnonzero(np.abs(s - guess) < 40.0)
    d = np.hypot(*(xy[near] - nodes[k]).T)
    return float(s[near[np.argmin(d)]])


def _car(b: g.MeshBuilder, xy, yaw: float, rng: np.random.Generator) -> None:
    """A parked car: body 4.4 x 1.8 x 0.85 m on 0.3 m clearance (wheels), cabin on top."""
    length = rng.uniform(3.9, 4.8)
    refl = rng.choice([g.METAL, g.PAINT, 0.25])
    b.add(g.box((xy[0], xy[1], 0.3), (length - 0.6, 1.6, 0.6), yaw, g.ASPHALT * 0.5))
    b.add(g.box((xy[0], xy[1], 0.75), (length, 1.8, 0.7), yaw, refl))
    back = -0.2 * length
    cx, cy = xy[0] + back * np.cos(yaw), xy[1] + back * np.sin(yaw)
    b.add(g.box((cx, cy, 1.35), (0.5 * length, 1.6, 0.55), yaw, g.GLASS * 2))


def _block_side(b: g.MeshBuilder, p0, p1, rng: np.random.Generator, depth: float = 12.0) -> None:
    """Buildings along the block side p0 -> p1 (the street on its left): facades with
    windows, 7-24 m high, 14-40 m long, a solid body ``depth`` m deep behind; some
    driveways (4-9 m) between them open onto a courtyard wall 16-22 m behind the faces."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.hypot(*(p1 - p0)))
    u_dir = (p1 - p0) / length
    yaw = float(np.arctan2(u_dir[1], u_dir[0]))
    u = 0.0
    while u < length - 1.0:
        if u > 8.0 and length - u > 14.0 and rng.random() < 0.3:
            w = rng.uniform(4.0, 9.0)
            back = rng.uniform(16.0, 22.0)
            parts = [g.box_minmax((u - 1.0, -back - 1.0, 0.0), (u + w + 1.0, -back, 9.0))]
            b.add(_to_world(parts, p0, yaw))
            u += w
            continue
        w = min(rng.uniform(14.0, 40.0), length - u)
        if length - u - w < 8.0:
            w = length - u
        h = float(rng.choice([7.0, 10.0, 13.0, 16.0, 20.0, 24.0]))
        a, c = p0 + u * u_dir, p0 + (u + w) * u_dir
        pitch = rng.uniform(2.6, 4.0)
        b.add(_facade(a, c, h, pitch=pitch, win_w=min(1.6, pitch - 0.8)))
        body = [g.box_minmax((0.0, -depth, 0.0), (w, -2.3, h), g.CONCRETE)]
        b.add(_to_world(body, a, yaw))
        u += w


def _street_furniture(
    b: g.MeshBuilder,
    p0,
    p1,
    rng: np.random.Generator,
    *,
    trees: bool,
    parked: float,
) -> None:
    """Along the street side from p0 to p1 (centre-line points, the side on the right):
    parked cars (occupancy ``parked``), lamp poles every ~30 m, street trees every ~14 m
    (porous crowns) when ``trees``, a sign near each end."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.hypot(*(p1 - p0)))
    e = (p1 - p0) / length
    n = np.array([e[1], -e[0]])
    yaw = float(np.arctan2(e[1], e[0]))

    def at(u: float, v: float) -> np.ndarray:
        return p0 + u * e + v * n

    u = rng.uniform(0.0, 5.0)
    while u < length - 5.0:  # parking slots of 6 m
        if rng.random() < parked:
            _car(b, at(u + 3.0, PARKING + rng.uniform(-0.15, 0.15)), yaw, rng)
        u += 6.0
    for u in np.arange(rng.uniform(5.0, 15.0), length - 3.0, rng.uniform(26.0, 34.0)):
        xy = at(u, CURB + 0.4)
        b.add(g.cylinder(xy, 0.08, 7.5, 0.0, g.METAL, 8))
        arm = at(u, CURB - 0.6)
        b.add(g.box((arm[0], arm[1], 7.4), (0.4, 2.0, 0.15), yaw, g.METAL))
    if trees:
        for u in np.arange(rng.uniform(4.0, 10.0), length - 3.0, rng.uniform(12.0, 16.0)):
            xy = at(u + rng.uniform(-1.0, 1.0), 8.2)
            trunk = rng.uniform(2.6, 3.4)
            b.add(g.cylinder(xy, rng.uniform(0.12, 0.2), trunk + 0.8, 0.15, g.BARK, 10))
            r = rng.uniform(1.8, 2.6)
            crown = g.ellipsoid((xy[0], xy[1], trunk + r), (r, r, 1.2 * r), g.FOLIAGE, 8)
            b.add(g.porous(crown, g.CROWN_EXTINCTION))
    for u in (2.0, length - 2.0):
        xy = at(u, CURB + 0.5)
        b.add(g.cylinder(xy, 0.035, 2.6, 0.0, g.METAL, 6))
        b.add(g.box((xy[0], xy[1], 2.3), (0.05, 0.7, 0.7), yaw, g.PAINT))


def _street_pieces() -> list[tuple[np.ndarray, np.ndarray]]:
    """Centre-line pieces (p0, p1) between junctions and out to the stub ends."""
    xs = (-STUB, *_X, _X[-1] + STUB)
    ys = (-STUB, *_Y, _Y[-1] + STUB)
    pieces = []
    for y in _Y:
        pieces += [
            (np.array([a, y]), np.array([c, y])) for a, c in zip(xs[:-1], xs[1:], strict=True)
        ]
    for x in _X:
        pieces += [
            (np.array([x, a]), np.array([x, c])) for a, c in zip(ys[:-1], ys[1:], strict=True)
        ]
    return pieces


def _blocks(b: g.MeshBuilder, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> None:
    """The blocks: the cells between street lines, clipped to the world (lo, hi; m); a raised
    sidewalk (0.15 m) up to CURB from each street and buildings from FACADE inwards."""
    x_lines, y_lines = (lo[0], *_X, hi[0]), (lo[1], *_Y, hi[1])
    for i in range(len(x_lines) - 1):
        for j in range(len(y_lines) - 1):
            x0, x1 = x_lines[i], x_lines[i + 1]
            y0, y1 = y_lines[j], y_lines[j + 1]
            street = (i > 0, i < len(x_lines) - 2, j > 0, j < len(y_lines) - 2)  # W E S N
            ins = [CURB if s else 0.0 for s in street]
            b.add(
                g.box_minmax(
                    (x0 + ins[0], y0 + ins[2], 0.0), (x1 - ins[1], y1 - ins[3], 0.15), g.CONCRETE
                )
            )
            f = [FACADE if s else 0.0 for s in street]
            c00, c10 = (x0 + f[0], y0 + f[2]), (x1 - f[1], y0 + f[2])
            c11, c01 = (x1 - f[1], y1 - f[3]), (x0 + f[0], y1 - f[3])
            # Each side with a street: walk it with the street on the left.
            if street[2]:
                _block_side(b, c10, c00, rng)
            if street[1]:
                _block_side(b, c11, c10, rng)
            if street[3]:
                _block_side(b, c01, c11, rng)
            if street[0]:
                _block_side(b, c00, c01, rng)


def _stub_ends(b: g.MeshBuilder) -> None:
    """A building across each street leaving the grid, 8 m past its end."""
    for p0, p1 in _street_pieces():
        for end, other in ((p0, p1), (p1, p0)):
            if np.all((end >= [_X[0], _Y[0]]) & (end <= [_X[-1], _Y[-1]])):
                continue
            e = (end - other) / np.hypot(*(end - other))
            n = np.array([-e[1], e[0]])
            a, c = end + 8.0 * e - FACADE * n, end + 8.0 * e + FACADE * n
            b.add(_facade(c, a, 14.0))
            b.add(_to_world([g.box_minmax((0.0, -12.0, 0.0), (20.0, -2.3, 14.0))], c, _yaw(a - c)))


def _furniture(b: g.MeshBuilder, rng: np.random.Generator) -> None:
    """Street furniture on both sides of every piece, clear of the junctions (14 m); trees
    along 60 % of the pieces, 30-70 % of the kerb parked."""
    for p0, p1 in _street_pieces():
        e = (p1 - p0) / np.hypot(*(p1 - p0))
        a, c = p0 + 14.0 * e, p1 - 14.0 * e
        trees = bool(rng.random() < 0.6)
        for q0, q1 in ((a, c), (c, a)):
            _street_furniture(b, q0, q1, rng, trees=trees, parked=rng.uniform(0.3, 0.7))


def _movers(rng: np.random.Generator) -> list[Pedestrian]:
    """Walkers on the sidewalks of every other street piece, and moving cars (boxes driving
    back and forth at 7-11 m/s) on the lanes the route never drives."""
    peds: list[Pedestrian] = []
    for p0, p1 in _street_pieces()[::2]:  # walkers on the sidewalks
        e = (p1 - p0) / np.hypot(*(p1 - p0))
        n = np.array([e[1], -e[0]])
        side = rng.choice([-1.0, 1.0]) * rng.uniform(7.6, 9.0)
        length = float(np.hypot(*(p1 - p0)))
        q0, q1 = p0 + 15.0 * e + side * n, p1 - 15.0 * e + side * n
        peds.append(
            Pedestrian(
                tuple(q0), tuple(q1), rng.uniform(1.0, 1.5), phase=rng.uniform(0, 2 * length),
                z=(0.15, 0.15),
            )
        )  # fmt: skip
    # Moving cars on lanes the route never drives (oncoming lanes of streets driven
    # once, and the stubs): boxes driving back and forth.
    for p0, p1, _name in _traffic_lanes():
        length = float(np.hypot(*(np.subtract(p1, p0))))
        peds.append(
            Pedestrian(
                p0, p1, rng.uniform(7.0, 11.0), size=(4.4, 1.8, 1.5),
                phase=rng.uniform(0, 2 * length),
            )
        )  # fmt: skip
    return peds


def _drive(rng: np.random.Generator) -> Trajectory:
    """The car's drive along ``urban_path`` at the legs' speed limits, with the STOPS."""
    s_path = urban_path()
    s, leg = _leg_index(s_path)
    v_limit = np.asarray(LEG_SPEED)[leg]
    stops = [
        (0.0 if k == 0 else _node_arclength(s_path, s, k) - before, dw) for k, before, dw in STOPS
    ]
    return route_trajectory(
        s_path,
        speed_limit=v_limit,
        stops=stops,
        height=CAR_SENSOR_HEIGHT,
        rng=rng,
    )


def urban(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """The city drive (see the module docstring); deterministic for a seed."""
    rng = np.random.default_rng([seed, 2026])
    b = g.MeshBuilder()
    lo = np.array([-STUB - 25.0, -STUB - 25.0])
    hi = np.array([_X[-1] + STUB + 25.0, _Y[-1] + STUB + 25.0])
    b.add(g.ground((lo[0], hi[0]), (lo[1], hi[1]), 0.0, g.ASPHALT))
    _blocks(b, lo, hi, rng)
    _stub_ends(b)
    _furniture(b, rng)
    peds = _movers(rng) if pedestrians else []
    traj = _drive(rng)
    return Scene.from_builder(
        "urban",
        b,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=80.0,
        revisit_radius=8.0,
        sensor=scene_sensor("urban"),
        description=(
            f"urban drive {traj.length:.0f} m through a 2x1 grid of {BLOCK_X:g}x{BLOCK_Y:g} m "
            f"blocks, up to {max(LEG_SPEED):g} m/s, {len(STOPS)} stops, streets revisited in "
            "the opposite direction"
        ),
    )


def _yaw(d) -> float:
    """Heading (rad) of the direction d (x, y)."""
    return float(np.arctan2(d[1], d[0]))


def _traffic_lanes() -> list[tuple[tuple[float, float], tuple[float, float], str]]:
    """(p0, p1, name) of lanes with moving cars, 14 m clear of junction centres."""
    (bx, _), (cx, _) = B, C
    lanes = [
        ((bx + 16.0, LANE), (cx - 16.0, LANE), "oncoming on B->C"),
        ((cx - LANE, 16.0), (cx - LANE, D[1] - 16.0), "oncoming on C->D"),
        ((bx + LANE, 16.0), (bx + LANE, E[1] - 16.0), "oncoming on E->B"),
        ((-LANE, 16.0), (-LANE, F[1] - 16.0), "oncoming on A->F"),
    ]
    for p0, p1 in _street_pieces():
        inside = [bool(np.all((p >= [_X[0], _Y[0]]) & (p <= [_X[-1], _Y[-1]]))) for p in (p0, p1)]
        if all(inside):
            continue
        e = (p1 - p0) / np.hypot(*(p1 - p0))
        n = np.array([e[1], -e[0]])
        q0, q1 = p0 + 14.0 * e + LANE * n, p1 - 14.0 * e + LANE * n
        if not inside[0]:
            q0 = p0 + 4.0 * e + LANE * n
        if not inside[1]:
            q1 = p1 - 4.0 * e + LANE * n
        lanes.append((tuple(q0), tuple(q1), "stub"))
    return lanes
