"""The ``park`` scene: a large outdoor park on uneven ground (~150 x 120 m) with porous
vegetation, driven with the realistic sensor errors.

The builder is a sequence of steps over one ``_ParkSite`` (the mesh being built, the random
generator, the terrain and the footprints taken so far); the steps draw from the generator
in a fixed order, so a seed always gives the same park.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from slam.sim import geometry as g
from slam.sim.registry import scene_sensor
from slam.sim.scene import Pedestrian, Scene
from slam.sim.scenes import _facade
from slam.sim.trajectory import closed_curve_trajectory

PARK_SENSOR_HEIGHT = 0.8  # m above the ground (outdoor robot with a short mast)
POND_CENTRE, POND_RADII = (-47.0, 0.0), (5.0, 7.5)  # m: the pond's ellipse


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


@dataclass
class _ParkSite:
    """The park while it is built: mesh, random generator, terrain z(x, y) (m), route and
    the footprints (x, y, radius; m) taken so far, kept free of further objects together
    with the ``blocked`` rectangles (x0, x1, y0, y1; m) of the buildings and the kiosk."""

    b: g.MeshBuilder
    rng: np.random.Generator
    height: Callable[[np.ndarray, np.ndarray], np.ndarray]
    path: np.ndarray
    path_tree: cKDTree
    taken: list[tuple[float, float, float]] = field(default_factory=list)
    blocked: list[tuple[float, float, float, float]] = field(default_factory=list)

    def free(self, xy, radius: float, clearance: float) -> bool:
        """Whether a footprint of radius (m) at xy keeps clearance (m) from the route and is
        clear of the blocked rectangles and the footprints taken."""
        if self.path_tree.query(xy)[0] < clearance + radius:
            return False
        for x0, x1, y0, y1 in self.blocked:
            if x0 - radius < xy[0] < x1 + radius and y0 - radius < xy[1] < y1 + radius:
                return False
        return not any(np.hypot(xy[0] - x, xy[1] - y) < r + radius + 0.3 for x, y, r in self.taken)

    def place(self, radius: float, clearance: float, box=((-75.0, 75.0), (-60.0, 60.0))):
        """A random free xy in box (m), taken; None after 300 tries."""
        for _ in range(300):
            xy = np.array([self.rng.uniform(*box[0]), self.rng.uniform(*box[1])])
            if self.free(xy, radius, clearance):
                self.taken.append((xy[0], xy[1], radius))
                return xy
        return None

    def ground_at(self, xy, r: float = 0.0) -> float:
        """Lowest terrain height under a footprint of radius r at xy (m)."""
        a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        return float(np.min(self.height(xy[0] + r * np.cos(a), xy[1] + r * np.sin(a))))

    def tree(self, xy) -> None:
        """A tree at xy: bark trunk and a porous crown, broadleaf (ellipsoid, 75 %) or
        conifer (cone), sizes drawn at random (m)."""
        rng, b = self.rng, self.b
        z0 = self.ground_at(xy, 0.5) - 0.2
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


def _ground(site: _ParkSite) -> None:
    """A 2 m height field: the paved route (asphalt) and grass with ~3 cm roughness; the
    pond's cells are left out (water returns nothing, it is specular)."""
    rng, height, path_tree = site.rng, site.height, site.path_tree
    gx, gy = np.arange(-80.0, 80.01, 2.0), np.arange(-66.0, 66.01, 2.0)
    xx, yy = np.meshgrid(gx, gy)
    zz = height(xx, yy)
    near = path_tree.query(np.column_stack([xx.ravel(), yy.ravel()]))[0].reshape(xx.shape)
    zz = zz + np.where(near > 3.0, rng.normal(0.0, 0.03, zz.shape), 0.0)
    cx, cy = 0.5 * (xx[:-1, :-1] + xx[1:, 1:]), 0.5 * (yy[:-1, :-1] + yy[1:, 1:])
    cell_d = path_tree.query(np.column_stack([cx.ravel(), cy.ravel()]))[0].reshape(cx.shape)
    cell_refl = np.where(cell_d < 2.6, g.ASPHALT, g.GRASS)
    pond_c, pond_r = np.array(POND_CENTRE), np.array(POND_RADII)
    in_pond = ((cx - pond_c[0]) / pond_r[0]) ** 2 + ((cy - pond_c[1]) / pond_r[1]) ** 2 < 1.0
    cell_refl = np.where(in_pond, -1.0, cell_refl)
    site.b.add([p for p in g.height_field(gx, gy, zz, cell_refl) if p.reflectivity >= 0])


def _avenue(site: _ParkSite) -> None:
    """The avenue: trees on both sides, lamp poles and benches between them."""
    rng, b = site.rng, site.b
    for side in (-1.0, 1.0):
        for x in np.arange(-21.0, 22.0, 8.5):
            xy = np.array([x + rng.uniform(-1.0, 1.0), side * rng.uniform(5.5, 6.5)])
            if site.free(xy, 0.4, 3.5):
                site.taken.append((xy[0], xy[1], 0.4))
                site.tree(xy)
        for x in np.arange(-17.0, 18.0, 17.0):
            xy = np.array([x + 4.0 * side, side * 3.6])
            site.taken.append((xy[0], xy[1], 0.3))
            _lamp(b, xy, site.ground_at(xy, 0.1))
        for x in (-10.0, 12.0):
            xy = np.array([x + 2.0 * side, side * 3.8])
            site.taken.append((xy[0], xy[1], 1.0))
            _bench(b, xy, 0.0 if side > 0 else np.pi, site.ground_at(xy, 0.9))


def _trees(site: _ParkSite) -> None:
    """Trees along the loops (4.5-7 m from the route on either side, with gaps) and 60
    attempts at scattered trees on the lawns."""
    rng, path = site.rng, site.path
    for s_idx in range(0, len(path), 75):
        p = path[s_idx]
        if abs(p[0]) < 27.0 or rng.random() < 0.25:
            continue
        t = path[(s_idx + 5) % len(path)] - path[s_idx - 5]
        n = np.array([-t[1], t[0]]) / np.hypot(*t)
        xy = p + n * rng.choice([-1.0, 1.0]) * rng.uniform(4.5, 7.0)
        if site.free(xy, 0.4, 3.5):
            site.taken.append((xy[0], xy[1], 0.4))
            site.tree(xy)
    for _ in range(60):  # scattered trees on the lawns
        xy = site.place(0.4, 5.0)
        if xy is not None:
            site.tree(xy)


def _hedges(site: _ParkSite) -> None:
    """Hedges: porous boxes along parts of the loops, 3.3 m off the centre line."""
    path, height = site.path, site.height
    for s0 in (1300, 2200, 4700, 6900, 7900):
        for s_idx in range(s0, s0 + 120, 30):
            p = path[s_idx % len(path)]
            t = path[(s_idx + 5) % len(path)] - path[(s_idx - 5) % len(path)]
            yaw = float(np.arctan2(t[1], t[0]))
            n = np.array([-np.sin(yaw), np.cos(yaw)])
            for side in (-1.0, 1.0):
                xy = p + side * 3.3 * n
                if site.path_tree.query(xy)[0] < 3.0:  # too close to another part of the route
                    continue
                z0 = site.ground_at(xy, 1.6) - 0.2
                top = float(height(xy[0], xy[1])) + 1.1
                hedge = g.box(
                    (xy[0], xy[1], 0.5 * (z0 + top)), (3.1, 0.9, top - z0), yaw, g.FOLIAGE
                )
                site.b.add(g.porous(hedge, g.HEDGE_EXTINCTION))


def _posts(site: _ParkSite) -> None:
    """Lamp poles, sign posts, bins and bollards along the loops (thin structures)."""
    b, path = site.b, site.path
    for k, s_idx in enumerate(range(600, len(path), 650)):
        p = path[s_idx]
        if abs(p[0]) < 27.0:
            continue
        t = path[(s_idx + 5) % len(path)] - path[s_idx - 5]
        n = np.array([-t[1], t[0]]) / np.hypot(*t)
        xy = p + (-1.0) ** k * 3.0 * n
        if site.path_tree.query(xy)[0] < 2.8:
            continue
        site.taken.append((xy[0], xy[1], 0.3))
        if k % 3 == 2:
            _sign(b, xy, site.ground_at(xy, 0.05))
        else:
            _lamp(b, xy, site.ground_at(xy, 0.1))
    for _ in range(6):
        xy = site.place(0.35, 2.8)
        if xy is not None:
            b.add(g.cylinder(xy, 0.3, 1.0, site.ground_at(xy, 0.3) - 0.1, g.METAL, 12))
    for x in (-27.0, 27.0):
        for y in (-4.2, -3.2, 3.2, 4.2):
            b.add(g.cylinder((x, y), 0.1, 1.0, site.ground_at((x, y), 0.1) - 0.1, g.CONCRETE, 8))


def _pond_fence(site: _ParkSite) -> None:
    """Fence around the pond: posts every ~2 m and two thin rails."""
    pond_c, pond_r = np.array(POND_CENTRE), np.array(POND_RADII)
    a = np.linspace(0, 2 * np.pi, 27, endpoint=False)
    posts = pond_c + np.column_stack([(pond_r[0] + 1.0) * np.cos(a), (pond_r[1] + 1.0) * np.sin(a)])
    for i, xy in enumerate(posts):
        z0 = site.ground_at(xy, 0.05) - 0.1
        site.b.add(g.cylinder(xy, 0.04, 1.2, z0, g.METAL, 6))
        q = posts[(i + 1) % len(posts)]
        mid, d = 0.5 * (xy + q), q - xy
        for zr in (0.55, 1.05):
            site.b.add(g.box((mid[0], mid[1], z0 + 0.1 + zr), (np.hypot(*d), 0.04, 0.04),
                             float(np.arctan2(d[1], d[0])), g.METAL))  # fmt: skip


def _buildings(site: _ParkSite) -> None:
    """Buildings at the east and north edges, a pavilion in the south-west corner, a kiosk."""
    for p0, p1, h, kw in (
        ((68.0, -38.0), (68.0, -6.0), 12.0, {}),
        ((68.0, 2.0), (68.0, 32.0), 9.0, {"pitch": 2.6}),
        ((45.0, 52.0), (5.0, 52.0), 15.0, {"pitch": 4.0, "win_w": 2.2}),
        ((-66.0, -46.0), (-44.0, -46.0), 5.0, {"pitch": 3.6}),
    ):
        xs, ys = np.linspace(p0[0], p1[0], 9), np.linspace(p0[1], p1[1], 9)
        site.b.add(_on_ground(_facade(p0, p1, h, **kw), float(np.min(site.height(xs, ys))) - 0.5))
    kiosk_z = site.ground_at((6.0, 12.0), 3.0) + 1.3
    site.b.add(g.box((6.0, 12.0, kiosk_z), (5.0, 3.5, 3.2), 0.1, g.WOOD))


_WALKS = (
    ((-20.0, -3.2), (18.0, -3.2)),
    ((22.0, 3.0), (-15.0, 3.0)),
    ((40.0, -30.0), (30.0, -12.0)),
    ((-38.0, 25.0), (-20.0, 30.0)),
    ((50.0, 30.0), (60.0, 40.0)),
    ((-65.0, -25.0), (-40.0, -32.0)),
)


def _walkers(site: _ParkSite) -> list[Pedestrian]:
    """Six pedestrians walking 1.0-1.5 m/s on the terrain, at random phases."""
    peds = []
    for p0, p1 in _WALKS:
        length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
        peds.append(
            Pedestrian(
                p0,
                p1,
                site.rng.uniform(1.0, 1.5),
                phase=site.rng.uniform(0, 2 * length),
                z=(float(site.height(*p0)), float(site.height(*p1))),
            )
        )
    return peds


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
    site = _ParkSite(g.MeshBuilder(), rng, height, path, cKDTree(path))
    _ground(site)
    site.taken.append((POND_CENTRE[0], POND_CENTRE[1], 8.5))
    # Footprints (x0, x1, y0, y1) of the buildings and the kiosk, kept free of objects.
    site.blocked += [(65.0, 80.0, -40.0, 34.0), (3.0, 47.0, 49.0, 66.0)]
    site.blocked += [(-68.0, -42.0, -66.0, -43.0), (2.5, 9.5, 9.5, 14.5)]
    _avenue(site)
    _trees(site)
    _hedges(site)
    _posts(site)
    _pond_fence(site)
    _buildings(site)
    peds = _walkers(site) if pedestrians else []
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
        site.b,
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
    """A 4.6 m lamp pole with a head, standing at height z0 (m)."""
    b.add(g.cylinder(xy, 0.07, 4.6, z0 - 0.1, g.METAL, 8))
    b.add(g.box((xy[0], xy[1], z0 + 4.6), (0.6, 0.3, 0.2), 0.0, g.METAL))


def _sign(b: g.MeshBuilder, xy, z0: float) -> None:
    """A 2.4 m sign post with its plate, standing at height z0 (m)."""
    b.add(g.cylinder(xy, 0.03, 2.4, z0 - 0.1, g.METAL, 6))
    b.add(g.box((xy[0], xy[1], z0 + 2.0), (0.6, 0.03, 0.45), 0.0, g.PAINT))


def _bench(b: g.MeshBuilder, xy, yaw: float, z0: float) -> None:
    """A bench (seat, backrest, metal frame) facing yaw (rad), standing at height z0 (m)."""
    b.add(g.box((xy[0], xy[1], z0 + 0.42), (1.8, 0.45, 0.08), yaw, g.WOOD))
    back = xy + 0.2 * np.array([-np.sin(yaw), np.cos(yaw)])
    b.add(g.box((back[0], back[1], z0 + 0.6), (1.8, 0.06, 0.4), yaw, g.WOOD))
    b.add(g.box((xy[0], xy[1], z0 + 0.14), (1.6, 0.4, 0.48), yaw, g.METAL))
