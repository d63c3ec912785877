"""Bag readers on real bags written by our writer and by rosbags directly."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from slam.errors import InputError, TopicError
from slam.io.bag_writer import write_laserscan_bag, write_pointcloud_bag
from slam.io.bags import BagSource
from slam.io.info import describe
from slam.io.pointcloud2 import encode_pointcloud2, make_header
from slam.io.source import ScanSource, open_source
from slam.types import Scan, SkippedMessage

TS1 = get_typestore(Stores.ROS1_NOETIC)
TS2 = get_typestore(Stores.ROS2_HUMBLE)
PC2 = "sensor_msgs/msg/PointCloud2"


def scans(n_scans: int = 4, n: int = 300, seed: int = 1) -> list[Scan]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_scans):
        time = np.sort(rng.uniform(0, 0.1, n))
        time[0] = 0.0
        out.append(
            Scan(
                stamp=1_600_000_000.0 + 0.1 * i,
                xyz=rng.uniform(-30, 30, (n, 3)),
                intensity=rng.uniform(0, 100, n).astype(np.float32),
                ring=rng.integers(0, 16, n).astype(np.int16),
                time=time,
                index=i,
            )
        )
    return out


def bag_name(tmp_path, fmt, name="bag"):
    return tmp_path / (name + ".bag" if fmt == "ros1" else name)


def open_raw(path, fmt):
    """A bare rosbags writer + its typestore and serializer."""
    if fmt == "ros1":
        return Writer1(path), TS1, TS1.serialize_ros1
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    return Writer2(path, version=8, storage_plugin=plugin), TS2, TS2.serialize_cdr


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
@pytest.mark.parametrize("layout", ["velodyne", "ouster"])
def test_round_trip_our_writer(tmp_path, fmt, layout):
    ref = scans()
    path = write_pointcloud_bag(bag_name(tmp_path, fmt), ref, fmt=fmt, layout=layout)
    src = open_source(path)
    assert isinstance(src, BagSource) and isinstance(src, ScanSource)
    assert len(src) == 4 and src.topic == "/velodyne_points"
    assert "4 msgs" in src.description
    got = list(src)
    assert [s.index for s in got] == [0, 1, 2, 3]
    for a, b in zip(got, ref, strict=True):
        assert a.stamp == pytest.approx(b.stamp, abs=1e-9)
        np.testing.assert_allclose(a.xyz, b.xyz, atol=4e-6)  # float32 at 30 m
        np.testing.assert_allclose(a.intensity, b.intensity, atol=1e-5)
        np.testing.assert_array_equal(a.ring, b.ring)
        np.testing.assert_allclose(a.time, b.time, atol=1e-8)
    assert len(list(src)) == 4  # iterable twice


@pytest.mark.parametrize("fmt", ["ros1", "ros2", "mcap"])
def test_bag_written_by_rosbags_directly(tmp_path, fmt):
    """float64 xyz, uint16 reflectivity, uint8 'line', absolute float64 'timestamp',
    plus an unrelated String topic that must be ignored."""
    path = bag_name(tmp_path, fmt)
    writer, ts, ser = open_raw(path, fmt)
    dt = np.dtype({"names": ["x", "y", "z", "reflectivity", "line", "timestamp"],
                   "formats": ["<f8", "<f8", "<f8", "<u2", "u1", "<f8"],
                   "offsets": [0, 8, 16, 24, 26, 28], "itemsize": 40})  # fmt: skip
    pf = ts.types["sensor_msgs/msg/PointField"]
    fields = [pf(name=n, offset=dt.fields[n][1], datatype=d, count=1)
              for n, d in zip(dt.names, [8, 8, 8, 4, 2, 8], strict=True)]  # fmt: skip
    with writer:
        c_pc = writer.add_connection("/points", PC2, typestore=ts)
        c_str = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        for i in range(3):
            stamp = 100.0 + i
            rec = np.zeros(5, dt)
            rec["x"] = np.arange(5) + 0.123456789123  # needs float64
            rec["reflectivity"] = [1, 2, 3, 4, 65535]
            rec["line"] = [0, 1, 2, 3, 4]
            rec["timestamp"] = stamp + np.array([0.02, 0.0, 0.04, 0.06, 0.08])
            msg = ts.types[PC2](
                header=make_header(ts, stamp, "os"), height=1, width=5, fields=fields,
                is_bigendian=False, point_step=40, row_step=200,
                data=rec.view(np.uint8).copy(), is_dense=True,
            )  # fmt: skip
            writer.write(c_pc, int(stamp * 1e9), ser(msg, PC2))
            s = ts.types["std_msgs/msg/String"](data="hi")
            writer.write(c_str, int(stamp * 1e9), ser(s, "std_msgs/msg/String"))
    src = open_source(path)
    assert src.topic == "/points" and len(src) == 3
    got = list(src)
    assert [s.stamp for s in got] == [100.0, 101.0, 102.0]
    np.testing.assert_array_equal(got[2].xyz[:, 0], np.arange(5) + 0.123456789123)
    np.testing.assert_array_equal(got[0].intensity, [1, 2, 3, 4, 65535])
    np.testing.assert_array_equal(got[0].ring, [0, 1, 2, 3, 4])
    np.testing.assert_allclose(got[1].time, [0.02, 0.0, 0.04, 0.06, 0.08], atol=1e-9)


def test_two_cloud_topics_error_names_both(tmp_path):
    path = tmp_path / "two.bag"
    with Writer1(path) as w:
        ca = w.add_connection("/lidar_front", PC2, typestore=TS1)
        cb = w.add_connection("/lidar_rear", PC2, typestore=TS1)
        for i, s in enumerate(scans(2, 20)):
            data = TS1.serialize_ros1(encode_pointcloud2(s, TS1), PC2)
            w.write(ca, 10**9 * (i + 1), data)
            w.write(cb, 10**9 * (i + 1), data)
            w.write(cb, 10**9 * (i + 1) + 5, data)
    with pytest.raises(TopicError) as err:
        open_source(path)
    msg = str(err.value)
    assert "/lidar_front" in msg and "/lidar_rear" in msg and "--topic" in msg
    assert "(2 msgs)" in msg and "(4 msgs)" in msg
    src = open_source(path, topic="/lidar_rear")
    assert len(src) == 4 and len(list(src)) == 4
    with pytest.raises(TopicError, match="(?s)/nope not found.*/lidar_front"):
        open_source(path, topic="/nope")


def test_laserscan_topic_chosen_when_no_cloud(tmp_path):
    ranges = np.array([[1.0, 2.0, np.inf], [3.0, 3.0, 3.0]])
    path = write_laserscan_bag(
        tmp_path / "scan", [1.0, 1.1], ranges, -0.5, 0.5, 10.0, fmt="ros2", time_increment=1e-3
    )
    src = open_source(path)
    assert src.topic == "/scan" and len(src) == 2
    a, b = list(src)
    assert len(a) == 2 and len(b) == 3
    np.testing.assert_allclose(a.xyz[1], [2.0, 0.0, 0.0], atol=1e-7)  # beam 1: angle 0
    np.testing.assert_allclose(b.time, [0.0, 1e-3, 2e-3], atol=1e-9)


@pytest.mark.parametrize("fmt", ["ros1", "ros2"])
def test_empty_bag(tmp_path, fmt):
    path = bag_name(tmp_path, fmt)
    writer, ts, _ = open_raw(path, fmt)
    with writer:
        writer.add_connection("/velodyne_points", PC2, typestore=ts)
    with pytest.raises(InputError, match="contains no messages"):
        open_source(path)


@pytest.mark.parametrize("name", ["cut.bag", "rec.bag.active", "mcap"])
def test_bag_without_index_is_read_record_by_record(tmp_path, name):
    """A ROS1 bag cut short (its index at the end gone), a killed ROS1 recording
    (.bag.active) or a ROS2 MCAP file without its end: rosbags cannot open them; every
    complete message before the cut is read, noted once, then the error of the cut."""
    ref = scans(6, 2000)
    if name == "mcap":
        path = write_pointcloud_bag(tmp_path / "m", ref, fmt="mcap")
        data_file = next(path.glob("*.mcap"))
    else:
        full = write_pointcloud_bag(tmp_path / "full.bag", ref)
        path = data_file = tmp_path / name
        shutil.copy(full, path)
    raw = data_file.read_bytes()
    data_file.write_bytes(raw[: len(raw) // 2])
    src = open_source(path)
    got = []
    with pytest.raises(InputError, match="is cut short: read error at its end") as err:
        for s in src:  # then the error of the cut: the caller stops, keeps what it has
            got.append(s)
    n = 3 if name == "mcap" else 2  # the cut falls inside the 3rd (ROS1) / 4th message
    assert f"the {n} messages on /velodyne_points before the cut were read" in str(err.value)
    assert len(src) == len(got) == n
    for s, r in zip(got, ref, strict=False):
        assert s.stamp == pytest.approx(r.stamp, abs=1e-6)
        np.testing.assert_allclose(s.xyz, r.xyz, atol=4e-6)
        np.testing.assert_array_equal(s.ring, r.ring)
    assert len(src.notes) == 1 and "no usable index" in src.notes[0]
    assert f"read record by record, {n} messages (the file's" in src.notes[0]
    # slam info describes it the same way instead of "cannot open"
    from slam.io.info import describe

    info = describe(path)
    assert info["topics"]["/velodyne_points"]["count"] == n
    assert info["topics"]["/velodyne_points"]["points"] == len(ref[0])
    assert "record by record" in info["note"]
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    with pytest.raises(InputError, match="record by record failed too"):
        open_source(tmp_path / "junk.bag")


def test_corrupt_message_in_the_middle_names_index(tmp_path):
    path = tmp_path / "bad.bag"
    with Writer1(path) as w:
        c = w.add_connection("/velodyne_points", PC2, typestore=TS1)
        for i, s in enumerate(scans(5, 30)):
            data = TS1.serialize_ros1(encode_pointcloud2(s, TS1), PC2)
            if i == 2:
                data = data[:40]  # cut inside the fields list
            w.write(c, 10**9 * (i + 1), data)
    got = list(open_source(path))  # one corrupt message costs one frame, not the run
    assert [s.index for s in got] == [0, 1, 2, 3, 4]
    bad = got[2]
    assert isinstance(bad, SkippedMessage) and bad.reason == "corrupt message"
    assert "message 2 on /velodyne_points" in bad.detail
    assert all(isinstance(s, Scan) and len(s) == 30 for i, s in enumerate(got) if i != 2)


def test_bare_mcap_file_and_db3_without_metadata(tmp_path):
    ref = scans(3, 50)
    bag = write_pointcloud_bag(tmp_path / "m", ref, fmt="mcap")
    bare = tmp_path / "lonely.mcap"
    shutil.copy(next(bag.glob("*.mcap")), bare)
    src = open_source(bare)
    assert len(src) == 3
    np.testing.assert_allclose(list(src)[2].xyz, ref[2].xyz, atol=4e-6)
    db = write_pointcloud_bag(tmp_path / "d", ref, fmt="ros2")
    (db / "metadata.yaml").unlink()
    assert [s.index for s in open_source(db)] == [0, 1, 2]


def test_describe_bag(tmp_path):
    path = write_pointcloud_bag(tmp_path / "o.bag", scans(5, 40), layout="ouster")
    info = describe(path)
    assert info["format"] == "ROS1 bag" and info["message_count"] == 5
    assert info["duration"] == pytest.approx(0.4, abs=1e-6)
    assert list(info["topics"]) == ["/velodyne_points"]
    topic = info["topics"]["/velodyne_points"]
    assert topic["type"] == PC2 and topic["count"] == 5
    assert topic["rate_hz"] == pytest.approx(10.0, rel=1e-6)
    assert topic["points"] == 40 and topic["point_step"] == 48
    assert {"name": "t", "datatype": "UINT32", "offset": 20, "count": 1} in topic["fields"]
    assert (topic["time_field"], topic["time_unit"], topic["time_absolute"]) == ("t", "ns", False)


def test_unknown_input_lists_accepted_formats(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="KITTI sequence folder"):
        open_source(tmp_path / "notes.txt")
    with pytest.raises(InputError, match="not found"):
        open_source(tmp_path / "missing.bag")


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_messy_bag_costs_one_frame_per_bad_message(tmp_path, fmt):
    """Corrupt, all-NaN, empty and bad-x-datatype messages are skipped with their reason;
    an unknown datatype on the ring field drops the ring (noted once), not the scan."""
    path = bag_name(tmp_path, fmt)
    writer, ts, serialize = open_raw(path, fmt)
    ref = scans(7, 40)
    with writer:
        c = writer.add_connection("/velodyne_points", PC2, typestore=ts)
        for i, s in enumerate(ref):
            if i == 2:
                s = Scan(stamp=s.stamp, xyz=np.full((40, 3), np.nan))
            if i == 3:
                s = Scan(stamp=s.stamp, xyz=np.zeros((0, 3)))
            msg = encode_pointcloud2(s, ts)
            if i == 4:
                msg.fields[0].datatype = 11
            if i in (5, 6):
                msg.fields[4].datatype = 99  # ring
            data = serialize(msg, PC2)
            if i == 1:
                data = data[:60]
            writer.write(c, 10**9 * (i + 1), data)
    src = open_source(path)
    got = list(src)
    reasons = [s.reason if isinstance(s, SkippedMessage) else "scan" for s in got]
    assert reasons == [
        "scan", "corrupt message", "no finite points", "empty message", "bad field datatype",
        "scan", "scan",
    ]  # fmt: skip
    assert [s.index for s in got] == list(range(7))
    np.testing.assert_allclose(got[5].xyz, ref[5].xyz, atol=4e-6)
    assert got[5].ring is None and got[0].ring is not None and got[5].time is not None
    assert len(src.notes) == 1 and "'ring' has unknown datatype 99" in src.notes[0]


def _stamped_bag(path, header, record):
    """A ROS1 bag of small scans with these header stamps and record times (s)."""
    with Writer1(path) as w:
        c = w.add_connection("/velodyne_points", PC2, typestore=TS1)
        for s, h, r in zip(scans(len(header), 20), header, record, strict=True):
            s.stamp = float(h)
            w.write(c, int(round(r * 1e9)), TS1.serialize_ros1(encode_pointcloud2(s, TS1), PC2))
    return path


def test_the_clock_of_the_stamps(tmp_path):
    """auto: the header stamps, unless they run backwards: then the record time, noted;
    header / record force one; neither clock increasing is an InputError saying so."""
    t = 1_600_000_000.0 + 0.1 * np.arange(12)
    rec = t + 0.05
    back = _stamped_bag(tmp_path / "back.bag", t[::-1], rec)
    src = open_source(back)
    assert [s.stamp for s in src] == pytest.approx(t[::-1], abs=1e-6)  # default: header
    src.use_stamps("auto", 4)
    assert [s.stamp for s in src] == pytest.approx(rec, abs=1e-6)
    assert len(src.notes) == 1 and "scans stamped with the bag's record time" in src.notes[0]
    assert "run backwards" in src.notes[0]
    src.use_stamps("header")
    assert [s.stamp for s in src] == pytest.approx(t[::-1], abs=1e-6)
    swapped = t.copy()
    swapped[[0, 1, 6, 7]] = swapped[[1, 0, 7, 6]]  # recorded out of order: the buffer's job
    src = open_source(_stamped_bag(tmp_path / "swap.bag", swapped, rec))
    src.use_stamps("auto", 4)
    assert [s.stamp for s in src] == pytest.approx(swapped, abs=1e-6)
    src.use_stamps("auto", 0)  # without a buffer 2 of 12 drop: still 3 in 4 in order
    assert [s.stamp for s in src] == pytest.approx(swapped, abs=1e-6) and not src.notes
    unset = _stamped_bag(tmp_path / "unset.bag", np.zeros(12), np.full(12, 5.0))
    src = open_source(unset)
    src.use_stamps("auto", 4)
    with pytest.raises(InputError, match="are all 0.000000000 s .the driver does not set") as e:
        list(src)
    assert "neither clock can order the scans" in str(e.value)
    assert "--set source.stamps=header" in str(e.value)


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_absurd_coordinates_are_dropped_and_a_mostly_absurd_message_skipped(tmp_path, fmt, caplog):
    """A few points at 3e38 m or 1e5 m (damaged bytes, no lidar returns) are dropped from
    their scan, noted once; a message whose points are mostly such is skipped as "absurd
    coordinates", counted by the stream with one warning, and the scans after it are read."""
    from slam.config import SourceConfig
    from slam.io.stream import ScanStream

    path = bag_name(tmp_path, fmt)
    writer, ts, serialize = open_raw(path, fmt)
    ref = scans(5, 40)
    few, most = ref[1].xyz.copy(), ref[3].xyz.copy()
    few[[3, 17, 30]] = [[3.0e38, 1.0, 2.0], [1.0, -3.4e38, 0.0], [0.5, 0.5, 1.0e5]]
    most[:30, 2] = 3.0e38
    with writer:
        c = writer.add_connection("/velodyne_points", PC2, typestore=ts)
        for i, s in enumerate(ref):
            if i in (1, 3):
                s = Scan(s.stamp, few if i == 1 else most, s.intensity, s.ring, s.time, i)
            writer.write(c, 10**9 * (i + 1), serialize(encode_pointcloud2(s, ts), PC2))
    src = open_source(path)
    got = list(src)
    reasons = [s.reason if isinstance(s, SkippedMessage) else "scan" for s in got]
    assert reasons == ["scan", "scan", "scan", "absurd coordinates", "scan"]
    assert "30 of its 40 points" in got[3].detail and "message 3" in got[3].detail
    keep = np.setdiff1d(np.arange(40), [3, 17, 30])
    np.testing.assert_allclose(got[1].xyz, ref[1].xyz[keep], atol=4e-6)
    np.testing.assert_array_equal(got[1].ring, ref[1].ring[keep])
    assert len(got[1]) == 37 and len(got[0]) == len(got[4]) == 40
    assert src.notes == [
        "points with a coordinate beyond 10000 m (no lidar's returns: damaged data) dropped"
    ]
    stream = ScanStream(open_source(path), SourceConfig(beam_scans=0))
    kept = [s for s in stream.items() if isinstance(s, Scan)]
    assert [s.index for s in kept] == [0, 1, 2, 4]
    assert dict(stream.stats.skipped) == {"absurd coordinates": 1}
    assert sum("absurd coordinates" in r.getMessage() for r in caplog.records) == 1
