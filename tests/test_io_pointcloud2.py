"""PointCloud2 / LaserScan encoding and decoding on in-memory messages."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from slam.errors import InputError
from slam.io.pointcloud2 import (
    LAYOUTS,
    decode_laserscan,
    decode_pointcloud2,
    encode_laserscan,
    encode_pointcloud2,
    make_header,
    pointcloud2_time_field,
)
from slam.io.points import Notes
from slam.io.skips import FrameError
from slam.types import Scan

TS2 = get_typestore(Stores.ROS2_HUMBLE)
TS1 = get_typestore(Stores.ROS1_NOETIC)
STAMP = 1_700_000_000.25


def make_scan(n: int = 500, seed: int = 0) -> Scan:
    rng = np.random.default_rng(seed)
    time = np.sort(rng.uniform(0.0, 0.1, n))
    time[0] = 0.0
    return Scan(
        stamp=STAMP,
        xyz=rng.uniform(-50, 50, (n, 3)),
        intensity=rng.uniform(0, 255, n).astype(np.float32),
        ring=rng.integers(0, 16, n).astype(np.int16),
        time=time,
    )


def raw_cloud(fields, records: np.ndarray, *, bigendian=False, height=1, row_pad=0, ts=TS2):
    """A PointCloud2 from a structured array; ``fields`` = [(name, datatype)] in dtype order."""
    pf = ts.types["sensor_msgs/msg/PointField"]
    dt = records.dtype
    width = records.size // height
    rows = records.view(np.uint8).reshape(height, -1)
    if row_pad:
        rows = np.hstack([rows, np.full((height, row_pad), 0xAB, np.uint8)])
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=make_header(ts, STAMP, "lidar"),
        height=height,
        width=width,
        fields=[pf(name=n, offset=dt.fields[n][1], datatype=d, count=1) for n, d in fields],
        is_bigendian=bigendian,
        point_step=dt.itemsize,
        row_step=rows.shape[1],
        data=rows.reshape(-1).copy(),
        is_dense=False,
    )


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.parametrize("ts", [TS1, TS2], ids=["ros1", "ros2"])
def test_round_trip_every_layout(layout, ts):
    scan = make_scan()
    msg = encode_pointcloud2(scan, ts, layout=layout)
    # through real serialisation, as in a bag
    if ts is TS1:
        msg = ts.deserialize_ros1(ts.serialize_ros1(msg, msg.__msgtype__), msg.__msgtype__)
    else:
        msg = ts.deserialize_cdr(ts.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    out = decode_pointcloud2(msg, index=7)
    assert out.index == 7
    assert out.stamp == pytest.approx(STAMP, abs=1e-9)
    assert out.xyz.dtype == np.float64 and out.xyz.shape == (500, 3)
    tol = 0 if layout == "xyz64" else 4e-6  # float32 relative precision at 50 m
    np.testing.assert_allclose(out.xyz, scan.xyz, rtol=0, atol=tol)
    if layout == "xyz64":
        assert out.intensity is None and out.ring is None and out.time is None
        return
    np.testing.assert_allclose(out.intensity, scan.intensity, atol=1e-4)
    assert out.intensity.dtype == np.float32
    if layout == "xyzi":  # KITTI-converted HDL-64: x y z intensity, 16 bytes
        assert out.ring is None and out.time is None and msg.point_step == 16
        return
    np.testing.assert_array_equal(out.ring, scan.ring)
    assert out.ring.dtype == np.int16
    # hesai stores absolute float64 seconds: 1.7e9 s leaves ~2.4e-7 s resolution
    np.testing.assert_allclose(out.time, scan.time, atol=3e-7 if layout == "hesai" else 1e-8)
    assert out.time.min() == 0.0


def test_float64_fields_bigendian_and_row_padding():
    dt = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "time"],
            "formats": [">f8", ">f8", ">f8", ">f4", ">f8"],
            "offsets": [0, 8, 16, 28, 32],
            "itemsize": 48,
        }
    )
    rec = np.zeros(12, dtype=dt)
    rec["x"] = np.arange(12) * 1.123456789012
    rec["y"] = -np.arange(12)
    rec["z"] = 0.5
    rec["intensity"] = np.arange(12) * 10
    rec["time"] = np.linspace(-0.1, 0.0, 12)  # relative to an end-of-sweep stamp
    fields = [("x", 8), ("y", 8), ("z", 8), ("intensity", 7), ("time", 8)]
    msg = raw_cloud(fields, rec, bigendian=True, height=3, row_pad=5)
    out = decode_pointcloud2(msg)
    np.testing.assert_array_equal(out.xyz[:, 0], np.arange(12) * 1.123456789012)  # exact f64
    np.testing.assert_array_equal(out.xyz[:, 1], -np.arange(12))
    np.testing.assert_array_equal(out.intensity, np.arange(12) * 10)
    np.testing.assert_allclose(out.time, np.linspace(0.0, 0.1, 12), atol=1e-15)
    assert out.ring is None
    # the header stamps the sweep end; the scan (and its pose) is at the earliest point
    assert out.stamp == pytest.approx(STAMP - 0.1, abs=1e-9)


def test_ouster_t_nanoseconds_detected():
    dt = np.dtype({"names": ["x", "y", "z", "t"], "formats": ["<f4"] * 3 + ["<u4"],
                   "offsets": [0, 4, 8, 12], "itemsize": 16})  # fmt: skip
    rec = np.zeros(4, dtype=dt)
    rec["t"] = [0, 25_000_000, 50_000_000, 99_000_000]
    msg = raw_cloud([("x", 7), ("y", 7), ("z", 7), ("t", 6)], rec)
    out = decode_pointcloud2(msg)
    np.testing.assert_allclose(out.time, [0.0, 0.025, 0.05, 0.099], atol=1e-12)
    tf = pointcloud2_time_field(msg)
    assert (tf.name, tf.unit, tf.absolute) == ("t", "ns", False)


def test_absolute_timestamp_float64_seconds():
    dt = np.dtype({"names": ["x", "y", "z", "timestamp", "channel"],
                   "formats": ["<f4"] * 3 + ["<f8", "<u1"],
                   "offsets": [0, 4, 8, 12, 20], "itemsize": 21})  # fmt: skip
    rec = np.zeros(3, dtype=dt)
    rec["timestamp"] = STAMP + np.array([0.05, 0.0, 0.1])
    rec["channel"] = [3, 0, 31]
    msg = raw_cloud([("x", 7), ("y", 7), ("z", 7), ("timestamp", 8), ("channel", 2)], rec)
    out = decode_pointcloud2(msg)
    np.testing.assert_allclose(out.time, [0.05, 0.0, 0.1], atol=1e-6)
    assert out.stamp == pytest.approx(STAMP, abs=1e-6)  # absolute: the earliest point's time
    np.testing.assert_array_equal(out.ring, [3, 0, 31])
    tf = pointcloud2_time_field(msg)
    assert (tf.unit, tf.absolute) == ("s", True)


def test_absolute_float_nanoseconds_and_relative_microseconds():
    dt = np.dtype({"names": ["x", "y", "z", "time"], "formats": ["<f4"] * 3 + ["<f8"]})
    rec = np.zeros(3, dtype=dt)
    rec["time"] = 1.7e18 + np.array([0.0, 5e7, 1e8])
    out = decode_pointcloud2(raw_cloud([("x", 7), ("y", 7), ("z", 7), ("time", 8)], rec))
    np.testing.assert_allclose(out.time, [0.0, 0.05, 0.1], atol=1e-6)
    assert out.stamp == pytest.approx(1.7e9, abs=1e-6)
    rec["time"] = [0.0, 50_000.0, 100_000.0]  # microseconds as float
    out = decode_pointcloud2(raw_cloud([("x", 7), ("y", 7), ("z", 7), ("time", 8)], rec))
    np.testing.assert_allclose(out.time, [0.0, 0.05, 0.1], atol=1e-9)


def test_nan_points_dropped_consistently():
    scan = make_scan(100)
    scan.xyz[[3, 50, 99], 1] = np.nan
    scan.xyz[10, 2] = np.inf
    out = decode_pointcloud2(encode_pointcloud2(scan, TS2, layout="velodyne"))
    keep = np.ones(100, bool)
    keep[[3, 10, 50, 99]] = False
    assert len(out) == 96
    assert out.intensity.shape == out.ring.shape == out.time.shape == (96,)
    np.testing.assert_allclose(out.xyz, scan.xyz[keep], atol=4e-6)
    np.testing.assert_array_equal(out.ring, scan.ring[keep])
    np.testing.assert_allclose(out.intensity, scan.intensity[keep], atol=1e-4)


def test_all_nan_cloud_gives_empty_scan():
    scan = Scan(stamp=1.0, xyz=np.full((5, 3), np.nan), time=np.zeros(5))
    out = decode_pointcloud2(encode_pointcloud2(scan, TS2, layout="velodyne"))
    assert len(out) == 0 and out.xyz.shape == (0, 3) and out.time.shape == (0,)


def test_malformed_clouds_raise_input_error():
    dt = np.dtype({"names": ["x", "y"], "formats": ["<f4", "<f4"]})
    with pytest.raises(InputError, match=r"no field\(s\) \['z'\]"):
        decode_pointcloud2(raw_cloud([("x", 7), ("y", 7)], np.zeros(3, dt)))
    msg = encode_pointcloud2(make_scan(10), TS2)
    msg.data = msg.data[:-30]
    with pytest.raises(InputError, match="truncated"):
        decode_pointcloud2(msg)


def test_laserscan_decode():
    ranges = np.array([1.0, 2.0, np.inf, 4.0, 0.05, 50.0])
    msg = encode_laserscan(
        TS2, 3.5, ranges, angle_min=-np.pi / 2, angle_increment=np.pi / 4, range_max=30.0,
        range_min=0.1, time_increment=0.001, intensities=np.arange(6.0),
    )  # fmt: skip
    out = decode_laserscan(msg)
    assert out.stamp == 3.5 and out.ring is None
    angles = -np.pi / 2 + np.array([0, 1, 3]) * np.pi / 4
    r = np.array([1.0, 2.0, 4.0])
    np.testing.assert_allclose(out.xyz[:, 0], r * np.cos(angles), atol=1e-6)
    np.testing.assert_allclose(out.xyz[:, 1], r * np.sin(angles), atol=1e-6)
    np.testing.assert_array_equal(out.xyz[:, 2], 0.0)
    np.testing.assert_allclose(out.time, [0.0, 0.001, 0.003], atol=1e-9)
    np.testing.assert_array_equal(out.intensity, [0.0, 1.0, 3.0])


# ------------------------------------------------------------------ units, layouts, bad fields


def xyzt_cloud(tcode: str, tdatatype: int, times, name: str = "time"):
    """A 4-point cloud with x = 0..3 and a per-point time field of numpy type ``tcode``."""
    dt = np.dtype({"names": ["x", "y", "z", name], "formats": ["<f4"] * 3 + ["<" + tcode]})
    rec = np.zeros(len(times), dtype=dt)
    rec["x"] = np.arange(len(times))
    rec[name] = times
    return raw_cloud([("x", 7), ("y", 7), ("z", 7), (name, tdatatype)], rec)


SWEEP = np.array([0.0, 0.025, 0.05, 0.099])  # s


@pytest.mark.parametrize(
    ("tcode", "datatype", "scale", "unit"),
    [
        ("u4", 6, 1e6, "us"),  # integer microseconds: read as ns before (1000x too short)
        ("i4", 5, 1e6, "us"),
        ("u4", 6, 1e9, "ns"),
        ("u4", 6, 1e3, "ms"),
        ("f4", 7, 1e3, "ms"),
        ("f8", 8, 1e6, "us"),
        ("f4", 7, 1.0, "s"),
        ("f8", 8, 1e9, "ns"),
    ],
)
def test_relative_time_units_decode_to_seconds(tcode, datatype, scale, unit):
    msg = xyzt_cloud(
        tcode, datatype, np.round(SWEEP * scale) if tcode[0] in "iu" else SWEEP * scale
    )
    out = decode_pointcloud2(msg)
    np.testing.assert_allclose(out.time, SWEEP, atol=1e-7)
    assert out.stamp == pytest.approx(STAMP, abs=1e-9)  # earliest point at the header stamp
    tf = pointcloud2_time_field(msg)
    assert (tf.unit, tf.absolute) == (unit, False)


@pytest.mark.parametrize(("scale", "unit"), [(1e9, "ns"), (1e6, "us"), (1e3, "ms"), (1.0, "s")])
def test_absolute_float64_time_units(scale, unit):
    # PointField has no 64-bit integer type: absolute times come as float64
    out_stamp = 1_600_000_000.5
    msg = xyzt_cloud("f8", 8, (out_stamp + SWEEP) * scale, name="timestamp")
    out = decode_pointcloud2(msg)
    atol = 1e-6 if scale < 1e9 else 3e-7  # float64 at 1.6e18 ns resolves 256 ns
    np.testing.assert_allclose(out.time, SWEEP, atol=atol)
    assert out.stamp == pytest.approx(out_stamp, abs=1e-6)  # the earliest point's time
    tf = pointcloud2_time_field(msg)
    assert (tf.unit, tf.absolute) == (unit, True)


def xyz_plus(name: str, code: str, datatype: int, values, count: int = 1):
    """A cloud with x = 0..n-1, y = z = 0 and one more field (``count`` elements)."""
    n = len(values)
    fmt = "<" + code if count == 1 else (np.dtype("<" + code), (count,))
    dt = np.dtype({"names": ["x", "y", "z", name], "formats": ["<f4"] * 3 + [fmt]})
    rec = np.zeros(n, dtype=dt)
    rec["x"] = np.arange(n)
    rec[name] = np.asarray(values) if count == 1 else np.asarray(values)[:, None] + np.arange(count)
    msg = raw_cloud([("x", 7), ("y", 7), ("z", 7), (name, datatype)], rec)
    msg.fields[-1].count = count
    return msg


def test_uint16_ring_above_int16_is_dropped_with_a_note_small_rings_kept():
    notes = Notes()
    out = decode_pointcloud2(xyz_plus("ring", "u2", 4, [0, 40000, 65535]), notes=notes)
    assert out.ring is None and len(out) == 3  # never wrapped into negative beams
    assert len(notes.lines) == 1 and "ring dropped" in notes.lines[0]
    out = decode_pointcloud2(xyz_plus("ring", "u4", 6, [0, 127, 32767]))
    np.testing.assert_array_equal(out.ring, [0, 127, 32767])
    assert out.ring.dtype == np.int16


def test_count_above_one_reads_the_first_element():
    notes = Notes()
    out = decode_pointcloud2(xyz_plus("intensity", "f4", 7, [5.0, 6.0, 7.0], count=3), notes=notes)
    np.testing.assert_array_equal(out.intensity, [5.0, 6.0, 7.0])  # not 6, 7, 8 (element 1)
    assert "count 3: first element read" in notes.lines[0]


def test_unknown_datatype_on_optional_field_drops_it_and_keeps_the_scan():
    notes = Notes()
    msg = xyz_plus("intensity", "f4", 7, [1.0, 2.0])
    msg.fields[-1].datatype = 42
    for _ in range(3):
        out = decode_pointcloud2(msg, notes=notes)
    assert out.intensity is None and out.xyz[:, 0].tolist() == [0.0, 1.0]
    assert len(notes.lines) == 1 and "unknown datatype 42" in notes.lines[0]  # noted once


def test_unknown_datatype_on_x_is_a_frame_error():
    msg = xyz_plus("intensity", "f4", 7, [1.0, 2.0])
    msg.fields[0].datatype = 0
    with pytest.raises(FrameError, match="'x' has unknown datatype 0") as err:
        decode_pointcloud2(msg)
    assert err.value.reason == "bad field datatype" and isinstance(err.value, InputError)


def test_nan_per_point_times_drop_the_time_field():
    notes = Notes()
    out = decode_pointcloud2(xyz_plus("time", "f4", 7, [0.0, np.nan, 0.05]), notes=notes)
    assert out.time is None and len(out) == 3 and out.stamp == STAMP
    assert "non-finite per-point times" in notes.lines[0]
    # times of points dropped for their NaN coordinates do not matter
    msg = xyz_plus("time", "f4", 7, [0.0, np.nan, 0.05])
    data = np.frombuffer(bytes(msg.data), np.float32).copy()
    data[4] = np.nan  # x of point 1 (16-byte records)
    msg.data = data.view(np.uint8)
    np.testing.assert_allclose(decode_pointcloud2(msg).time, [0.0, 0.05], atol=1e-9)
