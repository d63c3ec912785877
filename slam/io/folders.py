"""Folders of ``.pcd`` / ``.ply`` scans (one file per scan), read with open3d.t.io.

Files are sorted naturally by name (``2.pcd`` before ``10.pcd``). Stamps come from the
file names when all of them are numbers (seconds; values above 1e15 are taken as ns, above
1e12 as us), else index * 0.1 s. Intensity, ring and per-point time are kept when the files
have such attributes (``intensity``, ``ring``, ``time``).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from slam.errors import InputError
from slam.types import Scan

SUFFIXES = (".pcd", ".ply")
SCAN_PERIOD_S = 0.1


def natural_key(path: Path) -> list:
    """Sort key that orders embedded numbers by value."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", path.name)]


def cloud_files(path: Path) -> list[Path]:
    """The .pcd/.ply files of a folder, naturally sorted."""
    return sorted((p for p in path.iterdir() if p.suffix.lower() in SUFFIXES), key=natural_key)


def stamps_from_names(files: list[Path]) -> np.ndarray:
    """Stamps (s) parsed from numeric file stems, or index * 0.1 when any does not parse."""
    try:
        values = np.array([float(f.stem) for f in files], dtype=np.float64)
    except ValueError:
        return np.arange(len(files)) * SCAN_PERIOD_S
    if values.size and values.min() > 1e15:
        return values * 1e-9
    if values.size and values.min() > 1e12:
        return values * 1e-6
    return values


def read_cloud(path: str | Path, *, index: int = 0, stamp: float = 0.0) -> Scan:
    """One .pcd/.ply file -> Scan (non-finite points dropped)."""
    import open3d as o3d

    path = Path(path)
    try:
        pcd = o3d.t.io.read_point_cloud(str(path))
    except Exception as exc:  # open3d raises RuntimeError with its own message
        raise InputError(f"cannot read point cloud {path}: {exc}") from exc
    if "positions" not in pcd.point:
        raise InputError(f"{path}: no points (empty or unreadable file)")
    xyz = pcd.point.positions.numpy().astype(np.float64).reshape(-1, 3)
    keep = np.isfinite(xyz).all(axis=1)

    def attr(name: str, dtype: type) -> np.ndarray | None:
        if name not in pcd.point:
            return None
        return pcd.point[name].numpy().reshape(-1)[keep].astype(dtype)

    time = attr("time", np.float64)
    if time is not None and time.size:
        time = time - time.min()
    return Scan(
        stamp=stamp,
        xyz=xyz[keep],
        intensity=attr("intensity", np.float32),
        ring=attr("ring", np.int16),
        time=time,
        index=index,
    )


def is_cloud_dir(path: Path) -> bool:
    return path.is_dir() and any(p.suffix.lower() in SUFFIXES for p in path.iterdir())


class FolderSource:
    """Scans of a folder of .pcd/.ply files."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise InputError(f"{self.path}: not a folder")
        self.files = cloud_files(self.path)
        if not self.files:
            raise InputError(f"{self.path} contains no .pcd or .ply files")
        self.stamps = stamps_from_names(self.files)
        self.topic: str | None = None
        self.description = f"point-cloud folder {self.path} ({len(self.files)} files)"

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Scan]:
        for i, f in enumerate(self.files):
            yield read_cloud(f, index=i, stamp=float(self.stamps[i]))
