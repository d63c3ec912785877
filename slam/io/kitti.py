"""KITTI odometry sequences: ``velodyne/*.bin`` (float32 x, y, z, reflectance per point).

The path is the sequence folder or the folder of ``.bin`` scans itself (``SEQ/velodyne``,
or any folder of them). Optional files in the sequence folder (for a bare folder of scans:
beside them, or in the parent when the folder is named ``velodyne``): ``times.txt`` (one
stamp in s per scan; otherwise from numeric file names as for .pcd folders, ``frame_period``
apart for frame counters), ``calib.txt`` (``Tr`` = T_cam0_velo) and ``poses.txt`` (ground
truth, T_cam0start_cam0 as KITTI rows). KITTI gives no ring or per-point time: both are None.
A .bin file that is empty, not a whole number of points or all NaN is yielded as a
SkippedMessage and reading goes on; one that cannot be opened raises InputError.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from slam.config import FRAME_PERIOD_S
from slam.errors import InputError
from slam.io.folders import name_stamps, natural_key, period_note
from slam.io.points import Notes, assemble_scan
from slam.io.skips import CORRUPT_FILE, EMPTY_FILE, FrameError, checked, skip
from slam.io.trajectory import read_kitti
from slam.types import Scan, SkippedMessage


def _has_bins(path: Path) -> bool:
    return path.is_dir() and any(path.glob("*.bin"))


def is_kitti_dir(path: Path) -> bool:
    """True for a directory holding ``.bin`` scans or a ``velodyne/`` folder of them."""
    return _has_bins(path / "velodyne") or _has_bins(path)


def kitti_layout(path: Path) -> tuple[Path, Path]:
    """(scans folder, sequence folder) of a KITTI path: the sequence folder holds
    ``velodyne/``, or ``path`` is the folder of .bin scans (its parent is the sequence when
    it is named ``velodyne`` and the parent holds a times / poses / calib file)."""
    if _has_bins(path / "velodyne"):
        return path / "velodyne", path
    meta = ("times.txt", "poses.txt", "calib.txt")
    if path.name == "velodyne" and not any((path / m).is_file() for m in meta):
        if any((path.parent / m).is_file() for m in meta):
            return path, path.parent
    return path, path


def read_bin(path: str | Path) -> np.ndarray:
    """(N, 4) float32 x, y, z, reflectance of one KITTI ``.bin`` file.

    FrameError when it is empty or not a whole number of 16-byte points; InputError when
    it cannot be opened."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot open {path}: {exc}") from exc
    if not buf:
        raise FrameError(EMPTY_FILE, f"{path}: empty file (0 bytes)")
    if len(buf) % 16:
        raise FrameError(
            CORRUPT_FILE, f"{path}: {len(buf)} bytes is not a whole number of KITTI points"
        )
    return np.frombuffer(buf, dtype="<f4").reshape(-1, 4)


def read_calib_tr(path: str | Path) -> np.ndarray | None:
    """T_cam0_velo (4x4) from the ``Tr:`` line of a KITTI calib.txt, None if absent."""
    for line in Path(path).read_text().splitlines():
        key, _, values = line.partition(":")
        if key.strip() in ("Tr", "Tr_velo_to_cam"):
            T = np.eye(4)
            T[:3, :] = np.array(values.split(), dtype=float).reshape(3, 4)
            return T
    return None


def camera_poses_to_lidar(poses: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """KITTI camera poses (N,4,4) (T_cam0start_cam0, as poses.txt) -> LiDAR poses
    T_velo0_velo = Tr^-1 P Tr, ``tr`` = T_cam0_velo of calib.txt."""
    return np.linalg.inv(tr)[None] @ np.asarray(poses, dtype=float) @ tr[None]


class KittiSource:
    """Scans of a KITTI odometry sequence folder, in file-name order; ``frame_period``: seconds
    between scans without ``times.txt`` (``source.frame_period``)."""

    def __init__(self, path: str | Path, frame_period: float = FRAME_PERIOD_S) -> None:
        given = Path(path)
        if not is_kitti_dir(given):
            raise InputError(
                f"{given}: not a KITTI sequence (expected velodyne/*.bin or *.bin inside)"
            )
        scans_dir, self.path = kitti_layout(given)
        self.files = sorted(scans_dir.glob("*.bin"), key=natural_key)
        times = self.path / "times.txt"
        self._notes = Notes()  # points dropped for absurd coordinates
        self._stamp_notes: list[str] = []  # how scans are stamped without times.txt
        if times.is_file():
            self.stamps = np.loadtxt(times, ndmin=1).astype(np.float64)
            if self.stamps.shape[0] != len(self.files):
                raise InputError(
                    f"{times} has {self.stamps.shape[0]} stamps for {len(self.files)} scans"
                    f" in {scans_dir}: give the sequence a times.txt line per scan"
                )
        else:
            self.stamps, from_period = name_stamps(self.files, frame_period)
            if from_period:
                self._stamp_notes.append(period_note(frame_period))
        self.topic: str | None = None
        what = "KITTI sequence" if scans_dir != given else "KITTI .bin folder"
        self.description = f"{what} {given} ({len(self.files)} scans)"

    @property
    def notes(self) -> list[str]:
        return [*self._notes.lines, *self._stamp_notes]

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Scan | SkippedMessage]:
        for i, f in enumerate(self.files):
            try:
                pts = read_bin(f)
                scan = assemble_scan(
                    pts[:, 0], pts[:, 1], pts[:, 2], stamp=float(self.stamps[i]), index=i,
                    intensity=pts[:, 3], notes=self._notes,
                )  # fmt: skip
            except FrameError as exc:
                yield skip(i, exc, str(f))
                continue
            yield checked(scan, len(pts), str(f), empty=EMPTY_FILE)

    @property
    def calib_file(self) -> Path:
        """The sequence's ``calib.txt`` (it may not exist)."""
        return self.path / "calib.txt"

    def camera_to_lidar(self, poses: np.ndarray) -> np.ndarray | None:
        """KITTI camera poses (N,4,4) (T_cam0start_cam0, as poses.txt) -> LiDAR poses
        T_velo0_velo = Tr^-1 P Tr with the ``Tr`` of calib.txt; None without it."""
        tr = read_calib_tr(self.calib_file) if self.calib_file.is_file() else None
        return None if tr is None else camera_poses_to_lidar(poses, tr)

    def ground_truth(self) -> np.ndarray | None:
        """(N, 4, 4) ground-truth poses in the LiDAR frame (T_velo0_velo), None without poses.txt.

        KITTI poses are camera poses; with calib.txt they are converted by Tr^-1 P Tr
        (without it they are returned as they are).
        """
        poses_file = self.path / "poses.txt"
        if not poses_file.is_file():
            return None
        poses = read_kitti(poses_file)
        lidar = self.camera_to_lidar(poses)
        return poses if lidar is None else lidar
