"""The simulated worlds: ``corridor`` (indoor ring), ``plaza`` (outdoor square), ``park``
(large outdoor park on uneven ground, porous vegetation, realistic sensor errors) and
``urban`` (a car-speed city drive, :mod:`slam.sim.urban`).

Each scene is a few lines over the primitive builders of :mod:`slam.sim.geometry`, a
closed robot path and a handful of pedestrians. Everything random draws from the
``seed`` given to the builder.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.sim import geometry as g
from slam.sim.registry import scene_sensor
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
    thick = 0.4
    b = g.MeshBuilder()
    b.add(g.box_minmax((-W / 2 - 1, -H / 2 - 1, -0.2), (W / 2 + 1, H / 2 + 1, 0.0), g.CONCRETE))
    b.add(
        g.box_minmax(
            (-W / 2 - 1, -H / 2 - 1, height), (W / 2 + 1, H / 2 + 1, height + 0.2), g.PAINT
        )
    )
    # Leg frames: origin on the centre line, yaw = direction of travel (counter-clockwise).
    legs = {
        "south": ((0.0, -H / 2 + width / 2), 0.0, W),
        "east": ((W / 2 - width / 2, 0.0), 0.5 * np.pi, H),
        "north": ((0.0, H / 2 - width / 2), np.pi, W),
        "west": ((-W / 2 + width / 2, 0.0), 1.5 * np.pi, H),
    }
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
    v, t, r = b.build()

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
    path_tree = cKDTree(path)
    b = g.MeshBuilder()
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

    peds = []
    ped_lines = [
        ((-8.0, 5.0), (8.0, 6.5)),
        ((-20.0, -24.0), (12.0, -25.0)),
        ((24.0, 8.5), (25.0, 24.0)),
        ((-24.0, -14.0), (-25.0, 14.0)),
    ]
    if pedestrians:
        for p0, p1 in ped_lines:
            length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
            peds.append(Pedestrian(p0, p1, rng.uniform(1.0, 1.4), phase=rng.uniform(0, 2 * length)))
    ped_pts = np.vstack([np.linspace(p0, p1, 50) for p0, p1 in ped_lines])
    ped_tree = cKDTree(ped_pts)
    taken: list[tuple[float, float, float]] = [(0.0, 0.0, 3.5), (27.0, -2.0, 6.0)]

    def place(radius: float, clearance: float, box_xy=(-27.0, 27.0)) -> np.ndarray:
        """A random xy whose footprint (radius) is clear of the path, walkers and objects."""
        for _ in range(500):
            xy = rng.uniform(*box_xy, size=2)
            if path_tree.query(xy)[0] < clearance + radius:
                continue
            if ped_tree.query(xy)[0] < 0.9 + radius:
                continue
            if any(np.hypot(xy[0] - x, xy[1] - y) < r + radius + 0.5 for x, y, r in taken):
                continue
            taken.append((xy[0], xy[1], radius))
            return xy
        raise RuntimeError("plaza: could not place an object")  # pragma: no cover

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


# ---------------------------------------------------------------------------- park

PARK_SENSOR_HEIGHT = 0.8  # m above the ground (outdoor robot with a short mast)


def park_path() -> np.ndarray:
    """Closed route (N,2) of about 306 m: an east-west avenue (50 m) driven eastwards on
    the south lane (y = -1.5), a teardrop loop through the east part of the park, the
    avenue back westwards on the north lane (y = +1.5, a revisit in the opposite direction
    3 m apart), a teardrop loop through the west part and back onto the avenue."""
    from scipy.ndimage import gaussian_filter1d

    from slam.sim.trajectory import resample_closed

    east = [(34, -6), (42, -16), (52, -20), (59, -9), (59, 9), (52, 20), (42, 16), (34, 6)]
    west = [(-x, -y) for x, y in east]
    wp = [(0.0, -1.5), (25.0, -1.5), *east, (25.0, 1.5), (-25.0, 1.5), *west, (-25.0, -1.5)]
    ds = 0.1
    xy = resample_closed(np.asarray(wp, dtype=float), ds)
    # Periodic Gaussian smoothing (sigma 5 m): straight lanes stay straight, corners get
    # a continuous curvature (minimum radius ~5.5 m).
    return np.column_stack([gaussian_filter1d(xy[:, i], 5.0 / ds, mode="wrap") for i in (0, 1)])


def park_terrain(seed: int = 0) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Smooth ground height z(x, y) (m) of the park: ~1.5 m relief over 150 x 120 m,
    slopes below ~6 %; deterministic for a seed."""
    rng = np.random.default_rng([seed, 31])
    waves = []
    for amp, wl in ((0.35, 90.0), (0.25, 70.0), (0.15, 55.0), (0.08, 40.0)):
        a = rng.uniform(0, np.pi)
        waves.append((amp, 2 * np.pi * np.cos(a) / wl, 2 * np.pi * np.sin(a) / wl))
    phases = rng.uniform(0, 2 * np.pi, len(waves))

    def z(x, y):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        out = np.zeros(np.broadcast(x, y).shape)
        for (amp, kx, ky), ph in zip(waves, phases, strict=True):
            out = out + amp * np.sin(kx * x + ky * y + ph)
        return out

    return z


def _on_ground(parts: g.Part | list[g.Part], dz: float) -> list[g.Part]:
    """Parts raised by dz (m)."""
    parts = parts if isinstance(parts, list) else [parts]
    off = np.array([0.0, 0.0, dz])
    return [g.Part(p.vertices + off, p.triangles, p.reflectivity, p.extinction) for p in parts]


def park(
    seed: int = 0,
    *,
    loops: float = 1.08,
    speed: float = 2.0,
    pedestrians: bool = True,
) -> Scene:
    """Outdoor park / campus ~150 x 120 m on gently undulating ground (~1.5 m relief): an
    avenue lined with trees, lamps and benches, two teardrop loops through lawns with
    scattered trees (porous crowns), hedges, a fenced pond (no returns from water) and a
    few buildings at the east and north edges; the west half is open and vegetated
    (feature-poor). The robot drives ``loops`` laps of a ~306 m route at ``speed`` m/s,
    accelerating and braking, with high-frequency vibration; the avenue is revisited in
    the opposite direction and the start at the end. Uses the realistic sensor."""
    rng = np.random.default_rng(seed)
    height = park_terrain(seed)
    path = park_path()
    path_tree = cKDTree(path)
    b = g.MeshBuilder()

    # Ground: a 2 m height field; paved route (asphalt) and grass with ~3 cm roughness.
    gx, gy = np.arange(-80.0, 80.01, 2.0), np.arange(-66.0, 66.01, 2.0)
    xx, yy = np.meshgrid(gx, gy)
    zz = height(xx, yy)
    near = path_tree.query(np.column_stack([xx.ravel(), yy.ravel()]))[0].reshape(xx.shape)
    zz = zz + np.where(near > 3.0, rng.normal(0.0, 0.03, zz.shape), 0.0)
    cx, cy = 0.5 * (xx[:-1, :-1] + xx[1:, 1:]), 0.5 * (yy[:-1, :-1] + yy[1:, 1:])
    cell_d = path_tree.query(np.column_stack([cx.ravel(), cy.ravel()]))[0].reshape(cx.shape)
    cell_refl = np.where(cell_d < 2.6, g.ASPHALT, g.GRASS)
    # The pond: water returns nothing (specular), so its cells are left out.
    pond_c, pond_r = np.array([-47.0, 0.0]), np.array([5.0, 7.5])
    in_pond = ((cx - pond_c[0]) / pond_r[0]) ** 2 + ((cy - pond_c[1]) / pond_r[1]) ** 2 < 1.0
    cell_refl = np.where(in_pond, -1.0, cell_refl)
    b.add([p for p in g.height_field(gx, gy, zz, cell_refl) if p.reflectivity >= 0])

    taken: list[tuple[float, float, float]] = [(pond_c[0], pond_c[1], 8.5)]
    # Footprints (x0, x1, y0, y1) of the buildings and the kiosk, kept free of objects.
    blocked = [(65.0, 80.0, -40.0, 34.0), (3.0, 47.0, 49.0, 66.0), (-68.0, -42.0, -66.0, -43.0)]
    blocked.append((2.5, 9.5, 9.5, 14.5))

    def free(xy, radius: float, clearance: float) -> bool:
        if path_tree.query(xy)[0] < clearance + radius:
            return False
        for x0, x1, y0, y1 in blocked:
            if x0 - radius < xy[0] < x1 + radius and y0 - radius < xy[1] < y1 + radius:
                return False
        return not any(np.hypot(xy[0] - x, xy[1] - y) < r + radius + 0.3 for x, y, r in taken)

    def place(radius: float, clearance: float, box=((-75.0, 75.0), (-60.0, 60.0))):
        for _ in range(300):
            xy = np.array([rng.uniform(*box[0]), rng.uniform(*box[1])])
            if free(xy, radius, clearance):
                taken.append((xy[0], xy[1], radius))
                return xy
        return None

    def ground_at(xy, r: float = 0.0) -> float:
        """Lowest terrain height under a footprint of radius r at xy (m)."""
        a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        return float(np.min(height(xy[0] + r * np.cos(a), xy[1] + r * np.sin(a))))

    def tree(xy) -> None:
        z0 = ground_at(xy, 0.5) - 0.2
        r_trunk = rng.uniform(0.15, 0.4)
        trunk_h = rng.uniform(1.8, 3.2)
        if rng.random() < 0.75:  # broadleaf: porous ellipsoid crown
            rxy, rz = rng.uniform(1.8, 3.6), rng.uniform(1.6, 3.0)
            centre = (xy[0], xy[1], z0 + 0.2 + trunk_h + 0.8 * rz)
            crown = g.ellipsoid(centre, (rxy, rxy * rng.uniform(0.8, 1.1), rz), g.FOLIAGE, 8)
            top = centre[2]
        else:  # conifer: porous cone
            rxy = rng.uniform(1.4, 2.4)
            crown = _on_ground(g.cone(xy, rxy, rng.uniform(2.5, 3.5) * rxy, 0.0, g.FOLIAGE, 12),
                               z0 + 0.2 + 0.5 * trunk_h)[0]  # fmt: skip
            top = z0 + 0.2 + 0.5 * trunk_h + 1.5 * rxy
        ext = rng.uniform(0.6, 1.3) * g.CROWN_EXTINCTION
        b.add(g.cylinder(xy, r_trunk, top - z0, z0, g.BARK, 10))
        b.add(g.porous(crown, ext))

    # Avenue: trees on both sides, lamp poles and benches between them.
    for side in (-1.0, 1.0):
        for x in np.arange(-21.0, 22.0, 8.5):
            xy = np.array([x + rng.uniform(-1.0, 1.0), side * rng.uniform(5.5, 6.5)])
            if free(xy, 0.4, 3.5):
                taken.append((xy[0], xy[1], 0.4))
                tree(xy)
        for x in np.arange(-17.0, 18.0, 17.0):
            xy = np.array([x + 4.0 * side, side * 3.6])
            taken.append((xy[0], xy[1], 0.3))
            _lamp(b, xy, ground_at(xy, 0.1))
        for x in (-10.0, 12.0):
            xy = np.array([x + 2.0 * side, side * 3.8])
            taken.append((xy[0], xy[1], 1.0))
            _bench(b, xy, 0.0 if side > 0 else np.pi, ground_at(xy, 0.9))
    # Along the loops: trees 4.5-7 m from the route on either side, with gaps.
    for s_idx in range(0, len(path), 75):
        p = path[s_idx]
        if abs(p[0]) < 27.0 or rng.random() < 0.25:
            continue
        t = path[(s_idx + 5) % len(path)] - path[s_idx - 5]
        n = np.array([-t[1], t[0]]) / np.hypot(*t)
        xy = p + n * rng.choice([-1.0, 1.0]) * rng.uniform(4.5, 7.0)
        if free(xy, 0.4, 3.5):
            taken.append((xy[0], xy[1], 0.4))
            tree(xy)
    for _ in range(60):  # scattered trees on the lawns
        xy = place(0.4, 5.0)
        if xy is not None:
            tree(xy)
    # Hedges: porous boxes along parts of the loops, 3 m off the centre line.
    for s0 in (1300, 2200, 4700, 6900, 7900):
        for s_idx in range(s0, s0 + 120, 30):
            p = path[s_idx % len(path)]
            t = path[(s_idx + 5) % len(path)] - path[(s_idx - 5) % len(path)]
            yaw = float(np.arctan2(t[1], t[0]))
            n = np.array([-np.sin(yaw), np.cos(yaw)])
            for side in (-1.0, 1.0):
                xy = p + side * 3.3 * n
                if path_tree.query(xy)[0] < 3.0:  # too close to another part of the route
                    continue
                z0 = ground_at(xy, 1.6) - 0.2
                top = float(height(xy[0], xy[1])) + 1.1
                hedge = g.box(
                    (xy[0], xy[1], 0.5 * (z0 + top)), (3.1, 0.9, top - z0), yaw, g.FOLIAGE
                )
                b.add(g.porous(hedge, g.HEDGE_EXTINCTION))
    # Lamp poles, sign posts, bins and bollards along the loops (thin structures).
    for k, s_idx in enumerate(range(600, len(path), 650)):
        p = path[s_idx]
        if abs(p[0]) < 27.0:
            continue
        t = path[(s_idx + 5) % len(path)] - path[s_idx - 5]
        n = np.array([-t[1], t[0]]) / np.hypot(*t)
        xy = p + (-1.0) ** k * 3.0 * n
        if path_tree.query(xy)[0] < 2.8:
            continue
        taken.append((xy[0], xy[1], 0.3))
        if k % 3 == 2:
            _sign(b, xy, ground_at(xy, 0.05))
        else:
            _lamp(b, xy, ground_at(xy, 0.1))
    for _ in range(6):
        xy = place(0.35, 2.8)
        if xy is not None:
            b.add(g.cylinder(xy, 0.3, 1.0, ground_at(xy, 0.3) - 0.1, g.METAL, 12))
    for x in (-27.0, 27.0):
        for y in (-4.2, -3.2, 3.2, 4.2):
            b.add(g.cylinder((x, y), 0.1, 1.0, ground_at((x, y), 0.1) - 0.1, g.CONCRETE, 8))
    # Fence around the pond: posts every ~2 m and two thin rails.
    a = np.linspace(0, 2 * np.pi, 27, endpoint=False)
    posts = pond_c + np.column_stack([(pond_r[0] + 1.0) * np.cos(a), (pond_r[1] + 1.0) * np.sin(a)])
    for i, xy in enumerate(posts):
        z0 = ground_at(xy, 0.05) - 0.1
        b.add(g.cylinder(xy, 0.04, 1.2, z0, g.METAL, 6))
        q = posts[(i + 1) % len(posts)]
        mid, d = 0.5 * (xy + q), q - xy
        for zr in (0.55, 1.05):
            b.add(g.box((mid[0], mid[1], z0 + 0.1 + zr), (np.hypot(*d), 0.04, 0.04),
                        float(np.arctan2(d[1], d[0])), g.METAL))  # fmt: skip
    # Buildings at the east and north edges, a pavilion in the south-west corner, a kiosk.
    for p0, p1, h, kw in (
        ((68.0, -38.0), (68.0, -6.0), 12.0, {}),
        ((68.0, 2.0), (68.0, 32.0), 9.0, {"pitch": 2.6}),
        ((45.0, 52.0), (5.0, 52.0), 15.0, {"pitch": 4.0, "win_w": 2.2}),
        ((-66.0, -46.0), (-44.0, -46.0), 5.0, {"pitch": 3.6}),
    ):
        xs, ys = np.linspace(p0[0], p1[0], 9), np.linspace(p0[1], p1[1], 9)
        b.add(_on_ground(_facade(p0, p1, h, **kw), float(np.min(height(xs, ys))) - 0.5))
    b.add(g.box((6.0, 12.0, ground_at((6.0, 12.0), 3.0) + 1.3), (5.0, 3.5, 3.2), 0.1, g.WOOD))

    peds: list[Pedestrian] = []
    if pedestrians:
        lines = [
            ((-20.0, -3.2), (18.0, -3.2)),
            ((22.0, 3.0), (-15.0, 3.0)),
            ((40.0, -30.0), (30.0, -12.0)),
            ((-38.0, 25.0), (-20.0, 30.0)),
            ((50.0, 30.0), (60.0, 40.0)),
            ((-65.0, -25.0), (-40.0, -32.0)),
        ]
        for p0, p1 in lines:
            length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
            peds.append(
                Pedestrian(
                    p0,
                    p1,
                    rng.uniform(1.0, 1.5),
                    phase=rng.uniform(0, 2 * length),
                    z=(float(height(*p0)), float(height(*p1))),
                )
            )
    traj = closed_curve_trajectory(
        path,
        loops=loops,
        speed=speed,
        height=PARK_SENSOR_HEIGHT,
        rng=rng,
        ramp_distance=3.0,
        wobble_deg=0.6,
        speed_variation=0.15,
        vibration_deg=0.25,
        terrain=height,
    )
    return Scene.from_builder(
        "park",
        b,
        trajectory=traj,
        pedestrians=peds,
        loop_max_radius=60.0,
        revisit_radius=5.0,
        sensor=scene_sensor("park"),
        description=(
            f"outdoor park 150x120 m, uneven ground, porous trees, {traj.loop_length:.0f} m "
            f"route (avenue revisited in the opposite direction), {loops:g} laps"
        ),
    )


def _lamp(b: g.MeshBuilder, xy, z0: float) -> None:
    b.add(g.cylinder(xy, 0.07, 4.6, z0 - 0.1, g.METAL, 8))
    b.add(g.box((xy[0], xy[1], z0 + 4.6), (0.6, 0.3, 0.2), 0.0, g.METAL))


def _sign(b: g.MeshBuilder, xy, z0: float) -> None:
    b.add(g.cylinder(xy, 0.03, 2.4, z0 - 0.1, g.METAL, 6))
    b.add(g.box((xy[0], xy[1], z0 + 2.0), (0.6, 0.03, 0.45), 0.0, g.PAINT))


def _bench(b: g.MeshBuilder, xy, yaw: float, z0: float) -> None:
    b.add(g.box((xy[0], xy[1], z0 + 0.42), (1.8, 0.45, 0.08), yaw, g.WOOD))
    back = xy + 0.2 * np.array([-np.sin(yaw), np.cos(yaw)])
    b.add(g.box((back[0], back[1], z0 + 0.6), (1.8, 0.06, 0.4), yaw, g.WOOD))
    b.add(g.box((xy[0], xy[1], z0 + 0.14), (1.6, 0.4, 0.48), yaw, g.METAL))
