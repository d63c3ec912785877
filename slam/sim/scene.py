"""A ray-castable scene: static triangle mesh (open3d RaycastingScene) + walking pedestrians
+ optional porous vegetation.

Pedestrians are boxes intersected analytically (slab test) at each ray's own time, so a
person walking past is as distorted as it would be in a real sweep.

Porous vegetation (tree crowns, hedges) is a second mesh of closed volumes with an
extinction coefficient k (1/m): a ray inside such a volume returns within depth d with
probability 1 - exp(-k d) (Beer-Lambert), at a random depth; otherwise it passes through.
Tree crowns thus give the sparse, scattered returns of real foliage, and what stands
behind them is partly visible.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from slam.errors import InputError
from slam.sim.geometry import CLOTH, MeshBuilder, Part
from slam.sim.lidar import LidarModel, RayHits
from slam.sim.trajectory import Trajectory


@dataclass
class Pedestrian:
    """A box walking back and forth between xy ``p0`` and ``p1`` (m) at ``speed`` (m/s).

    size: (along, across, height) m. phase: distance (m) already walked at t = 0.
    z: ground height (m) at p0 and p1 (linear in between), for uneven terrain.
    """

    p0: tuple[float, float]
    p1: tuple[float, float]
    speed: float = 1.2
    size: tuple[float, float, float] = (0.5, 0.5, 1.7)
    phase: float = 0.0
    z: tuple[float, float] = (0.0, 0.0)

    def position(self, times: np.ndarray) -> np.ndarray:
        """(M,3) centre of the box footprint on the ground at ``times`` (s)."""
        p0, p1 = np.asarray(self.p0, dtype=float), np.asarray(self.p1, dtype=float)
        length = float(np.hypot(*(p1 - p0)))
        u = np.mod(self.phase + self.speed * np.asarray(times, dtype=float), 2 * length)
        d = np.where(u < length, u, 2 * length - u)
        xy = p0 + np.outer(d / length, p1 - p0)
        z = np.zeros(len(d))
        if self.z[0] or self.z[1]:
            z = self.z[0] + (d / length) * (self.z[1] - self.z[0])
        return np.column_stack([xy, z])

    @property
    def yaw(self) -> float:
        return float(np.arctan2(self.p1[1] - self.p0[1], self.p1[0] - self.p0[0]))

    def intersect(
        self, origins: np.ndarray, dirs: np.ndarray, times: np.ndarray, group: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance (M,) along unit rays to the box at each ray's time (inf = miss) and the
        cosine of incidence (M,). ``group``: consecutive rays sharing origin, time and
        (nearly) azimuth, as the beams of one LiDAR column; used for fast culling."""
        m = len(origins)
        dist = np.full(m, np.inf)
        cos_inc = np.zeros(m)
        half = 0.5 * np.asarray(self.size, dtype=float)
        # Cull whole groups in 2D with a circle bounding the box during the rays' time span.
        t_lo, t_hi = float(np.min(times)), float(np.max(times))
        mid = self.position(np.array([0.5 * (t_lo + t_hi)]))[0, :2]
        radius = float(np.hypot(half[0], half[1])) + 0.5 * self.speed * (t_hi - t_lo) + 0.02
        o = origins[::group, :2]
        a = dirs[::group, :2]
        a = a / np.maximum(np.hypot(a[:, 0], a[:, 1]), 1e-9)[:, None]
        w = mid - o
        along = w[:, 0] * a[:, 0] + w[:, 1] * a[:, 1]
        perp = np.abs(w[:, 0] * a[:, 1] - w[:, 1] * a[:, 0])
        # 0.02 * along: beams of a tilted sensor leave the column's vertical plane slightly.
        keep = np.flatnonzero((perp <= radius + 0.02 * np.abs(along)) & (along > -radius))
        if keep.size == 0:
            return dist, cos_inc
        sel = (keep[:, None] * group + np.arange(group)[None, :]).ravel()
        sel = sel[sel < m]
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box
        centre = self.position(times[sel])
        centre[:, 2] += half[2]
        o3 = (origins[sel] - centre) @ R.T
        d = dirs[sel] @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1 = (-half - o3) * inv
            t2 = (half - o3) * inv
        tlo = np.fmin(t1, t2)
        thi = np.fmax(t1, t2)
        tmin = tlo.max(axis=1)
        tmax = thi.min(axis=1)
        hit = (tmax >= tmin) & (tmin > 0)
        face = np.argmax(tlo, axis=1)  # the slab entered last is the face hit
        dist[sel[hit]] = tmin[hit]
        cos_inc[sel] = np.abs(d[np.arange(sel.size), face])
        return dist, cos_inc


@dataclass
class Scene:
    """A simulated world: static mesh, pedestrians, the robot's trajectory and hints.

    loop_max_radius: a sensible Scan Context max radius (m). revisit_radius: two ground
    truth poses closer than this (m) are "the same place" for loop-closure evaluation.
    porous_*: the porous vegetation mesh (closed volumes), per-triangle reflectivity and
    extinction (1/m); None = no porous geometry. sensor: the LiDAR model this scene is
    simulated with when none is given (None = the default :class:`LidarModel`).
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    reflectivity: np.ndarray  # (F,) per triangle
    trajectory: Trajectory | None = None
    pedestrians: list[Pedestrian] = field(default_factory=list)
    loop_max_radius: float = 30.0
    revisit_radius: float = 3.0
    description: str = ""
    porous_vertices: np.ndarray | None = None
    porous_triangles: np.ndarray | None = None
    porous_reflectivity: np.ndarray | None = None
    porous_extinction: np.ndarray | None = None
    sensor: LidarModel | None = None
    _raycaster: o3d.t.geometry.RaycastingScene | None = field(default=None, init=False, repr=False)
    _porous_caster: o3d.t.geometry.RaycastingScene | None = field(
        default=None, init=False, repr=False
    )

    @classmethod
    def from_parts(cls, name: str, parts: list[Part], **kwargs) -> Scene:
        """A scene from primitive parts (see :mod:`slam.sim.geometry`); parts with
        extinction > 0 become porous volumes."""
        return cls.from_builder(name, MeshBuilder(list(parts)), **kwargs)

    @classmethod
    def from_builder(cls, name: str, builder: MeshBuilder, **kwargs) -> Scene:
        """A scene from the solid and porous parts collected by ``builder``."""
        v, t, r = builder.build()
        porous = builder.build_porous()
        if porous is not None:
            pv, pt, pr, pe = porous
            kwargs.update(
                porous_vertices=pv,
                porous_triangles=pt,
                porous_reflectivity=pr,
                porous_extinction=pe,
            )
        return cls(name, v, t, r, **kwargs)

    @property
    def duration(self) -> float:
        """Length of the drive (s); 0 without a trajectory."""
        return 0.0 if self.trajectory is None else self.trajectory.duration

    def pose_at(self, times) -> np.ndarray:
        """(M,4,4) T_world_sensor at ``times`` (s from the start)."""
        if self.trajectory is None:
            raise InputError(f"scene {self.name!r} has no trajectory")
        return self.trajectory.pose_at(times)

    @property
    def raycaster(self) -> o3d.t.geometry.RaycastingScene:
        if self._raycaster is None:
            self._raycaster = _raycasting_scene(self.vertices, self.triangles)
        return self._raycaster

    @property
    def porous_caster(self) -> o3d.t.geometry.RaycastingScene | None:
        """Raycaster of the porous vegetation (None without)."""
        if self._porous_caster is None and self.porous_vertices is not None:
            self._porous_caster = _raycasting_scene(self.porous_vertices, self.porous_triangles)
        return self._porous_caster

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """The static scene as a legacy open3d mesh (for viewing / export)."""
        return o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles)
        )

    def cast(
        self,
        origins: np.ndarray,
        dirs: np.ndarray,
        times: np.ndarray | None = None,
        *,
        pedestrians: bool = True,
        group: int = 1,
        rng: np.random.Generator | None = None,
    ) -> RayHits:
        """First hits of unit rays (M,3) in the world frame at scene ``times`` (M,) s.

        group: consecutive rays that share origin and time (beams of a column), for speed.
        rng: draws the returns inside porous vegetation (only used when the scene has some;
        default: a fixed seed).
        """
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        out = self.raycaster.cast_rays(o3d.core.Tensor(rays))
        dist = out["t_hit"].numpy().astype(np.float64)
        prim = out["primitive_ids"].numpy().astype(np.int64)
        normals = out["primitive_normals"].numpy().astype(np.float64)
        hit = np.isfinite(dist)
        refl = np.zeros(len(dist))
        refl[hit] = self.reflectivity[prim[hit]]
        cos_inc = np.abs(np.sum(normals * dirs, axis=1))
        porous = None
        if self.porous_caster is not None:
            porous = self._cast_porous(origins, dirs, dist, refl, cos_inc, rng)
        dynamic = np.zeros(len(dist), dtype=bool)
        if pedestrians and self.pedestrians and times is not None:
            for ped in self.pedestrians:
                d, c = ped.intersect(origins, dirs, times, group)
                closer = d < dist
                dist[closer] = d[closer]
                refl[closer] = CLOTH
                cos_inc[closer] = c[closer]
                dynamic[closer] = True
                if porous is not None:
                    porous[closer] = False
        return RayHits(dist, refl, cos_inc, dynamic, porous)

    def _cast_porous(
        self,
        origins: np.ndarray,
        dirs: np.ndarray,
        dist: np.ndarray,
        refl: np.ndarray,
        cos_inc: np.ndarray,
        rng: np.random.Generator | None,
        max_crossings: int = 8,
    ) -> np.ndarray:
        """Returns inside porous volumes in front of the solid hits ``dist``; updates
        dist / refl / cos_inc in place and returns the (M,) porous flags.

        Walks each ray through the porous surfaces it crosses (entering where the surface
        faces the ray, leaving where it faces away). Inside a volume of extinction k, a
        segment of length L returns with probability 1 - exp(-k L), at an exponentially
        distributed depth; leaves are randomly oriented (|cos incidence| uniform)."""
        rng = rng if rng is not None else np.random.default_rng(0)
        flags = np.zeros(len(dist), dtype=bool)
        k_tab, refl_tab = self.porous_extinction, self.porous_reflectivity
        eps = 1e-3
        # State of the rays still travelling through vegetation (compacted each step).
        ids = np.arange(len(dist))  # ray index
        o, d, end = origins, dirs, dist
        t = np.zeros(len(dist))  # distance travelled
        inside = np.zeros(len(dist), dtype=np.int32)  # number of volumes the ray is in
        k = np.zeros(len(dist))  # extinction of the volume entered last
        rr = np.zeros(len(dist))  # its reflectivity
        for _ in range(max_crossings):
            if ids.size == 0:
                break
            rays = np.concatenate([o + d * t[:, None], d], axis=1).astype(np.float32)
            out = self.porous_caster.cast_rays(o3d.core.Tensor(rays))
            step = out["t_hit"].numpy().astype(np.float64)
            nxt = t + step  # next crossing (inf: none)
            inn = np.flatnonzero(inside > 0)
            returned = np.zeros(ids.size, dtype=bool)
            if inn.size:
                # Inside a volume: a return before the next crossing or the solid hit. A
                # ray finding no further porous surface (an open mesh) gets no return.
                depth = rng.exponential(1.0, inn.size) / k[inn]
                seg_end = np.where(np.isfinite(nxt[inn]), np.minimum(nxt[inn], end[inn]), 0.0)
                hit = inn[t[inn] + depth < seg_end]
                r_ids = ids[hit]
                dist[r_ids] = t[hit] + depth[t[inn] + depth < seg_end]
                refl[r_ids] = rr[hit]
                cos_inc[r_ids] = rng.random(hit.size)
                flags[r_ids] = True
                returned[hit] = True
            go = np.flatnonzero(np.isfinite(nxt) & (nxt < end) & ~returned)
            prim = out["primitive_ids"].numpy()[go].astype(np.int64)
            nrm = out["primitive_normals"].numpy()[go].astype(np.float64)
            ids, o, d, end, t = ids[go], o[go], d[go], end[go], nxt[go] + eps
            inside, k, rr = inside[go], k[go], rr[go]
            entering = np.sum(nrm * d, axis=1) < 0
            inside = np.maximum(inside + np.where(entering, 1, -1), 0)
            k = np.where(entering, k_tab[prim], k)
            rr = np.where(entering, refl_tab[prim], rr)
        return flags


def _raycasting_scene(vertices: np.ndarray, triangles: np.ndarray):
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(vertices.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(triangles.astype(np.int32))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(mesh)
    return rc
