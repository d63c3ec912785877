"""sensor_msgs/PointCloud2 and sensor_msgs/LaserScan <-> Scan, vectorised with numpy.

Decoding accepts any field layout and endianness: x/y/z of any PointField datatype,
optional intensity (``intensity``/``reflectivity``/``i``), ring (``ring``/``channel``/
``line``) and per-point time under the names drivers use (``time``, ``t``, ``timestamp``,
``offset_time``), relative or absolute, in s, ms, us or ns (guessed from the span, see
``slam.io.points``). Per-point time is normalised to float64 seconds from the first point
of the sweep (>= 0). Points with a non-finite coordinate are dropped. A malformed message
raises FrameError (an InputError with a skip ``reason``); an unreadable optional field is
dropped instead and noted.

Encoding writes one of the driver layouts in :data:`LAYOUTS` (velodyne, ouster, hesai,
livox, xyzi, xyz64) so tests and the simulator exercise the same paths as real recordings.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.errors import InputError
from slam.io.points import (
    INTENSITY_NAMES,
    RING_NAMES,
    TIME_NAMES,
    Notes,
    TimeField,
    assemble_scan,
    finite_mask,
    guess_time_unit,
    pick,
)
from slam.io.skips import BAD_DATATYPE, CORRUPT_MESSAGE, NO_XYZ, FrameError
from slam.types import Scan

# sensor_msgs/PointField datatype constants -> numpy type codes (little endian by default).
POINTFIELD_DTYPES: dict[int, str] = {
    1: "i1",
    2: "u1",
    3: "i2",
    4: "u2",
    5: "i4",
    6: "u4",
    7: "f4",
    8: "f8",
}
POINTFIELD_NAMES: dict[int, str] = {
    1: "INT8",
    2: "UINT8",
    3: "INT16",
    4: "UINT16",
    5: "INT32",
    6: "UINT32",
    7: "FLOAT32",
    8: "FLOAT64",
}
_DTYPE_TO_POINTFIELD = {v: k for k, v in POINTFIELD_DTYPES.items()}


@dataclass(frozen=True)
class Field:
    """One field of a layout: name, numpy type code ('f4', 'u2', ...), byte offset."""

    name: str
    dtype: str
    offset: int


@dataclass(frozen=True)
class Layout:
    """A driver's point layout. ``source`` maps each field name to what it is filled from."""

    fields: tuple[Field, ...]
    point_step: int
    source: dict[str, str]


def _layout(step: int, *spec: tuple[str, str, int, str]) -> Layout:
    return Layout(tuple(Field(n, d, o) for n, d, o, _ in spec), step, {n: s for n, _, _, s in spec})


# Sources: x/y/z, intensity, ring, "rel_s" (time, seconds), "rel_ns" (time, uint ns),
# "abs_s" (stamp + time, seconds), "range_mm", "zero".
LAYOUTS: dict[str, Layout] = {
    "velodyne": _layout(
        22,
        ("x", "f4", 0, "x"),
        ("y", "f4", 4, "y"),
        ("z", "f4", 8, "z"),
        ("intensity", "f4", 12, "intensity"),
        ("ring", "u2", 16, "ring"),
        ("time", "f4", 18, "rel_s"),
    ),
    "ouster": _layout(
        48,
        ("x", "f4", 0, "x"),
        ("y", "f4", 4, "y"),
        ("z", "f4", 8, "z"),
        ("intensity", "f4", 16, "intensity"),
        ("t", "u4", 20, "rel_ns"),
        ("reflectivity", "u2", 24, "zero"),
        ("ring", "u2", 26, "ring"),
        ("ambient", "u2", 28, "zero"),
        ("range", "u4", 32, "range_mm"),
    ),
    "hesai": _layout(
        26,
        ("x", "f4", 0, "x"),
        ("y", "f4", 4, "y"),
        ("z", "f4", 8, "z"),
        ("intensity", "f4", 12, "intensity"),
        ("timestamp", "f8", 16, "abs_s"),
        ("ring", "u2", 24, "ring"),
    ),
    "livox": _layout(
        22,
        ("x", "f4", 0, "x"),
        ("y", "f4", 4, "y"),
        ("z", "f4", 8, "z"),
        ("intensity", "f4", 12, "intensity"),
        ("tag", "u1", 16, "zero"),
        ("line", "u1", 17, "ring"),
        ("offset_time", "u4", 18, "rel_ns"),
    ),
    # KITTI-converted HDL-64 bags (kitti2bag): no ring, no per-point time
    "xyzi": _layout(
        16,
        ("x", "f4", 0, "x"),
        ("y", "f4", 4, "y"),
        ("z", "f4", 8, "z"),
        ("intensity", "f4", 12, "intensity"),
    ),
    "xyz64": _layout(24, ("x", "f8", 0, "x"), ("y", "f8", 8, "y"), ("z", "f8", 16, "z")),
}


# --------------------------------------------------------------------------- encoding


def stamp_to_sec_nsec(stamp: float) -> tuple[int, int]:
    """Seconds (float) -> (sec, nanosec) of a ROS time, rounded to the nanosecond."""
    sec = int(np.floor(stamp))
    nsec = int(round((float(stamp) - sec) * 1e9))  # split first: 1.7e18 ns is not exact in f64
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return sec, nsec


def make_header(typestore: Any, stamp: float, frame_id: str, seq: int = 0) -> Any:
    """A std_msgs/Header for ROS1 (with seq) or ROS2 typestores."""
    sec, nsec = stamp_to_sec_nsec(stamp)
    time = typestore.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    header_t = typestore.types["std_msgs/msg/Header"]
    names = [f[0] for f in typestore.fielddefs["std_msgs/msg/Header"][1]]
    if "seq" in names:
        return header_t(seq=seq, stamp=time, frame_id=frame_id)
    return header_t(stamp=time, frame_id=frame_id)


def pack_points(scan: Scan, layout: str = "velodyne", *, bigendian: bool = False) -> np.ndarray:
    """Scan -> structured array of ``layout`` (one record per point, padding zeroed).

    Missing intensity/ring/time are written as zeros.
    """
    try:
        spec = LAYOUTS[layout]
    except KeyError:
        raise InputError(
            f"unknown point layout {layout!r}; choose one of {sorted(LAYOUTS)}"
        ) from None
    order = ">" if bigendian else "<"
    dtype = np.dtype(
        {
            "names": [f.name for f in spec.fields],
            "formats": [order + f.dtype for f in spec.fields],
            "offsets": [f.offset for f in spec.fields],
            "itemsize": spec.point_step,
        }
    )
    n = len(scan)
    out = np.zeros(n, dtype=dtype)
    xyz = np.asarray(scan.xyz, dtype=np.float64).reshape(-1, 3)
    zeros = np.zeros(n)
    time = zeros if scan.time is None else np.asarray(scan.time, dtype=np.float64)
    values = {
        "x": xyz[:, 0],
        "y": xyz[:, 1],
        "z": xyz[:, 2],
        "intensity": zeros if scan.intensity is None else scan.intensity,
        "ring": zeros if scan.ring is None else scan.ring,
        "rel_s": time,
        "rel_ns": np.round(time * 1e9),
        "abs_s": float(scan.stamp) + time,
        "range_mm": np.round(np.linalg.norm(xyz, axis=1) * 1000.0),
        "zero": zeros,
    }
    for f in spec.fields:
        out[f.name] = values[spec.source[f.name]]
    return out


def encode_pointcloud2(
    scan: Scan,
    typestore: Any,
    *,
    frame_id: str = "velodyne",
    layout: str = "velodyne",
    seq: int = 0,
    bigendian: bool = False,
) -> Any:
    """Scan -> sensor_msgs/PointCloud2 message object of ``typestore`` (unorganised, height 1)."""
    points = pack_points(scan, layout, bigendian=bigendian)
    spec = LAYOUTS[layout]
    pf = typestore.types["sensor_msgs/msg/PointField"]
    fields = [
        pf(name=f.name, offset=f.offset, datatype=_DTYPE_TO_POINTFIELD[f.dtype], count=1)
        for f in spec.fields
    ]
    n = len(points)
    return typestore.types["sensor_msgs/msg/PointCloud2"](
        header=make_header(typestore, scan.stamp, frame_id, seq),
        height=1,
        width=n,
        fields=fields,
        is_bigendian=bigendian,
        point_step=spec.point_step,
        row_step=spec.point_step * n,
        data=points.view(np.uint8).reshape(-1),
        is_dense=True,
    )


def encode_laserscan(
    typestore: Any,
    stamp: float,
    ranges: np.ndarray,
    *,
    angle_min: float,
    angle_increment: float,
    range_max: float,
    range_min: float = 0.0,
    time_increment: float = 0.0,
    scan_time: float = 0.0,
    intensities: np.ndarray | None = None,
    frame_id: str = "laser",
    seq: int = 0,
) -> Any:
    """One sensor_msgs/LaserScan message (angles in rad, ranges in m, times in s)."""
    ranges = np.asarray(ranges, dtype=np.float32).reshape(-1)
    inten = (
        np.zeros(0, dtype=np.float32)
        if intensities is None
        else np.asarray(intensities, dtype=np.float32).reshape(-1)
    )
    return typestore.types["sensor_msgs/msg/LaserScan"](
        header=make_header(typestore, stamp, frame_id, seq),
        angle_min=float(angle_min),
        angle_max=float(angle_min + angle_increment * max(len(ranges) - 1, 0)),
        angle_increment=float(angle_increment),
        time_increment=float(time_increment),
        scan_time=float(scan_time),
        range_min=float(range_min),
        range_max=float(range_max),
        ranges=ranges,
        intensities=inten,
    )


# --------------------------------------------------------------------------- decoding


def header_stamp(msg: Any) -> float:
    """Header time of a ROS1/ROS2 message in seconds."""
    stamp = msg.header.stamp
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def _field_problem(f: Any, point_step: int) -> str | None:
    """Why field ``f`` cannot be read (unknown datatype, outside the point), else None."""
    code = POINTFIELD_DTYPES.get(int(f.datatype))
    if code is None:
        return f"PointCloud2 field {f.name!r} has unknown datatype {f.datatype} (valid: 1..8)"
    size = np.dtype(code).itemsize
    if int(f.offset) + size > point_step:
        return (
            f"PointCloud2 field {f.name!r} (offset {f.offset}, {size} bytes) does not fit in "
            f"point_step {point_step}: the message is malformed"
        )
    return None


def _point_dtype(msg: Any, wanted: dict[str, Any]) -> np.dtype:
    """Structured dtype of one point: the first element of each wanted field."""
    order = ">" if msg.is_bigendian else "<"
    return np.dtype(
        {
            "names": [f.name for f in wanted.values()],
            "formats": [order + POINTFIELD_DTYPES[int(f.datatype)] for f in wanted.values()],
            "offsets": [int(f.offset) for f in wanted.values()],
            "itemsize": int(msg.point_step),
        }
    )


def _records(msg: Any, dtype: np.dtype) -> np.ndarray:
    """The point records of ``msg`` as a structured array, row padding removed."""
    height, width = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    if n == 0:
        return np.zeros(0, dtype=dtype)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if height > 1 and row_step < width * step:
        raise FrameError(
            CORRUPT_MESSAGE,
            f"PointCloud2 row_step {row_step} < width {width} x point_step {step}",
        )
    need = (height - 1) * row_step + width * step
    if data.size < need:
        raise FrameError(
            CORRUPT_MESSAGE,
            f"PointCloud2 data has {data.size} bytes, header says {need} "
            f"({height}x{width} points, point_step {step}, row_step {row_step}): "
            "truncated message",
        )
    if height > 1 and row_step != width * step:
        data = data[:need]
        rows = np.lib.stride_tricks.as_strided(data, (height, width * step), (row_step, 1))
        data = np.ascontiguousarray(rows).reshape(-1)
    return np.frombuffer(data, dtype=dtype, count=n)


def _fields(msg: Any, notes: Notes | None) -> tuple[dict[str, Any], dict[str, str | None]]:
    """The readable fields to decode and which one fills each role (x, y, z, i, ring, t).

    Raises FrameError when x/y/z are missing or unreadable; an unreadable optional field
    (intensity/ring/time) is left out with a line in ``notes``.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise FrameError(
            NO_XYZ,
            f"PointCloud2 has no field(s) {missing}; fields are {sorted(fields)}: "
            "cannot read point coordinates",
        )
    step = int(msg.point_step)
    wanted: dict[str, Any] = {}
    roles: dict[str, str | None] = {}
    for c in "xyz":
        problem = _field_problem(fields[c], step)
        if problem is not None:
            known = int(fields[c].datatype) in POINTFIELD_DTYPES
            raise FrameError(CORRUPT_MESSAGE if known else BAD_DATATYPE, problem)
        wanted[c], roles[c] = fields[c], c
    for role, names in (("i", INTENSITY_NAMES), ("ring", RING_NAMES), ("t", TIME_NAMES)):
        name = pick(names, fields)
        problem = None if name is None else _field_problem(fields[name], step)
        if problem is not None:
            if notes is not None:
                notes.add(f"{problem}: field {name!r} dropped")
            name = None
        roles[role] = name
        if name is not None:
            wanted[name] = fields[name]
    if notes is not None:
        for f in wanted.values():
            if int(f.count) > 1:
                notes.add(f"PointCloud2 field {f.name!r} has count {f.count}: first element read")
    return wanted, roles


def pointcloud2_time_field(msg: Any) -> TimeField | None:
    """Which per-point time field ``decode_pointcloud2`` would use, with its unit (or None)."""
    fields = {f.name: f for f in msg.fields}
    name = pick(TIME_NAMES, fields)
    if name is None:
        return None
    tf = fields[name]
    problem = _field_problem(tf, int(msg.point_step))
    if problem is not None:
        raise FrameError(BAD_DATATYPE, problem)
    values = _records(msg, _point_dtype(msg, {name: tf}))[name]
    integer = values.dtype.kind in "iu"
    values = values.astype(np.float64)
    return guess_time_unit(name, values[finite_mask(values)], integer=integer)


def decode_pointcloud2(msg: Any, *, index: int = 0, notes: Notes | None = None) -> Scan:
    """sensor_msgs/PointCloud2 (ROS1 or ROS2, any layout) -> Scan with finite points only.

    xyz float64 (N,3) m; intensity float32; ring int16; time float64 s from the earliest
    point (>= 0), unit guessed from the span (see ``slam.io.points.guess_time_unit``).
    stamp: the header stamp, or with per-point time the absolute time of the earliest
    point (header + its relative time, or its absolute time). Fields with count > 1: the
    first element. An unreadable intensity/ring/time field is dropped (noted once in
    ``notes``). Raises FrameError (an InputError) when x/y/z are missing or unreadable or
    the buffer is malformed. A cloud without finite points gives an empty Scan.
    """
    wanted, roles = _fields(msg, notes)
    rec = _records(msg, _point_dtype(msg, wanted))
    ri, rr, rt = roles["i"], roles["ring"], roles["t"]
    return assemble_scan(
        rec["x"],
        rec["y"],
        rec["z"],
        stamp=header_stamp(msg),
        index=index,
        intensity=None if ri is None else rec[ri],
        ring=None if rr is None else (rr, rec[rr]),
        time=None if rt is None else (rt, rec[rt]),
        notes=notes,
    )


def decode_laserscan(msg: Any, *, index: int = 0) -> Scan:
    """sensor_msgs/LaserScan -> Scan in the laser frame (z = 0).

    Beam i has angle ``angle_min + i * angle_increment`` (rad). Ranges that are not finite
    or outside [range_min, range_max] (m) mean "no return" and are dropped. time is
    ``i * time_increment`` (s) when the driver fills time_increment, else None; ring is None.
    intensity is kept when the message has one value per beam.
    """
    ranges = np.asarray(msg.ranges, dtype=np.float64).reshape(-1)
    n = ranges.size
    beams = np.arange(n)
    angles = float(msg.angle_min) + beams * float(msg.angle_increment)
    with np.errstate(invalid="ignore"):
        valid = (
            finite_mask(ranges)
            & (ranges >= float(msg.range_min))
            & (ranges <= float(msg.range_max))
            & (ranges > 0.0)
        )
    r, a = ranges[valid], angles[valid]
    xyz = np.column_stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r)])
    inten = np.asarray(msg.intensities, dtype=np.float32).reshape(-1)
    intensity = inten[valid] if inten.size == n else None
    dt = float(msg.time_increment)
    time = beams[valid] * dt if dt > 0 else None
    return Scan(
        stamp=header_stamp(msg), xyz=xyz, intensity=intensity, ring=None, time=time, index=index
    )
