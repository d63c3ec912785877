"""PCD files (Point Cloud Library format v0.5-0.7) read with numpy, DATA ascii or binary.

Exactly POINTS records are read after the header: bytes after the data (as in the
KITTI-raw PCDs of ``../shared/data/kitti_raw_drive``, ~3.9 kB each) are ignored. Fields with
COUNT > 1 keep their first element. ``binary_compressed`` (LZF) is left to open3d by the
caller. Every problem raises FrameError (an InputError) with a skip reason: a PCD reader
that prints a warning and returns nothing (open3d's behaviour) cannot say which file or why.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.io.points import Notes
from slam.io.skips import BAD_DATATYPE, CORRUPT_FILE, EMPTY_FILE, FrameError

_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")
# (TYPE, SIZE) -> numpy code; PCD data is little endian
_TYPES = {(t, s): f"{t.lower()}{s}" for t, s in [("F", 4), ("F", 8)]} | {
    (t, s): f"{t.lower()}{s}" for t in "UI" for s in (1, 2, 4, 8)
}
_MAX_HEADER = 65536


@dataclass(frozen=True)
class PcdHeader:
    """The parsed header: field names, TYPE letters, numpy codes (None: unknown type, read
    as bytes), sizes (bytes), counts, point count, DATA kind and the data's byte offset."""

    names: tuple[str, ...]
    types: tuple[str, ...]
    codes: tuple[str | None, ...]
    sizes: tuple[int, ...]
    counts: tuple[int, ...]
    points: int
    data: str
    data_offset: int


def _ints(values: list[str], key: str, where: str) -> list[int]:
    try:
        out = [int(v) for v in values]
    except ValueError:
        raise FrameError(CORRUPT_FILE, f"{where}: PCD {key} {values} is not integers") from None
    if any(v < 0 for v in out):
        raise FrameError(CORRUPT_FILE, f"{where}: PCD {key} {values} has negative values")
    return out


def parse_header(buf: bytes, where: str = "PCD") -> PcdHeader:
    """The header of a PCD file held in ``buf``; FrameError when it is not a valid one."""
    if not buf:
        raise FrameError(EMPTY_FILE, f"{where}: empty file (0 bytes)")
    entries: dict[str, list[str]] = {}
    pos = 0
    data_kind = None
    while pos < min(len(buf), _MAX_HEADER):
        end = buf.find(b"\n", pos)
        end = len(buf) if end < 0 else end
        line = buf[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        if key == "DATA":
            data_kind = values[0].lower() if values else ""
            break
        if key not in _KEYS:
            raise FrameError(CORRUPT_FILE, f"{where}: not a PCD file (header line {line[:40]!r})")
        entries[key] = values
    if data_kind is None:
        raise FrameError(CORRUPT_FILE, f"{where}: PCD header without a DATA line")
    names = tuple(entries.get("FIELDS", []))
    if not names:
        raise FrameError(CORRUPT_FILE, f"{where}: PCD header without FIELDS")
    sizes = _ints(entries.get("SIZE", []), "SIZE", where)
    types = [t.upper() for t in entries.get("TYPE", [])]
    counts = _ints(entries.get("COUNT", ["1"] * len(names)), "COUNT", where)
    if not (len(sizes) == len(types) == len(counts) == len(names)):
        raise FrameError(
            CORRUPT_FILE,
            f"{where}: PCD FIELDS/SIZE/TYPE/COUNT lengths differ "
            f"({len(names)}/{len(sizes)}/{len(types)}/{len(counts)})",
        )
    if any(s == 0 for s in sizes) or any(c == 0 for c in counts):
        raise FrameError(CORRUPT_FILE, f"{where}: PCD SIZE/COUNT of 0")
    width = _ints(entries.get("WIDTH", ["0"]), "WIDTH", where)[:1] or [0]
    height = _ints(entries.get("HEIGHT", ["1"]), "HEIGHT", where)[:1] or [1]
    points = _ints(entries.get("POINTS", [str(width[0] * height[0])]), "POINTS", where)[:1]
    if not points:
        raise FrameError(CORRUPT_FILE, f"{where}: PCD POINTS without a value")
    codes = tuple(_TYPES.get((t, s)) for t, s in zip(types, sizes, strict=True))
    return PcdHeader(
        names,
        tuple(types),
        codes,
        tuple(sizes),
        tuple(counts),
        points[0],
        data_kind,
        min(pos, len(buf)),
    )


def _check_fields(h: PcdHeader, where: str, notes: Notes | None) -> None:
    """FrameError for repeated names or an unknown TYPE/SIZE on x/y/z; other unknown fields
    are noted (they are dropped)."""
    if len(set(h.names)) != len(h.names):
        raise FrameError(CORRUPT_FILE, f"{where}: PCD FIELDS repeat a name: {list(h.names)}")
    for name, t, code, size in zip(h.names, h.types, h.codes, h.sizes, strict=True):
        if code is None:
            problem = f"PCD field {name!r} has unknown TYPE {t} / SIZE {size}"
            if name in ("x", "y", "z"):
                raise FrameError(BAD_DATATYPE, f"{where}: {problem}")
            if notes is not None:
                notes.add(f"{problem}: field dropped")


def _binary_columns(h: PcdHeader, body: memoryview, where: str) -> dict[str, np.ndarray]:
    """One column per readable field of ``data binary``: a strided record view of the body,
    no copy; FrameError when the body is shorter than POINTS records."""
    step = sum(s * c for s, c in zip(h.sizes, h.counts, strict=True))
    need = h.points * step
    if len(body) < need:
        raise FrameError(
            CORRUPT_FILE,
            f"{where}: PCD data has {len(body)} bytes, POINTS {h.points} x {step} bytes "
            f"need {need}: truncated file",
        )
    names, formats, offsets, off = [], [], [], 0
    for name, code, size, count in zip(h.names, h.codes, h.sizes, h.counts, strict=True):
        if code is not None:
            names.append(name)
            formats.append("<" + code)
            offsets.append(off)
        off += size * count
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rec = np.frombuffer(body, dtype=dtype, count=h.points)
    return {n: rec[n] for n in names}


def _ascii_columns(h: PcdHeader, body: memoryview, where: str) -> dict[str, np.ndarray]:
    """One column per readable field of ``data ascii`` (float64, or the field's integer type);
    FrameError for non-text, too few or unparsable values."""
    ncols = sum(h.counts)
    try:
        text = bytes(body).decode("ascii")
    except UnicodeDecodeError:
        raise FrameError(CORRUPT_FILE, f"{where}: PCD ascii data is not text") from None
    tokens = text.split(maxsplit=h.points * ncols)[: h.points * ncols]
    if len(tokens) < h.points * ncols:
        raise FrameError(
            CORRUPT_FILE,
            f"{where}: PCD ascii data has {len(tokens)} values, POINTS {h.points} x "
            f"{ncols} need {h.points * ncols}: truncated file",
        )
    try:
        table = np.array(tokens, dtype=np.float64).reshape(h.points, ncols)
    except ValueError as exc:
        raise FrameError(CORRUPT_FILE, f"{where}: PCD ascii data: {exc}") from None
    cols, first = {}, 0
    for name, code, count in zip(h.names, h.codes, h.counts, strict=True):
        if code is not None:
            col = table[:, first]
            cols[name] = col if code[0] == "f" else _as_int(col, code)
        first += count
    return cols


def read_pcd_columns(
    buf: bytes, where: str = "PCD", notes: Notes | None = None
) -> tuple[PcdHeader, dict[str, np.ndarray]]:
    """Header and one (POINTS,) column per readable field (first element of COUNT > 1;
    other fields of unknown TYPE/SIZE are left out, noted in ``notes``; on x/y/z they are
    a FrameError). ``data`` "binary_compressed" raises NotImplementedError (read it with
    open3d); other problems raise FrameError."""
    h = parse_header(buf, where)
    _check_fields(h, where, notes)
    if h.data == "binary_compressed":
        raise NotImplementedError("binary_compressed")
    body = memoryview(buf)[h.data_offset :]
    if h.data == "binary":
        return h, _binary_columns(h, body, where)
    if h.data == "ascii":
        return h, _ascii_columns(h, body, where)
    raise FrameError(CORRUPT_FILE, f"{where}: unknown PCD DATA kind {h.data!r}")


def _as_int(col: np.ndarray, code: str) -> np.ndarray:
    """An ascii integer column in its declared type when it fits, else as float64."""
    info = np.iinfo(code)
    if col.size == 0 or (
        np.isfinite(col).all() and col.min() >= info.min and col.max() <= info.max
    ):
        return col.astype(code)
    return col
