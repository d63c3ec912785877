"""Folders of ``.pcd`` / ``.ply`` scans (one file per scan), read with open3d.t.io.

Files are sorted naturally by name (``2.pcd`` before ``10.pcd``). Stamps come from the
file names when all of them are numbers (seconds; values above 1e15 are taken as ns, above
1e12 as us), else index * ``frame_period`` (``source.frame_period``, 0.1 s by default;
frame numbers: number * ``frame_period``). Intensity, ring and per-point time are kept when
the files have such attributes (``intensity``, ``ring``, ``time``, ...). A file that cannot be
decoded (empty, truncated, no x/y/z, all points NaN) is yielded as a SkippedMessage and
reading goes on; a file that cannot be opened at all raises InputError.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from slam.config import FRAME_PERIOD_S
from slam.errors import InputError
from slam.io.pcd import read_pcd_columns
from slam.io.points import INTENSITY_NAMES, RING_NAMES, TIME_NAMES, Notes, assemble_scan, pick
from slam.io.skips import CORRUPT_FILE, EMPTY_FILE, NO_XYZ, FrameError, checked, skip
from slam.types import Scan, SkippedMessage

SUFFIXES = (".pcd", ".ply")


def natural_key(path: Path) -> list:
    """Sort key that orders embedded numbers by value."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", path.name)]


def cloud_files(path: Path) -> list[Path]:
    """The .pcd/.ply files of a folder, naturally sorted."""
    return sorted((p for p in path.iterdir() if p.suffix.lower() in SUFFIXES), key=natural_key)


def name_stamps(files: list[Path], period: float = FRAME_PERIOD_S) -> tuple[np.ndarray, bool]:
    """(stamps in s, True when they come from ``period``: the names are no stamps): parsed
    from numeric file stems, or index * ``period`` when any does not parse.

    Zero-padded frame counters (``0000000000.pcd``, ``000001.bin``: small integers mostly
    one apart) are frame numbers, not seconds: number * ``period``."""
    try:
        values = np.array([float(f.stem) for f in files], dtype=np.float64)
    except ValueError:
        return np.arange(len(files)) * period, True
    if (
        values.size > 1
        and np.all(values == np.round(values))
        and values.max() < 1e6
        and np.median(np.diff(np.sort(values))) == 1.0
    ):
        return values * period, True
    if values.size and values.min() > 1e15:
        return values * 1e-9, False
    if values.size and values.min() > 1e12:
        return values * 1e-6, False
    return values, False


def period_note(period: float) -> str:
    """The input note of scans stamped from their numbers (``source.frame_period``)."""
    return (
        f"the file names are frame numbers, not stamps: scans are {period:g} s apart "
        f"({1 / period:g} Hz; --set source.frame_period=SECONDS for another rate)"
    )


def _open3d_columns(path: Path) -> dict[str, np.ndarray]:
    """Columns of a .ply (or binary_compressed .pcd) file read with open3d.t.io."""
    import open3d as o3d

    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            pcd = o3d.t.io.read_point_cloud(str(path))
    except Exception as exc:  # open3d raises RuntimeError with its own message
        raise FrameError(CORRUPT_FILE, f"cannot read point cloud {path}: {exc}") from exc
    if "positions" not in pcd.point:
        if path.stat().st_size == 0:
            raise FrameError(EMPTY_FILE, f"{path}: empty file (0 bytes)")
        raise FrameError(CORRUPT_FILE, f"{path}: no points (empty or unreadable file)")
    xyz = pcd.point.positions.numpy().reshape(-1, 3)
    cols = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    for name in (*INTENSITY_NAMES, *RING_NAMES, *TIME_NAMES):
        if name in pcd.point:
            cols[name] = pcd.point[name].numpy()[:, 0]
    return cols


def cloud_columns(path: str | Path, notes: Notes | None = None) -> dict[str, np.ndarray]:
    """One (N,) column per field of a .pcd/.ply file (first element of multi-count fields).

    PCD ascii/binary: numpy (:mod:`slam.io.pcd`); PLY and binary_compressed PCD: open3d.
    Raises FrameError naming the file and why; OSError when the file cannot be opened.
    """
    path = Path(path)
    if path.suffix.lower() != ".pcd":
        return _open3d_columns(path)
    buf = path.read_bytes()
    try:
        return read_pcd_columns(buf, str(path), notes)[1]
    except NotImplementedError:
        return _open3d_columns(path)


def read_cloud(
    path: str | Path, *, index: int = 0, stamp: float = 0.0, notes: Notes | None = None
) -> Scan:
    """One .pcd/.ply file -> Scan (non-finite points dropped; see ``assemble_scan``).

    Per-point time (``time``/``t``/``timestamp``/``offset_time``) in s, ms, us or ns,
    relative or absolute, is converted as for PointCloud2; with absolute times the stamp
    is the earliest point's time. Raises FrameError when the file holds no x/y/z or is
    malformed, InputError when it cannot be opened.
    """
    path = Path(path)
    try:
        cols = cloud_columns(path, notes)
    except OSError as exc:
        raise InputError(f"cannot open {path}: {exc}") from exc
    missing = [c for c in "xyz" if c not in cols]
    if missing:
        raise FrameError(NO_XYZ, f"{path}: no field(s) {missing}; fields are {sorted(cols)}")
    ni, nr, nt = (pick(names, cols) for names in (INTENSITY_NAMES, RING_NAMES, TIME_NAMES))
    return assemble_scan(
        cols["x"],
        cols["y"],
        cols["z"],
        stamp=stamp,
        index=index,
        intensity=None if ni is None else cols[ni],
        ring=None if nr is None else (nr, cols[nr]),
        time=None if nt is None else (nt, cols[nt]),
        notes=notes,
    )


def is_cloud_dir(path: Path) -> bool:
    return path.is_dir() and any(p.suffix.lower() in SUFFIXES for p in path.iterdir())


class FolderSource:
    """Scans of a folder of .pcd/.ply files; ``notes``: degradations met, once each, and
    how the scans were stamped when their names are no stamps. ``frame_period``: seconds
    between numbered scans (``source.frame_period``)."""

    def __init__(self, path: str | Path, frame_period: float = FRAME_PERIOD_S) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise InputError(f"{self.path}: not a folder")
        self.files = cloud_files(self.path)
        if not self.files:
            raise InputError(f"{self.path} contains no .pcd or .ply files")
        self.stamps, from_period = name_stamps(self.files, frame_period)
        self.topic: str | None = None
        self.description = f"point-cloud folder {self.path} ({len(self.files)} files)"
        self._notes = Notes()
        self._stamp_notes = [period_note(frame_period)] if from_period else []

    @property
    def notes(self) -> list[str]:
        return [*self._notes.lines, *self._stamp_notes]

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Scan | SkippedMessage]:
        for i, f in enumerate(self.files):
            try:
                scan = read_cloud(f, index=i, stamp=float(self.stamps[i]), notes=self._notes)
            except FrameError as exc:
                yield skip(i, exc, str(f))
                continue
            yield checked(scan, _raw_count(f), str(f), empty=EMPTY_FILE)


def _raw_count(path: Path) -> int:
    """How many points a file declares (only asked when none was kept): 0 or >0."""
    try:
        return read_pcd_columns(path.read_bytes(), str(path))[0].points
    except (FrameError, NotImplementedError, OSError):
        return 1
