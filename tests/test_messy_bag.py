"""A bag as real recordings come: damaged messages, duplicated stamps, a scan of NaNs.

Each costs its own frame (skipped, counted by reason in metrics.json); every other frame
gets exactly the pose the clean bag's run gives it.
"""

from __future__ import annotations

import json
from itertools import islice

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore

from slam.cli import main
from slam.io.pointcloud2 import encode_pointcloud2
from slam.io.source import open_source
from slam.io.trajectory import read_tum

TS1 = get_typestore(Stores.ROS1_NOETIC)
PC2 = "sensor_msgs/msg/PointCloud2"
N = 30


def _write(path, messages):
    with Writer1(path) as w:
        c = w.add_connection("/velodyne_points", PC2, typestore=TS1)
        for stamp, data in messages:
            w.write(c, int(stamp * 1e9), data)
    return path


def test_messy_bag_costs_only_the_damaged_frames(tmp_path, corridor_short):
    scans = list(islice(open_source(corridor_short.bag), N))
    clean = [(s.stamp, TS1.serialize_ros1(encode_pointcloud2(s, TS1), PC2)) for s in scans]
    messy = []
    for i, (stamp, data) in enumerate(clean):
        messy.append((stamp, data))
        if i in (5, 12, 20):  # a corrupt (cut) message between two good ones
            messy.append((stamp + 0.05, data[: len(data) // 3]))
        if i in (8, 16):  # the same scan recorded twice
            messy.append((stamp, data))
        if i == 14:  # a scan whose every point is NaN
            nan = scans[i].select(np.arange(len(scans[i])))
            nan.xyz = np.full_like(nan.xyz, np.nan)
            nan.stamp = stamp + 0.05
            messy.append((nan.stamp, TS1.serialize_ros1(encode_pointcloud2(nan, TS1), PC2)))
    a = _write(tmp_path / "clean.bag", clean)
    b = _write(tmp_path / "messy.bag", messy)
    assert main(["run", str(a), "--out", str(tmp_path / "a"), "--quiet"]) == 0
    assert main(["run", str(b), "--out", str(tmp_path / "b"), "--quiet"]) == 0
    sa, ta = read_tum(tmp_path / "a" / "trajectory.tum")
    sb, tb = read_tum(tmp_path / "b" / "trajectory.tum")
    np.testing.assert_array_equal(sa, sb)
    assert np.all(np.diff(sb) > 0)
    assert np.abs(ta[:, :3, 3] - tb[:, :3, 3]).max() < 1e-3
    m = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert m["frames"] == N
    assert m["messages_skipped"] == 6
    assert m["skipped_messages"]["duplicated stamp"] == 2
    assert sum(n for k, n in m["skipped_messages"].items() if k != "duplicated stamp") == 4
    # --strict: the first damaged message stops the run, outputs written, exit 2
    assert main(["run", str(b), "--out", str(tmp_path / "c"), "--quiet", "--strict"]) == 2
    assert len(read_tum(tmp_path / "c" / "trajectory.tum")[0]) == 6
