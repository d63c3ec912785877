"""Primitive builders for simulated scenes: boxes, walls, cylinders, cones, spheres, steps.

Each builder returns a :class:`Part` (vertices (V,3) m, triangles (F,3), reflectivity 0..1).
A :class:`MeshBuilder` collects parts; a scene is a few lines of builder calls.

A part with ``extinction > 0`` is a porous volume (foliage): a closed mesh that rays enter
and, with probability 1 - exp(-extinction * depth), return from inside (see
:meth:`slam.sim.scene.Scene.cast`). :func:`porous` turns a solid part into one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

# Reflectivity of common materials (0..1), drives the simulated intensity.
CONCRETE = 0.45
PAINT = 0.6
WOOD = 0.35
METAL = 0.85
GLASS = 0.08
ASPHALT = 0.18
STONE = 0.3
FOLIAGE = 0.25
BARK = 0.2
SOIL = 0.12
CLOTH = 0.4
GRASS = 0.3

# Extinction coefficients (1/m) of porous vegetation: k = G * LAD with projection factor
# G ~ 0.5 and leaf area density LAD ~ 1-4 m^2/m^3 (tree crowns) or more (clipped hedges).
CROWN_EXTINCTION = 0.9
HEDGE_EXTINCTION = 3.0


@dataclass
class Part:
    """A triangle mesh with one reflectivity. extinction > 0 (1/m): a porous volume."""

    vertices: np.ndarray
    triangles: np.ndarray
    reflectivity: float
    extinction: float = 0.0


def porous(part: Part | list[Part], extinction: float = CROWN_EXTINCTION) -> Part | list[Part]:
    """The same closed mesh(es) as a porous volume with ``extinction`` (1/m)."""
    if isinstance(part, list):
        return [Part(p.vertices, p.triangles, p.reflectivity, extinction) for p in part]
    return Part(part.vertices, part.triangles, part.reflectivity, extinction)


def ellipsoid(
    center, radii, reflectivity: float = FOLIAGE, resolution: int = 10, yaw: float = 0.0
) -> Part:
    """Ellipsoid (m) with semi-axes ``radii`` (rx, ry, rz), rotated by ``yaw`` about z."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution)
    v = np.asarray(mesh.vertices, dtype=float) * np.asarray(radii, dtype=float)
    v = v @ _rot_z(yaw).T + np.asarray(center, dtype=float)
    return Part(v, np.asarray(mesh.triangles, dtype=np.int32), reflectivity)


def height_field(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, reflectivity=ASPHALT
) -> Part | list[Part]:
    """Terrain mesh over the grid ``x`` (nx,) by ``y`` (ny,) with heights ``z`` (ny, nx), m,
    facing up. ``reflectivity``: a number, or (ny-1, nx-1) per grid cell, in which case one
    part per distinct value is returned."""
    xx, yy = np.meshgrid(np.asarray(x, float), np.asarray(y, float))
    v = np.column_stack([xx.ravel(), yy.ravel(), np.asarray(z, float).ravel()])
    nx = len(x)
    i, j = np.meshgrid(np.arange(len(y) - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).ravel()
    quads = np.column_stack([a, a + 1, a + nx + 1, a + nx])
    if np.ndim(reflectivity) == 0:
        tris = np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.int32)
        return Part(v, tris, float(reflectivity))
    cell = np.asarray(reflectivity, dtype=float).ravel()
    parts = []
    for value in np.unique(cell):
        q = quads[cell == value]
        tris = np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]).astype(np.int32)
        parts.append(Part(v, tris, float(value)))
    return parts


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_BOX_TRIS = np.array(
    [
        [0, 2, 1],
        [0, 3, 2],  # bottom z-
        [4, 5, 6],
        [4, 6, 7],  # top z+
        [0, 1, 5],
        [0, 5, 4],  # y-
        [2, 3, 7],
        [2, 7, 6],  # y+
        [1, 2, 6],
        [1, 6, 5],  # x+
        [0, 4, 7],
        [0, 7, 3],  # x-
    ],
    dtype=np.int32,
)


def box(center, size, yaw: float = 0.0, reflectivity: float = CONCRETE) -> Part:
    """Box of ``size`` (sx, sy, sz) m centred at ``center``, rotated by ``yaw`` (rad) about z."""
    h = 0.5 * np.asarray(size, dtype=float)
    corners = np.array(
        [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
        dtype=float,
    ) * h  # fmt: skip
    v = corners @ _rot_z(yaw).T + np.asarray(center, dtype=float)
    return Part(v, _BOX_TRIS.copy(), reflectivity)


def box_minmax(lo, hi, reflectivity: float = CONCRETE) -> Part:
    """Axis-aligned box between corners ``lo`` and ``hi`` (m)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    return box(0.5 * (lo + hi), hi - lo, 0.0, reflectivity)


def wall(
    p0, p1, height: float, thickness: float = 0.2, z0: float = 0.0, reflectivity: float = CONCRETE
) -> Part:
    """Wall segment from xy ``p0`` to ``p1`` (m), centred on that line, ``z0..z0+height``."""
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    d = p1 - p0
    length = float(np.hypot(*d))
    mid = 0.5 * (p0 + p1)
    return box(
        (mid[0], mid[1], z0 + 0.5 * height),
        (length, thickness, height),
        float(np.arctan2(d[1], d[0])),
        reflectivity,
    )


def _from_o3d(mesh: o3d.geometry.TriangleMesh, offset, reflectivity: float) -> Part:
    v = np.asarray(mesh.vertices, dtype=float) + np.asarray(offset, dtype=float)
    return Part(v, np.asarray(mesh.triangles, dtype=np.int32), reflectivity)


def cylinder(
    center_xy,
    radius: float,
    height: float,
    z0: float = 0.0,
    reflectivity: float = METAL,
    resolution: int = 16,
) -> Part:
    """Vertical cylinder (m) standing on ``z0``."""
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution, 1)
    return _from_o3d(mesh, (center_xy[0], center_xy[1], z0 + 0.5 * height), reflectivity)


def cone(
    center_xy,
    radius: float,
    height: float,
    z0: float = 0.0,
    reflectivity: float = FOLIAGE,
    resolution: int = 16,
) -> Part:
    """Upright cone (m) with its base on ``z0``."""
    mesh = o3d.geometry.TriangleMesh.create_cone(radius, height, resolution, 1)
    return _from_o3d(mesh, (center_xy[0], center_xy[1], z0), reflectivity)


def sphere(center, radius: float, reflectivity: float = FOLIAGE, resolution: int = 10) -> Part:
    """Sphere (m)."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution)
    return _from_o3d(mesh, center, reflectivity)


def ground(x_range, y_range, z: float = 0.0, reflectivity: float = ASPHALT) -> Part:
    """Horizontal rectangle (two triangles) at height ``z`` (m), facing up."""
    (x0, x1), (y0, y1) = x_range, y_range
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return Part(v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32), reflectivity)


def steps(
    origin_xy,
    yaw: float,
    n: int,
    rise: float,
    run: float,
    width: float,
    reflectivity: float = STONE,
) -> list[Part]:
    """A flight of ``n`` steps climbing along ``yaw`` from ``origin_xy`` (m); returns parts."""
    fwd = np.array([np.cos(yaw), np.sin(yaw)])
    parts = []
    for i in range(n):
        depth = run * (n - i)  # each block reaches the top landing line
        c = np.asarray(origin_xy, dtype=float) + fwd * (run * i + 0.5 * depth)
        parts.append(
            box(
                (c[0], c[1], 0.5 * rise * (i + 1)),
                (depth, width, rise * (i + 1)),
                yaw,
                reflectivity,
            )
        )
    return parts


@dataclass
class MeshBuilder:
    """Collects parts into one triangle mesh with per-triangle reflectivity."""

    parts: list[Part] = field(default_factory=list)

    def add(self, *parts: Part | list[Part]) -> MeshBuilder:
        for p in parts:
            if isinstance(p, list):
                self.parts.extend(p)
            else:
                self.parts.append(p)
        return self

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The solid parts: vertices (V,3) float64, triangles (F,3) int32, reflectivity
        (F,) float64."""
        return _merge([p for p in self.parts if p.extinction <= 0])[:3]

    def build_porous(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The porous parts as (vertices, triangles, reflectivity, extinction (F,) 1/m), or
        None when there are none."""
        parts = [p for p in self.parts if p.extinction > 0]
        return _merge(parts) if parts else None


def _merge(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    verts, tris, refl, ext = [], [], [], []
    offset = 0
    for p in parts:
        verts.append(p.vertices)
        tris.append(p.triangles + offset)
        refl.append(np.full(len(p.triangles), p.reflectivity))
        ext.append(np.full(len(p.triangles), p.extinction))
        offset += len(p.vertices)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(refl), np.concatenate(ext)
