"""TUM and KITTI trajectory files.

TUM: ``stamp tx ty tz qx qy qz qw`` per line. KITTI: the first 3 rows of the 4x4
pose, row-major, 12 numbers per line, no stamps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from slam.errors import InputError


def poses_to_tum_rows(stamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N,) stamps and (N,4,4) poses -> (N,8) TUM rows."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    quat = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    return np.column_stack([np.asarray(stamps, dtype=float), poses[:, :3, 3], quat])


def tum_rows_to_poses(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,8) TUM rows -> stamps (N,), poses (N,4,4)."""
    rows = np.atleast_2d(np.asarray(rows, dtype=float))
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0].copy(), poses


def write_tum(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    rows = poses_to_tum_rows(stamps, poses)
    np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """stamps (N,), poses (N,4,4) from a TUM file; comment lines start with '#'."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}")
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        raise InputError(
            f"{path}: not a TUM trajectory (stamp tx ty tz qx qy qz qw): {exc}"
        ) from exc
    if rows.size == 0:
        raise InputError(f"{path}: trajectory is empty")
    if rows.shape[1] != 8:
        raise InputError(f"{path}: expected 8 columns (TUM), found {rows.shape[1]}")
    return tum_rows_to_poses(rows)


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    np.savetxt(path, poses[:, :3, :].reshape(-1, 12), fmt="%.9e")


def read_kitti(path: str | Path) -> np.ndarray:
    """(N,4,4) poses from a KITTI pose file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}")
    rows = np.loadtxt(path, ndmin=2)
    if rows.shape[1] != 12:
        raise InputError(f"{path}: expected 12 columns (KITTI), found {rows.shape[1]}")
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses
