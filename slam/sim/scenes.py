"""The simulated worlds ``corridor`` (indoor ring) and ``plaza`` (outdoor square), and the
facade and placement helpers the other scenes share; ``park`` (large outdoor park on uneven
ground, porous vegetation, realistic sensor errors) lives in :mod:`slam.sim.park`, ``urban``
(a car-speed city drive) in :mod:`slam.sim.urban`.

Each scene is a few lines over the primitive builders of :mod:`slam.sim.geometry`, a
closed robot path and a handful of pedestrians. Everything random draws from the
``seed`` given to the builder.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.sim import geometry as g
from slam.sim.scene import Pedestrian, Scene
from slam.sim.trajectory import closed_curve_trajectory, rounded_rectangle

SENSOR_HEIGHT = 0.5  # m above the ground (ground robot)

# ---------------------------------------------------------------------------- corridor


@dataclass(frozen=True)
class Feature:
    """A corridor feature in leg coordinates: u along the direction of travel from the leg
    middle (m), side "outer" (robot's right) or "inner" (left).

    kind: "door" (recess, width x depth x 2.1 m), "alcove" (recess of full height),
    "pillar" / "cabinet" (box protruding depth m into the corridor, height h).
    """

    kind: str
    u: float
    side: str
    width: float = 1.0
    depth: float = 0.25
    h: float = 2.1


# The repeating section: identical on the south and north legs (180-degree symmetric),
# so that a place-recognition descriptor sees a convincing false loop candidate.
_REPEATED = (
    Feature("door", -3.6, "outer"),
    Feature("door", 0.4, "outer"),
    Feature("door", 3.4, "outer", width=1.6),
    Feature("door", -1.6, "inner"),
    Feature("cabinet", 1.9, "inner", width=1.2, depth=0.45, h=1.9),
    Feature("pillar", -5.0, "inner", width=0.4, depth=0.25, h=3.0),
)

_LEGS: dict[str, tuple[Feature, ...]] = {
    "south": _REPEATED
    + (
        Feature("pillar", -7.8, "outer", width=0.5, depth=0.3, h=3.0),
        Feature("cabinet", -7.0, "inner", width=0.9, depth=0.4, h=1.0),
        Feature("door", 7.6, "outer", width=1.2),
        Feature("pillar", 7.0, "inner", width=0.4, depth=0.25, h=3.0),
    ),
    "east": (
        Feature("alcove", 0.3, "outer", width=2.6, depth=1.2),
        Feature("cabinet", 0.3, "outer", width=0.8, depth=-0.7, h=1.8),  # inside the alcove
        Feature("door", -2.2, "inner", width=1.1),
        Feature("pillar", 2.6, "inner", width=0.5, depth=0.3, h=3.0),
    ),
    "north": _REPEATED
    + (
        Feature("cabinet", -8.2, "outer", width=1.6, depth=0.45, h=1.2),
        Feature("door", -7.2, "inner", width=0.9),
        Feature("pillar", 6.8, "outer", width=0.4, depth=0.3, h=3.0),
        Feature("alcove", 8.0, "inner", width=2.0, depth=0.8),
    ),
    "west": (
        Feature("door", -2.6, "outer"),
        Feature("cabinet", 1.4, "outer", width=1.4, depth=0.5, h=1.6),
        Feature("pillar", 0.0, "inner", width=0.4, depth=0.3, h=3.0),
        Feature("door", 3.1, "inner", width=1.4),
    ),
}


def _leg_wall(
    length: float, v_face: float, side: str, feats: list[Feature], height: float, thick: float
) -> list[g.Part]:
    """Wall face at leg coordinate v = v_face running u in [-length/2, length/2] with its
    door/alcove recesses and protruding pillars/cabinets (parts in leg coordinates)."""
    out = 1.0 if side == "inner" else -1.0  # +v points into the wall on the inner side
    parts: list[g.Part] = []
    recesses = sorted((f for f in feats if f.kind in ("door", "alcove")), key=lambda f: f.u)
    u = -0.5 * length

    def slab(u0: float, u1: float, d0: float, d1: float, z0: float, z1: float, refl: float):
        v0, v1 = sorted((v_face + out * d0, v_face + out * d1))
        parts.append(g.box_minmax((u0, v0, z0), (u1, v1, z1), refl))

    for f in recesses:
        a, b = f.u - 0.5 * f.width, f.u + 0.5 * f.width
        if a > u:
            slab(u, a, 0.0, thick, 0.0, height, g.PAINT)
        top = height if f.kind == "alcove" else f.h
        slab(a, b, f.depth, f.depth + thick, 0.0, top, g.WOOD if f.kind == "door" else g.PAINT)
        if top < height:
            slab(a, b, 0.0, thick, top, height, g.PAINT)
        u = b
    if u < 0.5 * length:
        slab(u, 0.5 * length, 0.0, thick, 0.0, height, g.PAINT)
    for f in feats:
        if f.kind in ("pillar", "cabinet"):
            a, b = f.u - 0.5 * f.width, f.u + 0.5 * f.width
            refl = g.CONCRETE if f.kind == "pillar" else g.METAL
            if f.depth >= 0:  # protrudes into the corridor
                slab(a, b, -f.depth, 0.0, 0.0, f.h, refl)
            else:  # stands inside a recess, against its back
                slab(a, b, -f.depth - 0.4, -f.depth, 0.0, f.h, refl)
    return parts


def _to_world(parts: list[g.Part], origin, yaw: float) -> list[g.Part]:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    o = np.array([origin[0], origin[1], 0.0])
    return [g.Part(p.vertices @ R.T + o, p.triangles, p.reflectivity) for p in parts]


def _corridor_legs(W: float, H: float, width: float) -> dict[str, tuple]:
    """Leg frames of the ring: origin on the centre line (m), yaw = direction of travel
    (counter-clockwise, rad), outer length (m)."""
    return {
        "south": ((0.0, -H / 2 + width / 2), 0.0, W),
        "east": ((W / 2 - width / 2, 0.0), 0.5 * np.pi, H),
        "north": ((0.0, H / 2 - width / 2), np.pi, W),
        "west": ((-W / 2 + width / 2, 0.0), 1.5 * np.pi, H),
    }


def _corridor_mesh(
    W: float, H: float, width: float, height: float, legs: dict[str, tuple]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, triangles, reflectivity) of the corridor ring (m): floor, ceiling, the legs'
    walls with their features and the filled inner block."""
    thick = 0.4
    b = g.MeshBuilder()
    b.add(g.box_minmax((-W / 2 - 1, -H / 2 - 1, -0.2), (W / 2 + 1, H / 2 + 1, 0.0), g.CONCRETE))
    b.add(
        g.box_minmax(
            (-W / 2 - 1, -H / 2 - 1, height), (W / 2 + 1, H / 2 + 1, height + 0.2), g.PAINT
        )
    )
    for name, (origin, yaw, outer_len) in legs.items():
        feats = list(_LEGS[name])
        outer_f = [f for f in feats if f.side == "outer"]
        inner_f = [f for f in feats if f.side == "inner"]
        parts = _leg_wall(outer_len, -width / 2, "outer", outer_f, height, thick)
        parts += _leg_wall(outer_len - 2 * width, width / 2, "inner", inner_f, height, thick)
        b.add(_to_world(parts, origin, yaw))
    # Fill the inner block so that nothing is seen through the inner walls' recesses.
    b.add(
        g.box_minmax(
            (-W / 2 + width + 1.2, -H / 2 + width + 1.2, 0.0),
            (W / 2 - width - 1.2, H / 2 - width - 1.2, height),
            g.CONCRETE,
        )
    )
    return b.build()


def corridor(
    seed: int = 0,
    *,
    outer: tuple[float, float] = (24.0, 14.0),
    width: float = 2.5,
    height: float = 3.0,
    loops: float = 1.1,
    speed: float = 1.25,
    pedestrians: bool = True,
) -> Scene:
    """Indoor corridor ring: outer x_size x y_size (m), corridor ``width`` wide and ``height``
    high, doors, alcoves, pillars and cabinets; the south and north legs share one door
    pattern (a false loop candidate). The robot drives ``loops`` laps counter-clockwise
    from the middle of the south leg at ``speed`` m/s."""
    rng = np.random.default_rng(seed)
    W, H = outer
    legs = _corridor_legs(W, H, width)
    v, t, r = _corridor_mesh(W, H, width, height, legs)

    path = rounded_rectangle(W - width, H - width, corner_length=2.5)
    traj = closed_curve_trajectory(
        path, loops=loops, speed=speed, height=SENSOR_HEIGHT, rng=rng, start_offset=-3.0
    )
    peds = []
    if pedestrians:
        # Walking along the legs, 0.75 m off the centre line, clear of the robot.
        peds = [
            _leg_ped(legs["south"], (3.8, 9.0), 0.75, rng),
            _leg_ped(legs["north"], (-6.0, 0.5), 0.72, rng),
            _leg_ped(legs["east"], (-3.0, 3.0), -0.75, rng),
        ]
    return Scene(
        name="corridor",
        vertices=v,
        triangles=t,
        reflectivity=r,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=20.0,
        revisit_radius=3.0,
        description=f"indoor corridor ring {W:g}x{H:g} m, {width:g} m wide, {loops:g} laps",
    )


def _leg_ped(leg, u_range, v: float, rng: np.random.Generator) -> Pedestrian:
    (ox, oy), yaw, _ = leg
    c, s = np.cos(yaw), np.sin(yaw)

    def w(u: float) -> tuple[float, float]:
        return (ox + c * u - s * v, oy + s * u + c * v)

    return Pedestrian(
        w(u_range[0]),
        w(u_range[1]),
        speed=rng.uniform(1.0, 1.4),
        phase=rng.uniform(0, 2 * (u_range[1] - u_range[0])),
    )


# ---------------------------------------------------------------------------- plaza


def _facade(
    p0,
    p1,
    height: float,
    floor_h: float = 3.0,
    win_w: float = 1.4,
    win_h: float = 1.6,
    pitch: float = 3.2,
    recess: float = 0.3,
) -> list[g.Part]:
    """Building facade from xy p0 to p1 (m), the plaza on its left, with recessed windows:
    glass ``recess`` m behind the face, stone piers and spandrels in front."""
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    length = float(np.hypot(*(p1 - p0)))
    yaw = float(np.arctan2(p1[1] - p0[1], p1[0] - p0[0]))
    # Local frame: u along the facade, the plaza at v > 0, the face at v = 0.
    parts = [g.box_minmax((0, -recess - 2.0, 0), (length, -recess, height), g.GLASS)]
    n_win = max(int((length - 1.0) // pitch), 0)
    centres = 0.5 * (length - n_win * pitch) + (np.arange(n_win) + 0.5) * pitch
    edges = np.concatenate(
        [[0.0], np.column_stack([centres - win_w / 2, centres + win_w / 2]).ravel(), [length]]
    )
    for a, b in edges.reshape(-1, 2):  # piers between windows, full height
        parts.append(g.box_minmax((a, -recess, 0), (b, 0, height), g.STONE))
    sills = np.arange(0.0, height, floor_h) + 1.0
    sills = sills[sills + win_h <= height - 0.3]
    solid = np.concatenate([[0.0], np.column_stack([sills, sills + win_h]).ravel(), [height]])
    for c in centres:  # spandrels between the windows of one column
        for z0, z1 in solid.reshape(-1, 2):
            parts.append(
                g.box_minmax((c - win_w / 2, -recess, z0), (c + win_w / 2, 0, z1), g.STONE)
            )
    return _to_world(parts, p0, yaw)


def plaza_path(n: int = 2000) -> np.ndarray:
    """Closed counter-clockwise loop (N,2) of about 95 m around the plaza centre."""
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False) - 0.5 * np.pi
    x = 16.0 * np.cos(th) + 1.2 * np.cos(2 * th + 0.4)
    y = 11.5 * np.sin(th) + 1.0 * np.sin(3 * th)
    return np.column_stack([x, y])


def _plaza_fixed(b: g.MeshBuilder) -> None:
    """The plaza's fixed structures (m): ground, facades around (streets between blocks),
    the terrace with steps on the east side and the fountain in the middle."""
    b.add(g.ground((-60, 60), (-60, 60), 0.0, g.ASPHALT))
    # Facades around (plaza on the left of each p0 -> p1), streets between blocks.
    b.add(_facade((-30, -30), (-4, -30), 12.0))
    b.add(_facade((1, -30), (30, -30), 9.0))
    b.add(_facade((30, -30), (30, 6), 15.0))
    b.add(_facade((30, 11), (30, 30), 9.0, pitch=2.6))
    b.add(_facade((30, 30), (-12, 30), 12.0, pitch=4.0, win_w=2.2))
    b.add(_facade((-17, 30), (-30, 30), 6.0))
    b.add(_facade((-30, 30), (-30, -30), 10.0, pitch=3.6))
    # Terrace with steps on the east side.
    b.add(g.box_minmax((24.0, -8.0, 0.0), (30.0, 4.0, 0.6), g.STONE))
    b.add(g.steps((22.6, -2.0), 0.0, 4, 0.15, 0.35, 6.0))
    # Fountain in the middle.
    b.add(g.cylinder((0.0, 0.0), 3.0, 0.5, 0.0, g.STONE, 32))
    b.add(g.cylinder((0.0, 0.0), 0.5, 1.6, 0.5, g.STONE, 16))
    b.add(g.cone((0.0, 0.0), 1.2, 0.6, 2.1, g.STONE, 16))


_PLAZA_WALKS = (
    ((-8.0, 5.0), (8.0, 6.5)),
    ((-20.0, -24.0), (12.0, -25.0)),
    ((24.0, 8.5), (25.0, 24.0)),
    ((-24.0, -14.0), (-25.0, 14.0)),
)


@dataclass
class _PlazaPlacer:
    """Random footprints on the plaza clear of the path, the walkers' lines and the objects
    placed so far (``taken``: x, y, radius in m)."""

    rng: np.random.Generator
    path_tree: cKDTree
    ped_tree: cKDTree
    taken: list[tuple[float, float, float]]

    def __call__(self, radius: float, clearance: float, box_xy=(-27.0, 27.0)) -> np.ndarray:
        """A random xy whose footprint (radius) is clear of the path, walkers and objects."""
        for _ in range(500):
            xy = self.rng.uniform(*box_xy, size=2)
            if self.path_tree.query(xy)[0] < clearance + radius:
                continue
            if self.ped_tree.query(xy)[0] < 0.9 + radius:
                continue
            if any(np.hypot(xy[0] - x, xy[1] - y) < r + radius + 0.5 for x, y, r in self.taken):
                continue
            self.taken.append((xy[0], xy[1], radius))
            return xy
        raise RuntimeError("plaza: could not place an object")  # pragma: no cover


def _plaza_objects(b: g.MeshBuilder, rng: np.random.Generator, place: _PlazaPlacer) -> None:
    """Trees (trunk + sphere or cone crown), flower beds, lamp poles and benches at random
    free places (m)."""
    for _ in range(12):  # trees: trunk + crown (sphere or cone)
        crown = rng.uniform(1.2, 2.0)
        xy = place(0.3, 1.8)
        trunk_h = rng.uniform(2.0, 3.0)
        b.add(g.cylinder(xy, rng.uniform(0.12, 0.25), trunk_h, 0.0, g.BARK, 12))
        if rng.random() < 0.6:
            b.add(g.sphere((xy[0], xy[1], trunk_h + 0.7 * crown), crown, g.FOLIAGE))
        else:
            b.add(g.cone(xy, crown, 2.5 * crown, trunk_h - 0.3, g.FOLIAGE))
    for _ in range(5):  # flower beds
        size = (rng.uniform(2.0, 4.0), rng.uniform(1.0, 2.0), rng.uniform(0.3, 0.5))
        xy = place(0.5 * np.hypot(size[0], size[1]), 1.0)
        b.add(g.box((xy[0], xy[1], size[2] / 2), size, rng.uniform(0, np.pi), g.SOIL))
    for _ in range(10):  # lamp poles with a head
        xy = place(0.3, 1.2)
        b.add(g.cylinder(xy, 0.07, 4.5, 0.0, g.METAL, 8))
        b.add(g.box((xy[0], xy[1], 4.6), (0.6, 0.3, 0.2), 0.0, g.METAL))
    for _ in range(6):  # benches: seat + backrest
        xy = place(1.0, 1.2)
        yaw = rng.uniform(0, np.pi)
        b.add(g.box((xy[0], xy[1], 0.42), (1.8, 0.45, 0.08), yaw, g.WOOD))
        back = xy + 0.2 * np.array([-np.sin(yaw), np.cos(yaw)])
        b.add(g.box((back[0], back[1], 0.6), (1.8, 0.06, 0.4), yaw, g.WOOD))
        b.add(g.box((xy[0], xy[1], 0.19), (1.6, 0.4, 0.38), yaw, g.METAL))


def plaza(
    seed: int = 0,
    *,
    loops: float = 1.12,
    speed: float = 1.4,
    pedestrians: bool = True,
) -> Scene:
    """Outdoor plaza ~60x60 m: facades with windows around, trees, flower beds, a fountain,
    steps to a terrace, lamp poles and benches; the robot drives a smooth ~95 m loop
    ``loops`` times at ``speed`` m/s."""
    rng = np.random.default_rng(seed)
    path = plaza_path()
    b = g.MeshBuilder()
    _plaza_fixed(b)
    peds = []
    if pedestrians:
        for p0, p1 in _PLAZA_WALKS:
            length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
            peds.append(Pedestrian(p0, p1, rng.uniform(1.0, 1.4), phase=rng.uniform(0, 2 * length)))
    ped_pts = np.vstack([np.linspace(p0, p1, 50) for p0, p1 in _PLAZA_WALKS])
    taken: list[tuple[float, float, float]] = [(0.0, 0.0, 3.5), (27.0, -2.0, 6.0)]
    _plaza_objects(b, rng, _PlazaPlacer(rng, cKDTree(path), cKDTree(ped_pts), taken))
    v, t, r = b.build()
    traj = closed_curve_trajectory(path, loops=loops, speed=speed, height=SENSOR_HEIGHT, rng=rng)
    return Scene(
        name="plaza",
        vertices=v,
        triangles=t,
        reflectivity=r,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=40.0,
        revisit_radius=5.0,
        description=f"outdoor plaza 60x60 m, {traj.loop_length:.0f} m loop, {loops:g} laps",
    )
