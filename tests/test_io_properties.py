"""Property-based tests (hypothesis) of the readers: PointCloud2 decoder, PCD folders, KITTI.

For any valid input (field layout, offsets, padding, endianness, NaN/inf coordinates,
per-point time in any unit) the decoded points equal the encoded ones within +-1e4 m (a
cloud whose finite points are mostly beyond is a damaged message); for any damaged
input (truncated, garbage, wrong sizes) only the project's typed errors escape the decoder
and the readers yield a SkippedMessage instead of raising. 500 examples per property.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from rosbags.typesys import Stores, get_typestore
from test_io_folders import pcd_bytes

from slam.errors import InputError
from slam.io.folders import FolderSource
from slam.io.kitti import KittiSource
from slam.io.pointcloud2 import POINTFIELD_DTYPES, decode_pointcloud2, make_header
from slam.io.points import INTENSITY_NAMES, RING_NAMES, TIME_NAMES, Notes
from slam.io.skips import FrameError
from slam.types import Scan, SkippedMessage

TS = get_typestore(Stores.ROS2_HUMBLE)
PF = TS.types["sensor_msgs/msg/PointField"]
PC2 = TS.types["sensor_msgs/msg/PointCloud2"]
STAMP = 1_700_000_000.0
CODE_TO_DATATYPE = {v: k for k, v in POINTFIELD_DTYPES.items()}
NUMERIC = list(CODE_TO_DATATYPE)
SETTINGS = settings(
    max_examples=500,
    deadline=None,
    derandomize=os.environ.get("CI") == "true",  # CI: the same 500 examples every run
    database=None if os.environ.get("CI") == "true" else settings.default.database,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def values_of(code: str, n: int, *, nan: bool = True) -> st.SearchStrategy:
    """n values of numpy type ``code``: any floats (NaN/inf too) or any integers in range."""
    dt = np.dtype(code)
    if dt.kind == "f":
        elem = st.floats(width=dt.itemsize * 8, allow_nan=nan, allow_infinity=nan)
    else:
        info = np.iinfo(dt)
        elem = st.integers(int(info.min), int(info.max))
    return hnp.arrays(dt, n, elements=elem)


# (numpy code, scale to the unit) pairs that can hold a 0.05-0.2 s sweep at >= 1 ms resolution
TIME_CODES = [
    ("f4", 1.0), ("f4", 1e3), ("f4", 1e6), ("f4", 1e9), ("f8", 1.0), ("f8", 1e3), ("f8", 1e6),
    ("f8", 1e9), ("u1", 1e3), ("u2", 1e3), ("i2", 1e3), ("u4", 1e6), ("i4", 1e6), ("u4", 1e9),
    ("i4", 1e3),
]  # fmt: skip


def _fill(draw, rec: np.ndarray, specs, n: int, scale: float) -> dict:
    """Fill the records' fields from their roles; the expected column of each role."""
    cols = {}
    for name, code, count, role in specs:
        if role == "t":
            t = draw(sweeps(n))
            cols["t"] = t
            raw = t * scale
            rec[name] = np.round(raw) if np.dtype(code).kind in "iu" else raw
        elif count == 1:
            rec[name] = draw(values_of(code, n))
        if role and role != "t":
            cols[role] = rec[name].copy()
    return cols


@st.composite
def sweeps(draw, n: int) -> np.ndarray:
    """Per-point times (s) of one sweep of n >= 2 points: 0 and the period are both there."""
    period = draw(st.floats(0.05, 0.2))
    inner = draw(hnp.arrays(np.float64, max(n - 2, 0), elements=st.floats(0.0, 1.0)))
    t = np.concatenate([[0.0, period], inner * period])
    return t[draw(st.permutations(range(n)))] if n > 1 else t[:n]


@st.composite
def clouds(draw):
    """A valid PointCloud2 message and the columns it encodes (roles -> arrays, time in s)."""
    big = draw(st.booleans())
    height = draw(st.integers(1, 3))
    width = draw(st.integers(0, 8))
    n = height * width
    specs = [(c, draw(st.sampled_from(["f4", "f8"])), 1, c) for c in "xyz"]
    for role, names in (("i", INTENSITY_NAMES), ("ring", RING_NAMES)):
        if draw(st.booleans()):
            specs.append((draw(st.sampled_from(names)), draw(st.sampled_from(NUMERIC)), 1, role))
    time_code, scale = None, 1.0
    if n >= 2 and draw(st.booleans()):
        time_code, scale = draw(st.sampled_from(TIME_CODES))
        specs.append((draw(st.sampled_from(TIME_NAMES)), time_code, 1, "t"))
    for k in range(draw(st.integers(0, 2))):  # fields no reader uses, some with count > 1
        specs.append((f"pad{k}", draw(st.sampled_from(NUMERIC)), draw(st.integers(1, 3)), ""))
    order = draw(st.permutations(range(len(specs))))
    offsets, off = {}, 0
    for i in order:
        off += draw(st.integers(0, 3))
        offsets[i] = off
        off += np.dtype(specs[i][1]).itemsize * specs[i][2]
    step = off + draw(st.integers(0, 4))
    e = ">" if big else "<"
    dtype = np.dtype(
        {
            "names": [s[0] for s in specs],
            "formats": [(e + c) if k == 1 else (np.dtype(e + c), (k,)) for _, c, k, _ in specs],
            "offsets": [offsets[i] for i in range(len(specs))],
            "itemsize": step,
        }
    )
    rec = np.zeros(n, dtype=dtype)
    cols = _fill(draw, rec, specs, n, scale)
    row_pad = draw(st.integers(0, 5))
    rows = rec.view(np.uint8).reshape(height, width * step)
    data = np.hstack([rows, np.full((height, row_pad), 0xAB, np.uint8)]).reshape(-1)
    fields = [
        PF(name=name, offset=offsets[i], datatype=CODE_TO_DATATYPE[code], count=count)
        for i, (name, code, count, _) in enumerate(specs)
    ]
    msg = PC2(
        header=make_header(TS, STAMP, "lidar"),
        height=height,
        width=width,
        fields=[fields[i] for i in draw(st.permutations(range(len(fields))))],
        is_bigendian=big,
        point_step=step,
        row_step=width * step + row_pad,
        data=data.copy(),
        is_dense=False,
    )
    return msg, cols, time_code


def expected_points(cols: dict) -> tuple[np.ndarray, np.ndarray, bool]:
    """(xyz (N, 3) of ``cols``, the rows a reader keeps, damaged?): kept rows are finite and
    within +-1e4 m; a cloud is damaged when more than half its finite rows are not kept."""
    xyz = np.column_stack([cols[c].astype(np.float64) for c in "xyz"]).reshape(-1, 3)
    finite = np.isfinite(xyz).all(axis=1)
    keep = finite & (np.abs(xyz) <= 1e4).all(axis=1)
    return xyz, keep, 2 * (finite.sum() - keep.sum()) > finite.sum()


def check_scan(out: Scan, cols: dict, *, time_code: str | None, stamp: float) -> None:
    """``out`` holds exactly the valid points of ``cols`` with their attributes."""
    xyz, keep, _ = expected_points(cols)
    np.testing.assert_array_equal(out.xyz, xyz[keep])
    assert out.xyz.dtype == np.float64 and (np.abs(out.xyz) <= 1e4).all()
    if "i" in cols:
        with np.errstate(over="ignore"):  # float64 beyond float32: inf on both sides
            np.testing.assert_array_equal(out.intensity, cols["i"][keep].astype(np.float32))
    else:
        assert out.intensity is None
    if "ring" in cols:
        r = cols["ring"][keep]
        fits = (
            r.size == 0
            or (np.isfinite(r).all() and (r == np.round(r)).all())
            and r.min() >= -32768
            and r.max() <= 32767
        )
        if fits:
            np.testing.assert_array_equal(out.ring, r.astype(np.int16))
        else:
            assert out.ring is None
    else:
        assert out.ring is None
    if time_code is None or "t" not in cols:
        assert out.time is None
        assert out.stamp == stamp
        return
    t = cols["t"][keep]
    # resolution of the stored times: integers in ms/us/ns; f4 keeps 24 bits of the value
    tol = 1e-3 if time_code in ("u1", "u2", "i2", "i4") else 1e-6
    tol = max(tol, 2e-7 if time_code == "f4" else 0.0)
    assert out.time.shape == t.shape and (out.time >= 0).all()
    if t.size:
        np.testing.assert_allclose(out.time, t - t.min(), atol=2 * tol)
        assert abs(out.stamp - (stamp + t.min())) < 2 * tol + 1e-6


@SETTINGS
@given(clouds())
def test_pointcloud2_decodes_what_was_encoded(case):
    msg, cols, time_code = case
    if expected_points(cols)[2]:
        with pytest.raises(FrameError, match="beyond 10000 m") as err:
            decode_pointcloud2(msg, index=3, notes=Notes())
        assert err.value.reason == "absurd coordinates"
        return
    out = decode_pointcloud2(msg, index=3, notes=Notes())
    assert out.index == 3
    check_scan(out, cols, time_code=time_code, stamp=STAMP)


@st.composite
def damaged_clouds(draw):
    """Valid clouds with one damage: data cut short, or any header value replaced."""
    msg, _, _ = draw(clouds())
    what = draw(st.sampled_from(["cut", "step", "row_step", "size", "field", "bytes"]))
    if what == "cut":
        msg.data = msg.data[: draw(st.integers(0, max(len(msg.data) - 1, 0)))]
    elif what == "step":
        msg.point_step = draw(st.integers(0, 64))
    elif what == "row_step":
        msg.row_step = draw(st.integers(0, 600))
    elif what == "size":
        msg.height, msg.width = draw(st.integers(0, 2**20)), draw(st.integers(0, 2**20))
    elif what == "field" and msg.fields:
        f = msg.fields[draw(st.integers(0, len(msg.fields) - 1))]
        f.datatype = draw(st.integers(0, 255))
        f.offset = draw(st.integers(0, 80))
        f.count = draw(st.integers(0, 5))
        f.name = draw(st.sampled_from([f.name, "x", "y", "z", "ring", "t", ""]))
    else:
        junk = draw(st.binary(max_size=len(msg.data)))
        msg.data = np.frombuffer(junk + bytes(msg.data)[len(junk) :], np.uint8).copy()
    return msg


@SETTINGS
@given(damaged_clouds())
def test_pointcloud2_damage_raises_only_typed_errors(msg):
    try:
        out = decode_pointcloud2(msg, notes=Notes())
    except FrameError as exc:
        assert isinstance(exc, InputError) and exc.reason and str(exc)
        return
    n = len(out)
    assert out.xyz.shape == (n, 3) and (np.abs(out.xyz) <= 1e4).all()
    for col in (out.intensity, out.ring, out.time):
        assert col is None or col.shape == (n,)
    assert out.time is None or (n == 0 or out.time.min() == 0.0)
    assert np.isfinite(out.stamp)


# ------------------------------------------------------------------ PCD folders


@st.composite
def pcd_files(draw):
    """(file bytes, columns) of a valid PCD: x/y/z F4/F8, optional intensity/ring/time of
    any type, unused fields with COUNT up to 3, ascii or binary, bytes after the data."""
    ascii_ = draw(st.booleans())
    n = draw(st.integers(0, 12))
    ints = ["u1", "i1", "u2", "i2", "u4", "i4"] + ([] if ascii_ else ["u8", "i8"])
    specs = [(c, draw(st.sampled_from(["f4", "f8"])), 1, c) for c in "xyz"]
    for role, names in (("i", INTENSITY_NAMES), ("ring", RING_NAMES)):
        if draw(st.booleans()):
            specs.append(
                (draw(st.sampled_from(names)), draw(st.sampled_from(["f4", *ints])), 1, role)
            )
    time_code, scale = None, 1.0
    if n >= 2 and draw(st.booleans()):
        time_code, scale = draw(st.sampled_from(TIME_CODES))
        specs.append((draw(st.sampled_from(TIME_NAMES)), time_code, 1, "t"))
    for k in range(draw(st.integers(0, 2))):
        specs.append((f"pad{k}", draw(st.sampled_from(["f4", *ints])), draw(st.integers(1, 3)), ""))
    specs = [specs[i] for i in draw(st.permutations(range(len(specs))))]
    dtype = np.dtype([(nm, "<" + c) if k == 1 else (nm, "<" + c, (k,)) for nm, c, k, _ in specs])
    rec = np.zeros(n, dtype)
    cols = _fill(draw, rec, specs, n, scale)
    tail = (
        draw(st.binary(max_size=40)) if not ascii_ else draw(st.sampled_from([b"", b"\n", b"\n\n"]))
    )
    return pcd_bytes(rec, data="ascii" if ascii_ else "binary", trailing=tail), cols, time_code, n


@SETTINGS
@given(pcd_files())
def test_pcd_folder_reads_what_was_written(case):
    buf, cols, time_code, n = case
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "12.5.pcd").write_bytes(buf)
        (item,) = list(FolderSource(tmp))
    _, keep, damaged = expected_points(cols)
    if damaged:
        assert isinstance(item, SkippedMessage) and item.reason == "absurd coordinates"
        return
    if not keep.any():
        assert isinstance(item, SkippedMessage)
        assert item.reason == ("empty file" if n == 0 else "no finite points")
        return
    check_scan(item, cols, time_code=time_code, stamp=12.5)


@st.composite
def damaged_pcds(draw):
    buf = draw(pcd_files())[0]
    what = draw(st.sampled_from(["cut", "overwrite", "insert", "header"]))
    at = draw(st.integers(0, len(buf)))
    if what == "cut":
        return buf[:at]
    junk = draw(st.binary(min_size=1, max_size=30))
    if what == "overwrite":
        return buf[:at] + junk + buf[at + len(junk) :]
    if what == "insert":
        return buf[:at] + junk + buf[at:]
    key = draw(st.sampled_from([b"FIELDS", b"SIZE", b"TYPE", b"COUNT", b"POINTS", b"DATA"]))
    value = draw(st.sampled_from([b"", b"0", b"-1", b"99999999999", b"x x", b"F", b"ascii"]))
    lines = buf.split(b"\n")
    return b"\n".join(key + b" " + value if ln.startswith(key) else ln for ln in lines)


@SETTINGS
@given(damaged_pcds())
def test_pcd_folder_damage_costs_one_file(buf):
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "0.pcd").write_bytes(buf)
        (item,) = list(FolderSource(tmp))
    if isinstance(item, SkippedMessage):
        assert item.index == 0 and item.reason and "0.pcd" in item.detail
        return
    assert len(item) > 0 and (np.abs(item.xyz) <= 1e4).all()
    for col in (item.intensity, item.ring, item.time):
        assert col is None or col.shape == (len(item),)


# ------------------------------------------------------------------ KITTI .bin folders


@SETTINGS
@given(
    hnp.arrays(np.float32, st.tuples(st.integers(0, 20), st.just(4)), elements=st.floats(width=32)),
    st.binary(max_size=15),
)
def test_kitti_reads_valid_points_or_skips(points, tail):
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "velodyne").mkdir()
        (Path(tmp) / "velodyne" / "000000.bin").write_bytes(points.astype("<f4").tobytes() + tail)
        (item,) = list(KittiSource(tmp))
    _, keep, damaged = expected_points({c: points[:, k] for k, c in enumerate("xyz")})
    if tail:
        assert isinstance(item, SkippedMessage) and item.reason == "corrupt file"
    elif len(points) == 0:
        assert isinstance(item, SkippedMessage) and item.reason == "empty file"
    elif damaged:
        assert isinstance(item, SkippedMessage) and item.reason == "absurd coordinates"
    elif not keep.any():
        assert isinstance(item, SkippedMessage) and item.reason == "no finite points"
    else:
        np.testing.assert_array_equal(item.xyz, points[keep, :3].astype(np.float64))
        np.testing.assert_array_equal(item.intensity, points[keep, 3])
        assert item.stamp == 0.0 and item.ring is None and item.time is None
