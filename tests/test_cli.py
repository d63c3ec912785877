"""The `slam` command end to end: outputs, exit codes and messages users see."""

from __future__ import annotations

import json
from itertools import islice

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.typesys import Stores, get_typestore

from slam.cli import main
from slam.io.bag_writer import write_pointcloud_bag
from slam.io.pointcloud2 import encode_pointcloud2
from slam.io.source import open_source
from slam.io.trajectory import read_tum

TS1 = get_typestore(Stores.ROS1_NOETIC)
PC2 = "sensor_msgs/msg/PointCloud2"
FRAMES = 30


@pytest.fixture(scope="module")
def short_run(corridor_short, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    code = main(
        [
            "run",
            str(corridor_short.bag),
            "--gt",
            str(corridor_short.ground_truth),
            "--out",
            str(out),
            "--max-frames",
            str(FRAMES),
            "--quiet",
        ]
    )
    return code, out


def test_run_writes_every_output(short_run):
    code, out = short_run
    assert code == 0
    for name in (
        "trajectory.tum",
        "trajectory.kitti",
        "odometry.tum",
        "map.pcd",
        "graph.g2o",
        "metrics.json",
        "config.yaml",
        "ape.json",
        "report.html",
    ):
        assert (out / name).stat().st_size > 0, name
    stamps, traj = read_tum(out / "trajectory.tum")
    assert len(stamps) == FRAMES and len(np.loadtxt(out / "trajectory.kitti")) == FRAMES
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == FRAMES and metrics["keyframes"] >= 2
    assert metrics["factors"]["odometry"] == metrics["keyframes"] - 1
    ape = json.loads((out / "ape.json").read_text())
    assert ape["ape_trans"]["rmse"] < 0.1  # 3 s of driving: centimetres, not metres


def test_run_stamps_are_the_scan_header_stamps(short_run, corridor_short):
    _, out = short_run
    stamps, _ = read_tum(out / "trajectory.tum")
    header = [s.stamp for s in islice(open_source(corridor_short.bag), FRAMES)]
    np.testing.assert_allclose(stamps, header, atol=1e-6)


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["run", "/no/such/bag.bag"], "not"),
        (["run", "BAG", "--config", "nope"], "built-in configs"),
        (["run", "BAG", "--set", "frontend.bogus_key=1"], "valid keys"),
        (["run", "BAG", "--set", "backend.name=isam3"], "isam2"),
        (["run", "BAG", "--topic", "/nope"], "/velodyne_points"),
    ],
)
def test_bad_input_exits_2_with_a_message(corridor_short, capsys, args, fragment):
    args = [str(corridor_short.bag) if a == "BAG" else a for a in args]
    assert main(args + ["--quiet", "--max-frames", "2"]) == 2
    assert fragment in capsys.readouterr().err


def test_truncated_bag_exits_2(tmp_path, corridor_short, capsys):
    raw = corridor_short.bag.read_bytes()
    bad = tmp_path / "cut.bag"
    bad.write_bytes(raw[: len(raw) // 3])
    assert main(["run", str(bad), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "error" in capsys.readouterr().err


def test_bad_message_half_way_keeps_what_was_computed(tmp_path, corridor_short, capsys):
    scans = list(islice(open_source(corridor_short.bag), 8))
    path = tmp_path / "bad.bag"
    with Writer1(path) as w:
        c = w.add_connection("/velodyne_points", PC2, typestore=TS1)
        for i, s in enumerate(scans):
            data = TS1.serialize_ros1(encode_pointcloud2(s, TS1), PC2)
            w.write(c, int(s.stamp * 1e9), data[:40] if i == 5 else data)
    out = tmp_path / "o"
    assert main(["run", str(path), "--out", str(out), "--quiet", "--strict"]) == 2
    assert "message 5" in capsys.readouterr().err
    stamps, _ = read_tum(out / "trajectory.tum")
    assert len(stamps) == 5
    # default: the damaged message costs its frame only, counted in metrics.json
    out = tmp_path / "skip"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "skipped 1 input messages: 1 corrupt message" in err
    stamps, _ = read_tum(out / "trajectory.tum")
    assert len(stamps) == 7 and scans[5].stamp not in stamps
    m = json.loads((out / "metrics.json").read_text())
    assert m["skipped_messages"] == {"corrupt message": 1} and m["messages_skipped"] == 1


def test_start_and_max_frames_pick_a_window(tmp_path, corridor_short):
    out = tmp_path / "w"
    assert main(["run", str(corridor_short.bag), "--out", str(out), "--quiet",
                 "--start", "20", "--max-frames", "5"]) == 0  # fmt: skip
    stamps, traj = read_tum(out / "trajectory.tum")
    all_stamps = [s.stamp for s in islice(open_source(corridor_short.bag), 25)]
    np.testing.assert_allclose(stamps, all_stamps[20:25])
    np.testing.assert_allclose(traj[0], np.eye(4), atol=1e-12)  # the window starts at the origin
    assert main(["run", str(corridor_short.bag), "--out", str(tmp_path / "x"), "--quiet",
                 "--start", "100000"]) == 2  # fmt: skip


def test_empty_scans_and_nan_points_do_not_crash(tmp_path, corridor_short):
    scans = list(islice(open_source(corridor_short.bag), 12))
    scans[4].xyz[::3] = np.nan  # decoder drops NaN points
    scans[6] = scans[6].select(np.zeros(len(scans[6]), dtype=bool))  # no points at all
    bag = write_pointcloud_bag(tmp_path / "holes.bag", scans)
    out = tmp_path / "o"
    assert main(["run", str(bag), "--out", str(out), "--quiet"]) == 0
    stamps, traj = read_tum(out / "trajectory.tum")
    assert len(stamps) == 11 and np.isfinite(traj).all()  # the empty scan is skipped, counted
    assert json.loads((out / "metrics.json").read_text())["messages_skipped"] == 1


def test_info_prints_topics_and_fields(corridor_short, capsys):
    assert main(["info", str(corridor_short.bag)]) == 0
    text = capsys.readouterr().out
    assert "/velodyne_points" in text and "ring" in text and "time" in text


def test_map_walls_are_sharp(short_run, corridor_short):
    """The end wall of the corridor's south leg (x = 12 m in the world) is thin in map.pcd."""
    import open3d as o3d

    _, out = short_run
    cloud = np.asarray(o3d.io.read_point_cloud(str(out / "map.pcd")).points)
    _, gt = read_tum(corridor_short.ground_truth)
    _, odom = read_tum(out / "odometry.tum")
    T_world_odom = gt[0] @ np.linalg.inv(odom[0])
    world = cloud @ T_world_odom[:3, :3].T + T_world_odom[:3, 3]
    sel = (np.abs(world[:, 0] - 12.0) < 0.3) & (world[:, 1] > -6.8) & (world[:, 1] < -4.7)
    sel &= (world[:, 2] > 0.3) & (world[:, 2] < 2.7)
    assert sel.sum() > 50
    residual = np.abs(world[sel, 0] - 12.0)
    # a few cm: the robot accelerates from rest here, where constant-velocity deskew lags
    assert np.median(residual) < 0.03 and np.percentile(residual, 90) < 0.08


def test_compare_table_and_no_loop_reproduces_odometry(corridor_short, tmp_path, capsys):
    out = tmp_path / "cmp"
    code = main(
        [
            "compare",
            str(corridor_short.bag),
            "--gt",
            str(corridor_short.ground_truth),
            "--configs",
            "floam",
            "improved_floam",
            "--out",
            str(out),
            "--max-frames",
            "20",
            "--quiet",
        ]
    )
    assert code == 0
    table = capsys.readouterr().out
    for word in ("Max", "Mean", "Median", "Min", "RMSE", "Std", "floam", "improved_floam", "%"):
        assert word in table
    assert (out / "compare.csv").read_text().count("\n") >= 3
    assert (out / "report.html").stat().st_size > 10_000
    assert (out / "floam" / "trajectory.tum").exists()
    loop_out = tmp_path / "noloop"
    assert (
        main(
            [
                "run",
                str(corridor_short.bag),
                "--config",
                "improved_floam_loop",
                "--no-loop",
                "--out",
                str(loop_out),
                "--max-frames",
                "20",
                "--quiet",
            ]
        )
        == 0
    )
    _, a = read_tum(out / "improved_floam" / "trajectory.tum")
    _, b = read_tum(loop_out / "trajectory.tum")
    assert np.array_equal(a, b)


def test_stop_codes_say_why_a_run_ended_early():
    from slam.cli.common import stop_code as _stop_code
    from slam.state import Stop, StopReason

    assert _stop_code({"stop": None, "out": "o"}) == 0
    assert _stop_code({"stop": Stop(StopReason.INTERRUPTED), "out": "o"}) == 130
    assert _stop_code({"stop": Stop(StopReason.BAD_INPUT, "truncated bag"), "out": "o"}) == 2
    assert _stop_code({"stop": Stop(StopReason.BACKEND_FAILED, "indeterminate"), "out": "o"}) == 1
    # the words stay what metrics.json and the summary have always said
    assert str(Stop(StopReason.INTERRUPTED)) == "interrupted (Ctrl-C)"
    assert str(Stop(StopReason.BAD_INPUT, "truncated bag")) == "bad input: truncated bag"


def test_stamps_flag_reaches_the_source_config(tmp_path, corridor_short):
    out = tmp_path / "s"
    assert main(["run", str(corridor_short.bag), "--out", str(out), "--quiet",
                 "--max-frames", "3", "--stamps", "record"]) == 0  # fmt: skip
    assert "stamps: record" in (out / "config.yaml").read_text()
    # the kernels were loaded before the first frame's clock (slam.warmup)
    assert json.loads((out / "metrics.json").read_text())["warmup_seconds"] > 0
    stamps, _ = read_tum(out / "trajectory.tum")
    assert len(stamps) == 3
    with pytest.raises(SystemExit):
        main(["run", str(corridor_short.bag), "--stamps", "bogus"])
