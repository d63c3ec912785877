"""The ``building`` scenes: one floor of a large public building under construction, the
experiment of LeGO-LOAM-LPB (paper 001, section 4.2.2: a hospital outpatient building,
one standard floor 292 x 142 m, 6 m high).

The floor is a ladder of corridors 3.5 m wide: four long east-west corridors (y = 8, 50,
92, 134 m, 288 m between the end spines) joined by two north-south spines along the west
and east exterior walls and a short middle spine between the first two. The corridors
are windowless, with parallel painted or bare-concrete walls, rooms behind them (open
doorways show the room, closed doors are shallow recesses), pilasters on the 8.4 m
structural grid and plain stretches of 26-30 m without either (the degenerate corridors
of the paper's Figure 11). Open spaces: a large-span hall on three of the corridors with a
column grid, and a 52 x 32 m atrium on the third corridor that is open above the floor
up to a roof at 22 m. Mixed materials: painted and concrete walls, glass room fronts,
metal fire doors and ducts, wooden doors, insulation stacks.

Moving things: workers walking along the corridors (boxes of 0.5 x 0.5 x 1.7 m, 0.8-1.4
m/s, 1.1 m off the centre line) and machinery in the halls and the atrium (scissor lifts
and material carts, 0.3-0.9 m/s), all clear of the robot's route.

Routes (a ground robot, VLP-16 at 0.88 m like the paper's platform, at most 3 m/s):

- ``building``: the S-shaped route of the experiment, ~1.28 km without revisits: the
  four corridors driven in turn (east, west, east, west), joined by the east, west and
  east spines; one 2 s stop in the third corridor.
- ``building_loop``: a ~0.41 km loop that comes back: east along the first corridor, up
  the middle spine, west along the second corridor, down the west spine and east along
  the first corridor again, 40 m past its start (for loop closure).

Both use the realistic VLP-16 (per-beam calibration, range noise, mixed pixels at the
many depth edges of doorways and pilasters). Everything random draws from the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.sim import geometry as g
from slam.sim.registry import scene_sensor
from slam.sim.scene import Pedestrian, Scene
from slam.sim.trajectory import Trajectory, lane_route, route_trajectory

SENSOR_HEIGHT = 0.88  # m: the paper's RS-Helios-16P above the floor (section 4.1)
MAX_SPEED = 3.0  # m/s: the platform's maximum velocity (section 4.1)
FLOOR_X, FLOOR_Y, STOREY = 292.0, 142.0, 6.0  # m (section 4.2.2)
EXT = 0.3  # exterior wall thickness (m)
WIDTH = 3.5  # corridor width (m)
WALL = 0.2  # interior wall thickness (m)
GRID = 8.4  # structural grid (m): columns, pilasters
ROOM_DEPTH = 7.0  # m behind the corridor walls
LANES = (8.0, 50.0, 92.0, 134.0)  # y of the east-west corridors' centre lines (m)
SPINE_W = EXT + WIDTH / 2  # x of the west spine's centre line (m)
SPINE_E = FLOOR_X - EXT - WIDTH / 2  # x of the east spine's centre line (m)
SPINE_M = 146.0  # x of the middle spine (between the first two corridors)
ATRIUM_ROOF = 22.0  # m

# Extra materials (reflectivity 0..1) besides those of slam.sim.geometry.
INSULATION = 0.75  # white insulation boards
PLASTIC = 0.5  # wrapped material, plastic sheeting
MACHINE = 0.55  # painted machinery

# Open spaces (x0, x1, y0, y1) m: the corridors crossing them have no walls there.
HALLS = {
    "hall_a": (70.0, 110.0, EXT, 26.0),
    "hall_b": (196.0, 236.0, 36.0, 64.0),
    "atrium": (120.0, 172.0, 76.0, 108.0),
    "hall_d": (210.0, 240.0, 118.0, FLOOR_Y - EXT),
}

# Stretches (corridor index, x0, x1) without doors or pilasters: plain parallel walls,
# 26-30 m long (a robot in the middle sees the nearest door or pilaster 13-15 m away),
# none where a route starts or turns into a corridor.
PLAIN = ((0, 36.0, 62.0), (1, 60.0, 90.0), (2, 236.0, 266.0), (3, 50.0, 80.0))

S_ROUTE = (
    (SPINE_W, LANES[0]),
    (SPINE_E, LANES[0]),
    (SPINE_E, LANES[1]),
    (SPINE_W, LANES[1]),
    (SPINE_W, LANES[2]),
    (SPINE_E, LANES[2]),
    (SPINE_E, LANES[3]),
    (SPINE_W, LANES[3]),
)
S_STOPS = ((4, 150.0, 2.0),)  # (node, metres after it, dwell s): in the atrium
LOOP_ROUTE = (
    (24.0, LANES[0]),
    (SPINE_M, LANES[0]),
    (SPINE_M, LANES[1]),
    (SPINE_W, LANES[1]),
    (SPINE_W, LANES[0]),
    (64.0, LANES[0]),
)
TURN_LENGTH = 6.0  # m of arc per 90-degree turn (minimum radius 1.9 m)


@dataclass(frozen=True)
class Corridor:
    """A straight corridor: its centre line at ``c`` across ``axis`` ("x": running along
    x at y = c; "y": along y at x = c), its walls from ``u0`` to ``u1`` along it (m)."""

    axis: str
    c: float
    u0: float
    u1: float

    def box(self, u0, u1, v0, v1, z0, z1, refl) -> g.Part:
        """Axis-aligned box in corridor coordinates (u along, v across from the centre
        line, z up; m)."""
        ua, ub = sorted((u0, u1))
        va, vb = sorted((self.c + v0, self.c + v1))
        if self.axis == "x":
            return g.box_minmax((ua, va, z0), (ub, vb, z1), refl)
        return g.box_minmax((va, ua, z0), (vb, ub, z1), refl)

    def world(self, u: float, v: float) -> tuple[float, float]:
        return (u, self.c + v) if self.axis == "x" else (self.c + v, u)


def _lane(k: int) -> Corridor:
    return Corridor("x", LANES[k], SPINE_W + WIDTH / 2, SPINE_E - WIDTH / 2)


def _spines() -> list[Corridor]:
    lo, hi = LANES[0] + WIDTH / 2, LANES[-1] - WIDTH / 2
    return [
        Corridor("y", SPINE_W, lo, hi),
        Corridor("y", SPINE_E, lo, hi),
        Corridor("y", SPINE_M, LANES[0] + WIDTH / 2, LANES[1] - WIDTH / 2),
    ]


def _subtract(a: float, b: float, holes: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The parts of [a, b] outside the intervals ``holes``."""
    out, u = [], a
    for h0, h1 in sorted(holes):
        if h1 <= u or h0 >= b:
            continue
        if h0 > u:
            out.append((u, h0))
        u = max(u, h1)
    if u < b:
        out.append((u, b))
    return [(p, q) for p, q in out if q - p > 0.05]


def _in_plain(k: int | None, u: float) -> bool:
    return k is not None and any(j == k and x0 <= u <= x1 for j, x0, x1 in PLAIN)


def _room_cuts(a: float, c: float, rooms: bool, rng: np.random.Generator) -> list[float]:
    """Positions u (m) of the partitions along a wall stretch (a, c): rooms 6-10 m wide, or
    12-24 m between service doors on walls without rooms; no remainder under 4 m."""
    cuts = [a]
    while cuts[-1] < c:
        w = rng.uniform(6.0, 10.0) if rooms else rng.uniform(12.0, 24.0)
        cuts.append(min(cuts[-1] + w, c))
        if c - cuts[-1] < 4.0:
            cuts[-1] = c
    return cuts


def _doors(
    cuts: list[float], rooms: bool, lane: int | None, rng: np.random.Generator
) -> list[tuple[float, float, str]]:
    """(u0, u1, "open"|"closed") of one door (1.2 or 1.8 m) per room of at least 3.2 m
    outside the plain stretches; open (45 %) only into rooms."""
    doors: list[tuple[float, float, str]] = []
    for r0, r1 in zip(cuts[:-1], cuts[1:], strict=True):
        mid = 0.5 * (r0 + r1)
        if _in_plain(lane, mid) or r1 - r0 < 3.2:
            continue
        dw = 1.8 if rng.random() < 0.25 else 1.2
        u = rng.uniform(r0 + 0.6, r1 - 0.6 - dw)
        is_open = rooms and rng.random() < 0.45
        doors.append((u, u + dw, "open" if is_open else "closed"))
    return doors


def _wall(
    b: g.MeshBuilder,
    rng: np.random.Generator,
    cor: Corridor,
    face: float,
    side: float,
    stretch: tuple[float, float],
    doors: list[tuple[float, float, str]],
    wall_refl: float,
    rooms: bool,
    lane: int | None,
) -> None:
    """The corridor wall of a stretch between its doors, lintels over and panels in the
    closed doors, sometimes (12 % of room walls) a glazed office front; then pilasters on
    the structural grid, clear of doors and of the stretch ends (m)."""
    a, c = stretch
    u = a
    glass_front = rooms and rng.random() < 0.12
    for d0, d1, kind in doors:
        b.add(cor.box(u, d0, face, face + side * WALL, 0.0, STOREY, wall_refl))
        b.add(cor.box(d0, d1, face, face + side * WALL, 2.2, STOREY, wall_refl))
        if kind == "closed":
            refl = g.METAL if rng.random() < 0.4 else g.WOOD
            panel = face + side * 0.08
            b.add(cor.box(d0, d1, panel, panel + side * 0.05, 0.0, 2.2, refl))
        u = d1
    b.add(cor.box(u, c, face, face + side * WALL, 0.0, STOREY, wall_refl))
    if glass_front and not _in_plain(lane, 0.5 * (a + c)):  # a glazed office front
        g0 = rng.uniform(a, max(a, c - 6.0))
        b.add(cor.box(g0, min(g0 + 5.0, c), face - side * 0.02, face, 0.9, 2.6, g.GLASS))
    for u in np.arange(np.ceil((a + 0.6) / GRID) * GRID, c - 0.6, GRID):
        if _in_plain(lane, u) or any(d0 - 0.6 < u < d1 + 0.6 for d0, d1, _ in doors):
            continue
        b.add(cor.box(u - 0.3, u + 0.3, face, face - side * 0.3, 0.0, STOREY, g.CONCRETE))


def _rooms(
    b: g.MeshBuilder,
    rng: np.random.Generator,
    cor: Corridor,
    face: float,
    side: float,
    stretch: tuple[float, float],
    cuts: list[float],
    depth: float,
    back_wall: bool,
) -> None:
    """The rooms behind a wall stretch (``depth`` m): back wall, partitions, and in half of
    them a stack of boards, insulation or a scaffold."""
    back = face + side * (WALL + depth)
    if back_wall:
        b.add(cor.box(*stretch, back, back + side * WALL, 0.0, STOREY, g.CONCRETE))
    for r in cuts:  # partitions between rooms and at the stretch ends
        b.add(cor.box(r - WALL / 2, r + WALL / 2, face, back, 0.0, STOREY, g.CONCRETE))
    for r0, r1 in zip(cuts[:-1], cuts[1:], strict=True):  # what lies in the rooms
        if rng.random() < 0.5:
            continue
        kind = rng.choice(["stack", "insulation", "scaffold"])
        w = min(rng.uniform(1.0, 3.0), r1 - r0 - 1.0)
        u = rng.uniform(r0 + 0.5, r1 - 0.5 - w)
        v = face + side * rng.uniform(1.0, depth - 2.0)
        if kind == "stack":
            b.add(cor.box(u, u + w, v, v + side * 1.0, 0.0, rng.uniform(0.6, 1.6), g.WOOD))
        elif kind == "insulation":
            b.add(cor.box(u, u + w, v, v + side * 1.2, 0.0, rng.uniform(0.8, 2.0), INSULATION))
        else:
            _scaffold(b, cor.world(u, v), rng)


def _side(
    b: g.MeshBuilder,
    rng: np.random.Generator,
    cor: Corridor,
    side: float,
    stretches: list[tuple[float, float]],
    *,
    rooms: bool,
    depth: float = ROOM_DEPTH,
    back_wall: bool = True,
    lane: int | None = None,
) -> None:
    """One side of a corridor (side +1: v > 0) over the wall ``stretches`` (u0, u1):
    the wall with doors (open ones into ``rooms`` 7 m deep, or closed recessed panels),
    pilasters on the structural grid, and the rooms behind it (``depth`` m from the wall;
    without ``back_wall`` they reach an exterior wall)."""
    face = side * WIDTH / 2  # v of the wall face
    wall_refl = g.PAINT if rng.random() < 0.6 else g.CONCRETE
    for a, c in stretches:
        cuts = _room_cuts(a, c, rooms, rng)
        doors = _doors(cuts, rooms, lane, rng)
        _wall(b, rng, cor, face, side, (a, c), doors, wall_refl, rooms, lane)
        if rooms:
            _rooms(b, rng, cor, face, side, (a, c), cuts, depth, back_wall)


def _scaffold(b: g.MeshBuilder, xy, rng: np.random.Generator) -> None:
    """A mobile scaffold tower: four tubes and two platforms (metal, plywood)."""
    sx, sy, h = 1.8, 0.8, rng.uniform(2.5, 4.0)
    for dx in (0.0, sx):
        for dy in (0.0, sy):
            b.add(g.cylinder((xy[0] + dx, xy[1] + dy), 0.025, h, 0.0, g.METAL, 6))
    for z in (0.4, h - 0.1):
        b.add(g.box_minmax((xy[0], xy[1], z), (xy[0] + sx, xy[1] + sy, z + 0.05), g.WOOD))


def _hall(b: g.MeshBuilder, rng: np.random.Generator, name: str) -> None:
    """An open space: walls on its boundary (openings where corridors enter, exterior
    walls already there), a column grid clear of the corridor lines."""
    x0, x1, y0, y1 = HALLS[name]
    top = ATRIUM_ROOF if name == "atrium" else STOREY
    lanes_in = [y for y in LANES if y0 < y < y1]
    for x in (x0, x1):  # west and east walls with the corridor openings
        holes = [(y - WIDTH / 2, y + WIDTH / 2) for y in lanes_in]
        for a, c in _subtract(y0, y1, holes):
            b.add(g.box_minmax((x - WALL / 2, a, 0.0), (x + WALL / 2, c, top), g.CONCRETE))
    for y in (y0, y1):  # south and north walls (the exterior one exists)
        if y <= EXT + 1e-6 or y >= FLOOR_Y - EXT - 1e-6:
            continue
        b.add(g.box_minmax((x0, y - WALL / 2, 0.0), (x1, y + WALL / 2, top), g.PAINT))
    xs = np.arange(np.ceil(x0 / GRID) * GRID, x1 - 1.5, GRID)
    ys = np.arange(np.ceil(y0 / GRID) * GRID, y1 - 1.5, GRID)
    for x in xs:
        for y in ys:
            if x - x0 < 1.5 or min(abs(y - ly) for ly in LANES) < 2.6 or y - y0 < 1.5:
                continue
            if rng.random() < 0.5:
                b.add(g.box((x, y, 0.5 * top), (0.7, 0.7, top), 0.0, g.CONCRETE))
            else:
                b.add(g.cylinder((x, y), 0.4, top, 0.0, g.CONCRETE, 12))
    if name == "atrium":  # an escalator block and a stair core, off the corridor line
        b.add(g.box_minmax((136.0, 99.0, 0.0), (152.0, 102.0, 1.2), g.METAL))
        b.add(g.box_minmax((158.0, 80.0, 0.0), (166.0, 86.0, STOREY), g.CONCRETE))
    else:  # material stacks along the walls
        for _ in range(4):
            x = rng.uniform(x0 + 2.0, x1 - 4.0)
            y = y1 - 2.0 if rng.random() < 0.5 or y0 <= EXT else y0 + 1.0
            w = rng.uniform(1.5, 3.0)
            refl = float(rng.choice([g.WOOD, INSULATION, PLASTIC, g.METAL]))
            b.add(g.box_minmax((x, y - 0.5, 0.0), (x + w, y + 0.5, rng.uniform(0.6, 1.8)), refl))


def _shell(b: g.MeshBuilder) -> None:
    """Slab, ceiling (open over the atrium, which has its own metal roof) and the exterior
    walls of the floor (m)."""
    X, Y = FLOOR_X, FLOOR_Y
    b.add(g.box_minmax((0.0, 0.0, -0.2), (X, Y, 0.0), g.CONCRETE))
    ax0, ax1, ay0, ay1 = HALLS["atrium"]
    for lo, hi in (
        ((0.0, 0.0), (X, ay0)),
        ((0.0, ay1), (X, Y)),
        ((0.0, ay0), (ax0, ay1)),
        ((ax1, ay0), (X, ay1)),
    ):
        b.add(g.box_minmax((*lo, STOREY), (*hi, STOREY + 0.3), g.CONCRETE))
    b.add(g.box_minmax((ax0, ay0, ATRIUM_ROOF), (ax1, ay1, ATRIUM_ROOF + 0.3), g.METAL))
    for lo, hi in (
        ((0.0, 0.0), (X, EXT)),
        ((0.0, Y - EXT), (X, Y)),
        ((0.0, 0.0), (EXT, Y)),
        ((X - EXT, 0.0), (X, Y)),
    ):
        b.add(g.box_minmax((*lo, 0.0), (*hi, STOREY), g.CONCRETE))


def _hall_holes(cor: Corridor, side: float) -> list[tuple[float, float]]:
    """(u0, u1) spans (m) where a hall opens the corridor's wall on ``side`` (0: its axis)."""
    holes = []
    for x0, x1, y0, y1 in HALLS.values():
        lo, hi = (y0, y1) if cor.axis == "x" else (x0, x1)
        u0, u1 = (x0, x1) if cor.axis == "x" else (y0, y1)
        face = cor.c + side * WIDTH / 2
        if lo < face < hi:
            holes.append((u0, u1))
    return holes


def _lanes(b: g.MeshBuilder, rng: np.random.Generator) -> None:
    """East-west corridors: rooms on both sides (up to the exterior on the outer sides of
    the first and last), openings at the halls and at the middle spine, and a duct under
    the ceiling along one side, interrupted by the open spaces."""
    for k in range(len(LANES)):
        cor = _lane(k)
        for side in (-1.0, 1.0):
            holes = _hall_holes(cor, side)
            if (k, side) in ((0, 1.0), (1, -1.0)):
                holes.append((SPINE_M - WIDTH / 2, SPINE_M + WIDTH / 2))
            outer = (k == 0 and side < 0) or (k == len(LANES) - 1 and side > 0)
            u0, u1 = (EXT, FLOOR_X - EXT) if outer else (cor.u0, cor.u1)
            depth = ROOM_DEPTH
            if outer:  # up to the exterior wall
                depth = min(cor.c, FLOOR_Y - cor.c) - WIDTH / 2 - WALL - EXT
            _side(b, rng, cor, side, _subtract(u0, u1, holes), rooms=True,
                  depth=depth, back_wall=not outer, lane=k)  # fmt: skip
        side = rng.choice([-1.0, 1.0])
        for a, c in _subtract(cor.u0, cor.u1, _hall_holes(cor, 0.0)):
            v = side * rng.uniform(0.4, 1.0)
            b.add(cor.box(a, c, v - 0.3, v + 0.3, 5.2, 5.6, g.METAL))


def _floor(rng: np.random.Generator) -> g.MeshBuilder:
    """The static floor: slab, ceiling (open over the atrium), exterior walls, corridors
    with their rooms, halls, ducts."""
    b = g.MeshBuilder()
    _shell(b)
    _lanes(b, rng)
    # North-south spines: service doors and pilasters, no rooms; the outer walls of the
    # end spines are the exterior walls.
    for cor in _spines():
        sides = (1.0,) if cor.c == SPINE_W else (-1.0,) if cor.c == SPINE_E else (-1.0, 1.0)
        holes = [(y - WIDTH / 2, y + WIDTH / 2) for y in LANES]
        for side in sides:
            _side(b, rng, cor, side, _subtract(cor.u0, cor.u1, holes), rooms=False)
    for name in HALLS:
        _hall(b, rng, name)
    return b


def _walkers(rng: np.random.Generator) -> list[Pedestrian]:
    """Workers along the corridors (1.1 m off the centre line) and machinery in the open
    spaces (at least 3 m from any corridor line the robot drives)."""
    peds: list[Pedestrian] = []
    for k in range(len(LANES)):
        cor = _lane(k)
        for _ in range(3):
            length = rng.uniform(15.0, 35.0)
            u = rng.uniform(cor.u0 + 10.0, cor.u1 - 10.0 - length)
            v = rng.choice([-1.0, 1.0]) * 1.1
            p0, p1 = cor.world(u, v), cor.world(u + length, v)
            peds.append(Pedestrian(p0, p1, rng.uniform(0.8, 1.4), phase=rng.uniform(0, 2 * length)))
    for cor in _spines():
        u = rng.uniform(cor.u0 + 5.0, cor.u1 - 25.0) if cor.u1 - cor.u0 > 40 else cor.u0 + 8.0
        p0, p1 = cor.world(u, 1.1), cor.world(u + 18.0, 1.1)
        peds.append(Pedestrian(p0, p1, rng.uniform(0.8, 1.4), phase=rng.uniform(0, 36.0)))
    lift, cart = (2.4, 1.2, 2.4), (1.2, 0.8, 1.1)
    machines = (
        ((74.0, 20.0), (106.0, 20.0), lift, 0.4),
        ((76.0, 3.2), (104.0, 3.2), cart, 0.8),
        ((200.0, 41.0), (232.0, 41.0), lift, 0.3),
        ((204.0, 58.0), (228.0, 58.0), cart, 0.9),
        ((124.0, 81.0), (154.0, 81.0), lift, 0.35),
        ((126.0, 104.0), (166.0, 104.0), cart, 0.7),
        ((214.0, 124.0), (236.0, 124.0), cart, 0.6),
    )
    for p0, p1, size, speed in machines:
        length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
        peds.append(Pedestrian(p0, p1, speed, size=size, phase=rng.uniform(0, 2 * length)))
    # Workers in the atrium and the halls, crossing parallel to the corridors.
    for p0, p1 in (((128.0, 97.0), (164.0, 97.0)), ((80.0, 14.0), (100.0, 14.0))):
        peds.append(Pedestrian(p0, p1, rng.uniform(0.9, 1.3), phase=rng.uniform(0, 40.0)))
    return peds


def route_path(nodes, ds: float = 0.05) -> np.ndarray:
    """The robot's path (K,2) along the corridor centre lines through ``nodes``."""
    return lane_route(
        np.asarray(nodes, dtype=float),
        lane_offset=0.0,
        left_turn_length=TURN_LENGTH,
        right_turn_length=TURN_LENGTH,
        ds=ds,
    )


def robot_trajectory(
    nodes, rng: np.random.Generator, stops: tuple[tuple[int, float, float], ...] = ()
) -> Trajectory:
    """A ground robot's drive through ``nodes``: at most :data:`MAX_SPEED`, 0.8 m/s^2
    acceleration, 1 m/s^2 braking, 1 m/s^2 lateral (about 1.4 m/s in the corridor
    corners), small body sway. stops: (node index, metres after it, dwell s)."""
    xy = route_path(nodes)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    stop_at = []
    for k, after, dwell in stops:
        d = np.hypot(*(xy - np.asarray(nodes[k])).T)
        s_node = float(s[np.argmin(d)])
        stop_at.append((s_node + after, dwell))
    return route_trajectory(
        xy,
        speed_limit=np.full(len(xy), MAX_SPEED),
        stops=stop_at,
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


def _scene(name: str, seed: int, nodes, stops, pedestrians: bool, description: str) -> Scene:
    b = _floor(np.random.default_rng([seed, 13]))  # the same floor for every route
    rng = np.random.default_rng([seed, 14])
    peds = _walkers(rng) if pedestrians else []
    traj = robot_trajectory(nodes, np.random.default_rng([seed, 15]), stops)
    return Scene.from_builder(
        name,
        b,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=40.0,
        revisit_radius=3.0,
        sensor=scene_sensor(name),
        description=f"{description}, {traj.length:.0f} m at up to {MAX_SPEED:g} m/s",
    )


def building(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """The paper's experiment: the S-shaped route through the floor, no revisits."""
    return _scene(
        "building",
        seed,
        S_ROUTE,
        S_STOPS,
        pedestrians,
        f"building under construction {FLOOR_X:g}x{FLOOR_Y:g} m, S-shaped route",
    )


def building_loop(seed: int = 0, *, pedestrians: bool = True) -> Scene:
    """The same floor, a route that comes back to its start (loop closure)."""
    return _scene(
        "building_loop",
        seed,
        LOOP_ROUTE,
        (),
        pedestrians,
        f"building under construction {FLOOR_X:g}x{FLOOR_Y:g} m, loop route back to the start",
    )
