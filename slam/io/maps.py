"""Map export: voxel-downsampled point cloud written as .pcd or .ply (open3d)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.errors import InputError
from slam.io.points import finite_points

MAP_SUFFIXES = (".pcd", ".ply")
_EMPTY_PCD = (
    "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
    "TYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 0\n"
    "DATA ascii\n"
)
_EMPTY_PLY = (
    "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
    "property float z\nend_header\n"
)


def write_map(path: str | Path, points: np.ndarray, voxel: float) -> int:
    """Voxel-downsample ``points`` (N, 3) m with cell ``voxel`` m (<= 0: keep all) and write
    ``path`` (.pcd or .ply, binary). Returns the number of points written."""
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in MAP_SUFFIXES:
        raise InputError(f"map file {path}: use a .pcd or .ply suffix")
    pts = finite_points(points)
    path.parent.mkdir(parents=True, exist_ok=True)
    if len(pts) == 0:  # open3d refuses to write empty clouds; write a valid empty file
        path.write_text(_EMPTY_PCD if path.suffix.lower() == ".pcd" else _EMPTY_PLY)
        return 0
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if voxel > 0 and len(pts):
        pcd = pcd.voxel_down_sample(float(voxel))
    if not o3d.io.write_point_cloud(str(path), pcd, write_ascii=False):
        raise InputError(f"could not write map {path} (is the folder writable?)")
    return len(pcd.points)
