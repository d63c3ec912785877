"""TUM and KITTI trajectory files.

TUM: ``stamp tx ty tz qx qy qz qw`` per line. KITTI: the first 3 rows of the 4x4
pose, row-major, 12 numbers per line, no stamps.
"""

from __future__ import annotations

import warnings
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
    """(N,8) TUM rows -> stamps (N,), poses (N,4,4). InputError for a row with a
    non-finite value or a zero quaternion (``check_rows`` names its file and line)."""
    rows = np.atleast_2d(np.asarray(rows, dtype=float))
    bad = bad_tum_rows(rows)
    if bad.size:
        raise InputError(f"TUM row {bad[0]}: {_row_problem(rows[bad[0]])}")
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:8]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0].copy(), poses


def bad_tum_rows(rows: np.ndarray) -> np.ndarray:
    """Indices of (N,8) TUM rows that are no pose: a value not finite, or a quaternion of
    (near) zero norm (scipy cannot normalise it)."""
    rows = np.atleast_2d(np.asarray(rows, dtype=float))
    norm = np.linalg.norm(rows[:, 4:8], axis=1)
    return np.flatnonzero(~np.all(np.isfinite(rows), axis=1) | ~(norm > 1e-9))


def _row_problem(row: np.ndarray) -> str:
    if not np.all(np.isfinite(row)):
        return f"values not finite ({' '.join(f'{v:g}' for v in row)})"
    return f"zero quaternion qx qy qz qw = {' '.join(f'{v:g}' for v in row[4:8])}"


def data_line_numbers(path: str | Path) -> np.ndarray:
    """1-based line number of each data row of a text trajectory (blank lines and '#'
    comments skipped, as ``np.loadtxt(comments='#')`` does): for messages naming a line."""
    lines = Path(path).read_text(errors="replace").splitlines()
    return np.array([i for i, ln in enumerate(lines, 1) if ln.split("#", 1)[0].strip()])


def check_rows(rows: np.ndarray, path: str | Path) -> None:
    """InputError naming the file and line of the first row that is no pose: a value not
    finite (any format), or a zero quaternion (TUM, 8 columns)."""
    rows = np.atleast_2d(rows)
    if rows.shape[1] == 8:
        bad = bad_tum_rows(rows)
    else:
        bad = np.flatnonzero(~np.all(np.isfinite(rows), axis=1))
    if not bad.size:
        return
    line = data_line_numbers(path)[bad[0]]
    more = f" ({bad.size} such rows)" if bad.size > 1 else ""
    what = _row_problem(rows[bad[0]]) if rows.shape[1] == 8 else "values not finite"
    raise InputError(
        f"{path}, line {line}: {what}{more}; a pose needs finite numbers"
        + (" and a unit quaternion" if rows.shape[1] == 8 else "")
    )


def write_tum(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    rows = poses_to_tum_rows(stamps, poses)
    np.savetxt(path, rows, fmt="%.9f", header="timestamp tx ty tz qx qy qz qw")


def load_rows(path: str | Path, what: str) -> np.ndarray:
    """(N, columns) numbers of a trajectory file ('#' comments and blank lines skipped).

    InputError when the file is missing, empty, or not ``what`` (named in the message)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"trajectory file not found: {path}")
    try:
        with warnings.catch_warnings():  # numpy warns on a file of comments only
            warnings.simplefilter("ignore", UserWarning)
            rows = np.loadtxt(path, comments="#", ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not {what}: {exc}") from exc
    if rows.size == 0:
        raise InputError(f"{path}: trajectory is empty")
    return rows


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """stamps (N,), poses (N,4,4) from a TUM file; comment lines start with '#'."""
    rows = load_rows(path, "a TUM trajectory (stamp tx ty tz qx qy qz qw)")
    if rows.shape[1] != 8:
        raise InputError(f"{path}: expected 8 columns (TUM), found {rows.shape[1]}")
    check_rows(rows, path)
    return tum_rows_to_poses(rows)


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    poses = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    np.savetxt(path, poses[:, :3, :].reshape(-1, 12), fmt="%.9e")


def read_kitti(path: str | Path) -> np.ndarray:
    """(N,4,4) poses from a KITTI pose file."""
    rows = load_rows(path, "a KITTI pose file (12 numbers per line)")
    if rows.shape[1] != 12:
        raise InputError(f"{path}: expected 12 columns (KITTI), found {rows.shape[1]}")
    check_rows(rows, path)
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses
