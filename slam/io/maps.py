"""Map export: a voxel-centroid map built by streaming clouds into an accumulator, written
as a binary .pcd or .ply (float32 x y z).

A run's map is not the concatenation of every keyframe cloud (that grows with the path and
was copied twice more by the writer): :class:`VoxelCentroidMap` takes one transformed cloud
at a time, keeps per occupied voxel the sum and count of its points, and merges buffered
clouds into its sorted voxel table every ``chunk_points`` points. Memory is bounded by the
number of occupied voxels (24 bytes each) plus one chunk (about 60 bytes a point).
:func:`voxel_centroids` is the one-shot numpy reference it equals.
"""

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
# voxel keys: 21 bits per axis around the origin, i.e. +-2^20 voxels (+-105 km at 0.1 m)
_BITS = 21
_HALF = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def _cells(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer voxel coordinates (float64 (N, 3)) and the mask of those inside the key range."""
    cells = np.floor(np.asarray(points, dtype=np.float64) / voxel)
    return cells, np.all(np.abs(cells) < _HALF, axis=1)


def _pack(cells: np.ndarray) -> np.ndarray:
    c = cells.astype(np.int64) + _HALF
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


def voxel_corner(keys: np.ndarray, voxel: float) -> np.ndarray:
    """(M, 3) float64 lower corner (m) of the voxels with these keys (inverse of the key)."""
    c = [((keys >> (shift * _BITS)) & _MASK) - _HALF for shift in (2, 1, 0)]
    return np.column_stack(c).astype(np.float64) * voxel


def voxel_key(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Absolute int64 key of the voxel (edge ``voxel`` m, grid through the origin) holding
    each of ``points`` (N, 3) m, and the mask of points inside the key range (+-2^20
    voxels per axis); keys are equal exactly when the voxels are."""
    cells, inside = _cells(points, voxel)
    return _pack(cells[inside]), inside


def voxel_centroids(points: np.ndarray, voxel: float) -> np.ndarray:
    """Reference: (M, 3) float64 centroid of the finite points in each occupied voxel,
    ordered by voxel key (what :class:`VoxelCentroidMap` returns for the same points)."""
    pts = finite_points(np.asarray(points, dtype=np.float64))
    keys, inside = voxel_key(pts, voxel)
    uniq, inv = np.unique(keys, return_inverse=True)
    counts = np.bincount(inv, minlength=len(uniq)).astype(np.float64)
    cols = [np.bincount(inv, weights=pts[inside, a], minlength=len(uniq)) for a in range(3)]
    return np.column_stack(cols) / counts[:, None]


class VoxelCentroidMap:
    """Streaming voxel-centroid accumulator (a sorted hash of voxel sums and counts).

    ``add`` buffers one cloud (N, 3) m, already in the map frame; when the buffer holds
    ``chunk_points`` points (up to 4 x that on large maps: a quarter of the table's voxels,
    so that the O(M) merges stay few) it is reduced per voxel and merged into the
    table (one ``searchsorted`` pass, no per-point Python). ``centroids()`` gives (M, 3)
    float64. The table holds per voxel its int64 key, the float32 sum of the points'
    offsets from the voxel's corner (< voxel each: exact to ~1e-8 m, unlike float32
    world coordinates) and a uint32 count: 24 bytes a voxel.
    voxel <= 0 keeps every point (float32), as ``write_map`` does. Points farther than
    2^20 voxels from the origin (a run-away estimate) are dropped and counted in
    ``dropped``.
    """

    def __init__(self, voxel: float, chunk_points: int = 262_144):
        if chunk_points < 1:
            raise InputError(f"chunk_points must be >= 1, got {chunk_points}")
        self.voxel = float(voxel)
        self.chunk_points = int(chunk_points)
        self.dropped = 0
        self.points_added = 0
        self._keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, 3), dtype=np.float32)  # offsets from the voxel corner
        self._counts = np.zeros(0, dtype=np.uint32)
        self._buffer: list[np.ndarray] = []  # offsets not merged yet (voxel <= 0: the map)
        self._buffer_keys: list[np.ndarray] = []  # their voxel keys
        self._buffered = 0

    def __len__(self) -> int:
        self._merge()
        return len(self._keys) if self.voxel > 0 else self._buffered

    def add(self, points: np.ndarray) -> None:
        """Add one cloud (N, 3) m in the map frame (non-finite points are ignored)."""
        pts = finite_points(np.asarray(points))
        if len(pts) == 0:
            return
        self.points_added += len(pts)
        if self.voxel <= 0:  # keep all: the buffer is the map
            self._buffer.append(np.asarray(pts, dtype=np.float32))
            self._buffered += len(pts)
            return
        cells, inside = _cells(pts, self.voxel)
        if not inside.all():
            self.dropped += int(len(pts) - inside.sum())
            pts, cells = pts[inside], cells[inside]
        self._buffer.append((pts - cells * self.voxel).astype(np.float32))
        self._buffer_keys.append(_pack(cells))
        self._buffered += len(pts)
        if self._buffered >= min(
            max(self.chunk_points, len(self._keys) // 4), 4 * self.chunk_points
        ):
            self._merge()

    def add_transformed(self, points: np.ndarray, T: np.ndarray) -> None:
        """Add ``points`` (N, 3) m of a sensor frame placed by ``T`` (4x4 T_map_sensor)."""
        if len(points) == 0:
            return
        T = np.asarray(T, dtype=np.float64)
        self.add(np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3])

    def _merge(self) -> None:
        if self.voxel <= 0 or not self._buffer:
            return
        offsets, keys = np.concatenate(self._buffer), np.concatenate(self._buffer_keys)
        self._buffer, self._buffer_keys, self._buffered = [], [], 0
        uniq, inv = np.unique(keys, return_inverse=True)
        del keys
        counts = np.bincount(inv, minlength=len(uniq)).astype(np.uint32)
        sums = np.column_stack(
            [np.bincount(inv, weights=offsets[:, a], minlength=len(uniq)) for a in range(3)]
        ).astype(np.float32)
        del offsets, inv
        pos = np.searchsorted(self._keys, uniq)
        known = pos < len(self._keys)
        known[known] = self._keys[pos[known]] == uniq[known]
        self._sums[pos[known]] += sums[known]
        self._counts[pos[known]] += counts[known]
        new = ~known
        if new.any():  # insert the new voxels at their sorted places
            at = pos[new]
            self._keys = np.insert(self._keys, at, uniq[new])
            self._sums = np.insert(self._sums, at, sums[new], axis=0)
            self._counts = np.insert(self._counts, at, counts[new])

    def _centroids(self, lo: int, hi: int) -> np.ndarray:
        """Centroids (float64) of table rows lo..hi-1."""
        mean = self._sums[lo:hi].astype(np.float64) / self._counts[lo:hi, None]
        return voxel_corner(self._keys[lo:hi], self.voxel) + mean

    def write(self, path: str | Path, block: int = 1 << 20) -> int:
        """Write the centroids to ``path`` (.pcd/.ply, binary float32) ``block`` voxels at a
        time (no full float64 copy of the map); returns the number of points written."""
        path = _map_path(path)
        if self.voxel <= 0:
            return write_points(path, self.centroids())
        self._merge()
        n = len(self._keys)
        blocks = (self._centroids(i, min(i + block, n)) for i in range(0, n, block))
        return _write_blocks(path, n, blocks)

    def centroids(self) -> np.ndarray:
        """(M, 3) centroid of each occupied voxel, by voxel key (voxel <= 0: every point)."""
        if self.voxel <= 0:
            if not self._buffer:
                return np.zeros((0, 3), dtype=np.float32)
            return np.concatenate(self._buffer)
        self._merge()
        return self._centroids(0, len(self._keys))


def _map_path(path: str | Path) -> Path:
    path = Path(path)
    if path.suffix.lower() not in MAP_SUFFIXES:
        raise InputError(f"map file {path}: use a .pcd or .ply suffix")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _header(suffix: str, n: int) -> bytes:
    """Header of a binary float32 x y z .pcd or .ply file of ``n`` points."""
    if suffix == ".pcd":
        text = (
            "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
            f"SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
        )
    else:
        text = (
            f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n"
            "property float y\nproperty float z\nend_header\n"
        )
    return text.encode("ascii")


def _write_blocks(path: Path, n: int, blocks) -> int:
    """Write ``n`` points given as an iterable of (k, 3) arrays (float32 on disk)."""
    if n == 0:
        path.write_text(_EMPTY_PCD if path.suffix.lower() == ".pcd" else _EMPTY_PLY)
        return 0
    try:
        with path.open("wb") as fh:
            fh.write(_header(path.suffix.lower(), n))
            for block in blocks:
                np.ascontiguousarray(block, dtype="<f4").tofile(fh)
    except OSError as exc:
        raise InputError(f"could not write map {path}: {exc} (is the folder writable?)") from exc
    return n


def write_points(path: str | Path, points: np.ndarray) -> int:
    """Write ``points`` (N, 3) m as a binary float32 .pcd or .ply; returns N.

    Written with numpy (header + one block), not open3d: open3d needs its own float64
    copy of a map that may hold tens of millions of points."""
    path = _map_path(path)
    pts = np.asarray(points)[:, :3]
    return _write_blocks(path, len(pts), [pts])


def write_map(path: str | Path, points: np.ndarray, voxel: float) -> int:
    """Voxel-downsample ``points`` (N, 3) m to voxel centroids with cell ``voxel`` m (<= 0:
    keep all finite points) and write ``path`` (.pcd or .ply, binary). Returns the number
    of points written."""
    if Path(path).suffix.lower() not in MAP_SUFFIXES:
        raise InputError(f"map file {path}: use a .pcd or .ply suffix")
    pts = finite_points(np.asarray(points, dtype=np.float64))
    if voxel > 0 and len(pts):
        pts = voxel_centroids(pts, voxel)
    return write_points(path, pts)
