"""KITTI and PCD/PLY folder readers, map export, describe() on folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from shared_data import shared_path

from slam.errors import InputError
from slam.io.folders import FolderSource, name_stamps, natural_key
from slam.io.info import describe
from slam.io.kitti import KittiSource
from slam.io.maps import write_map
from slam.io.source import open_source
from slam.types import Scan, SkippedMessage


def write_kitti(root, clouds, *, times=None, poses=None, calib=None):
    (root / "velodyne").mkdir(parents=True)
    for i, pts in enumerate(clouds):
        pts.astype("<f4").tofile(root / "velodyne" / f"{i:06d}.bin")
    if times is not None:
        np.savetxt(root / "times.txt", times)
    if poses is not None:
        np.savetxt(root / "poses.txt", poses[:, :3, :].reshape(-1, 12))
    if calib is not None:
        (root / "calib.txt").write_text(
            "P0: " + " ".join(["0"] * 12) + "\nTr: " + " ".join(map(str, calib[:3].ravel()))
        )
    return root


def test_kitti_folder(tmp_path):
    rng = np.random.default_rng(0)
    clouds = [rng.uniform(-20, 20, (100 + i, 4)).astype(np.float32) for i in range(3)]
    clouds[1][5, 0] = np.nan
    root = write_kitti(tmp_path / "00", clouds)
    src = open_source(root)
    assert isinstance(src, KittiSource) and len(src) == 3 and src.topic is None
    got = list(src)
    assert [s.index for s in got] == [0, 1, 2]
    assert [s.stamp for s in got] == pytest.approx([0.0, 0.1, 0.2])
    np.testing.assert_array_equal(got[0].xyz, clouds[0][:, :3].astype(np.float64))
    np.testing.assert_array_equal(got[2].intensity, clouds[2][:, 3])
    assert len(got[1]) == 100 and got[1].intensity.shape == (100,)  # NaN point dropped
    assert got[0].ring is None and got[0].time is None
    assert src.ground_truth() is None


def test_kitti_times_and_ground_truth_in_lidar_frame(tmp_path):
    clouds = [np.zeros((4, 4), np.float32)] * 2
    tr = np.eye(4)  # velodyne -> camera: x forward -> z forward
    tr[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    tr[:3, 3] = [0.1, -0.2, 0.3]
    cam = np.tile(np.eye(4), (2, 1, 1))
    cam[1, :3, 3] = [0.0, 0.0, 2.0]  # 2 m along camera z = lidar x
    root = write_kitti(tmp_path / "s", clouds, times=[5.0, 5.25], poses=cam, calib=tr)
    src = KittiSource(root)
    assert [s.stamp for s in src] == [5.0, 5.25]
    gt = src.ground_truth()
    np.testing.assert_allclose(gt[1][:3, 3], [2.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(gt[1][:3, :3], np.eye(3), atol=1e-9)


def test_kitti_bad_bin_size(tmp_path):
    root = write_kitti(tmp_path / "k", [np.zeros((3, 4), np.float32)])
    (root / "velodyne" / "000000.bin").write_bytes(b"\0" * 10)
    (bad,) = list(open_source(root))
    assert isinstance(bad, SkippedMessage) and bad.reason == "corrupt file"
    assert "10 bytes is not a whole number of KITTI points" in bad.detail


def write_cloud(path, xyz, intensity=None):
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(xyz.astype(np.float32))
    if intensity is not None:
        pc.point.intensity = o3d.core.Tensor(intensity.astype(np.float32).reshape(-1, 1))
    assert o3d.t.io.write_point_cloud(str(path), pc)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_cloud_folder_natural_order_and_intensity(tmp_path, suffix):
    rng = np.random.default_rng(3)
    data = {}
    for stem in ["10.5", "2", "1.25"]:
        xyz = rng.uniform(-5, 5, (50, 3))
        inten = rng.uniform(0, 1, 50)
        write_cloud(tmp_path / f"{stem}{suffix}", xyz, inten)
        data[stem] = (xyz, inten)
    (tmp_path / "readme.txt").write_text("ignored")
    src = open_source(tmp_path)
    assert isinstance(src, FolderSource) and len(src) == 3
    got = list(src)
    assert [s.stamp for s in got] == [1.25, 2.0, 10.5]
    xyz, inten = data["2"]
    np.testing.assert_allclose(got[1].xyz, xyz, atol=1e-6)
    np.testing.assert_allclose(got[1].intensity, inten, atol=1e-7)
    assert got[0].ring is None


def test_cloud_folder_non_numeric_names_and_no_intensity(tmp_path):
    for name in ["scan_10.pcd", "scan_9.pcd", "scan_100.pcd"]:
        write_cloud(tmp_path / name, np.ones((3, 3)) * len(name))
    src = FolderSource(tmp_path)
    assert [f.name for f in src.files] == ["scan_9.pcd", "scan_10.pcd", "scan_100.pcd"]
    got = list(src)
    assert [s.stamp for s in got] == pytest.approx([0.0, 0.1, 0.2])
    assert got[0].intensity is None and got[0].xyz[0, 0] == 10.0


def test_stamp_parsing_units():
    from pathlib import Path

    files = [Path("1600000000123456789.pcd"), Path("1600000000223456789.pcd")]
    np.testing.assert_allclose(name_stamps(files)[0], [1600000000.1234567, 1600000000.2234567])
    assert natural_key(Path("a2.pcd")) < natural_key(Path("a10.pcd"))


def test_write_map_voxel(tmp_path):
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(10)), -1).reshape(-1, 3)
    pts = np.vstack([grid + 0.01, grid + 0.02, [[np.nan, 0, 0]]]) * 1.0  # 2 points per 1 m cell
    n = write_map(tmp_path / "map.pcd", pts, voxel=1.0)
    assert n == 1000
    back = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "map.pcd")).points)
    assert back.shape == (1000, 3)
    assert write_map(tmp_path / "sub" / "map.ply", pts, voxel=0.0) == 2000
    assert write_map(tmp_path / "empty.pcd", np.zeros((0, 3)), voxel=1.0) == 0
    assert (tmp_path / "empty.pcd").read_text().count("POINTS 0") == 1
    with pytest.raises(InputError, match=".pcd or .ply"):
        write_map(tmp_path / "map.xyz", pts, voxel=1.0)


def test_describe_folder(tmp_path):
    root = write_kitti(tmp_path / "00", [np.ones((7, 4), np.float32)] * 4)
    info = describe(root)
    assert info["message_count"] == 4 and info["rate_hz"] == pytest.approx(10.0)
    assert info["first_scan"] == {"points": 7, "intensity": True, "ring": False, "time": False}


# ------------------------------------------------------------------ PCD files (numpy reader)

_PCD_TYPE = {"f": "F", "u": "U", "i": "I"}


def pcd_bytes(
    rec: np.ndarray, *, data: str = "binary", trailing: bytes = b"", points=None
) -> bytes:
    """A PCD v0.7 file holding the structured array ``rec`` (little endian, packed fields)."""
    names = rec.dtype.names
    fmts = [rec.dtype.fields[n][0] for n in names]
    sizes = [f.base.itemsize for f in fmts]
    counts = [int(np.prod(f.shape)) if f.shape else 1 for f in fmts]
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)}\nSIZE {' '.join(map(str, sizes))}\n"
        f"TYPE {' '.join(_PCD_TYPE[f.base.kind] for f in fmts)}\n"
        f"COUNT {' '.join(map(str, counts))}\nWIDTH {rec.size}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {rec.size if points is None else points}\n"
        f"DATA {data}\n"
    ).encode()
    if data == "ascii":
        cols = [rec[n].reshape(rec.size, -1).astype(np.float64) for n in names if rec.size]
        rows = np.hstack(cols) if rec.size else np.zeros((0, 1))
        body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in rows).encode()
    else:
        packed = np.dtype([(n, f.newbyteorder("<")) for n, f in zip(names, fmts, strict=True)])
        body = rec.astype(packed).tobytes()
    return header + body + trailing


def xyzit(n: int, tcode: str = "<f4", seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                ("intensity", "<f4"), ("time", tcode)]))  # fmt: skip
    for c in "xyz":
        rec[c] = rng.uniform(-30, 30, n)
    rec["intensity"] = rng.uniform(0, 1, n)
    return rec


@pytest.fixture(scope="module")
def kitti_raw_pcds(tmp_path_factory):
    """The 22 real HDL-64E PCDs of ../shared/data/kitti_raw_drive, extracted once."""
    import tarfile

    out = tmp_path_factory.mktemp("kitti_raw")
    with tarfile.open(shared_path("kitti_raw_drive", "data_1.tar.xz"), "r:xz") as tar:
        tar.extractall(out, filter="data")
    return out / "data_1"


def test_real_kitti_raw_pcds_with_trailing_bytes(kitti_raw_pcds):
    files = sorted(kitti_raw_pcds.glob("*.pcd"))
    assert len(files) == 22
    src = open_source(kitti_raw_pcds)
    assert isinstance(src, FolderSource) and len(src) == 22
    scans = list(src)
    header = files[0].read_bytes()[:400].decode("ascii", "replace")
    assert "POINTS 119978" in header and "DATA binary" in header
    assert files[0].stat().st_size > header.index("DATA binary") + 12 + 119978 * 16  # a tail
    assert len(scans[0]) == 119978
    assert all(isinstance(s, Scan) and 110_000 < len(s) < 130_000 for s in scans)
    # zero-padded frame counters as names: frame index x 0.1 s (KITTI's 10 Hz)
    assert [s.stamp for s in scans] == pytest.approx([0.1 * i for i in range(22)])
    first = scans[0]
    r = np.linalg.norm(first.xyz, axis=1)
    assert 70 < r.max() < 81 and first.intensity.min() >= 0 and first.intensity.max() < 1
    assert first.ring is None and first.time is None
    # the same numbers as open3d's reader (which ignores the tail too)
    ref = o3d.t.io.read_point_cloud(str(files[0]))
    np.testing.assert_array_equal(first.xyz, ref.point.positions.numpy().astype(np.float64))
    np.testing.assert_array_equal(first.intensity, ref.point.intensity.numpy()[:, 0])


def test_folder_with_an_empty_pcd_in_the_middle(tmp_path):
    for i in range(5):
        (tmp_path / f"{i}.pcd").write_bytes(pcd_bytes(xyzit(20 + i, seed=i)))
    (tmp_path / "2.pcd").write_bytes(b"")
    (tmp_path / "3.pcd").write_bytes(pcd_bytes(xyzit(0)))  # a valid header with POINTS 0
    got = list(FolderSource(tmp_path))
    assert [s.index for s in got] == [0, 1, 2, 3, 4]
    assert isinstance(got[2], SkippedMessage) and got[2].reason == "empty file"
    assert "2.pcd" in got[2].detail
    assert isinstance(got[3], SkippedMessage) and got[3].reason == "empty file"
    assert [len(got[i]) for i in (0, 1, 4)] == [20, 21, 24]
    assert [got[i].stamp for i in (0, 1, 4)] == pytest.approx([0.0, 0.1, 0.4])


def test_pcd_corrupt_files_are_skipped_with_reasons(tmp_path):
    good = pcd_bytes(xyzit(10))
    (tmp_path / "0.pcd").write_bytes(good[:-17])  # truncated data
    nan = xyzit(4)
    nan["y"] = np.nan
    (tmp_path / "1.pcd").write_bytes(pcd_bytes(nan))
    (tmp_path / "2.pcd").write_bytes(b"\x89PNG not a point cloud")
    (tmp_path / "3.pcd").write_bytes(good)
    got = list(FolderSource(tmp_path))
    assert [getattr(s, "reason", None) for s in got] == [
        "corrupt file", "no finite points", "corrupt file", None,
    ]  # fmt: skip
    assert "truncated" in got[0].detail and len(got[3]) == 10


@pytest.mark.parametrize(
    ("tcode", "scale"), [("<u4", 1e6), ("<f8", 1e9), ("<f4", 1e3), ("<f4", 1.0)]
)
def test_pcd_per_point_time_units(tmp_path, tcode, scale):
    rec = xyzit(50, tcode)
    sweep = np.linspace(0.0, 0.1, 50)
    rec["time"] = np.round(sweep * scale) if tcode[1] == "u" else sweep * scale
    (tmp_path / "7.5.pcd").write_bytes(pcd_bytes(rec))
    (scan,) = list(FolderSource(tmp_path))
    np.testing.assert_allclose(scan.time, sweep, atol=1e-6)
    assert scan.stamp == 7.5
    np.testing.assert_array_equal(scan.xyz[:, 0], rec["x"].astype(np.float64))


def test_pcd_absolute_time_sets_the_stamp(tmp_path):
    rec = xyzit(5, "<f8")
    rec["time"] = 1_600_000_000.0 + np.array([0.02, 0.0, 0.04, 0.06, 0.08])
    (tmp_path / "scan.pcd").write_bytes(pcd_bytes(rec))
    (scan,) = list(FolderSource(tmp_path))
    assert scan.stamp == pytest.approx(1_600_000_000.0, abs=1e-6)
    np.testing.assert_allclose(scan.time, [0.02, 0.0, 0.04, 0.06, 0.08], atol=1e-6)


def test_pcd_ascii_count_and_uint16_ring(tmp_path):
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<u2"), ("n", "<f4", (3,))])
    rec = np.zeros(3, dt)
    rec["x"] = [1.5, 2.5, 3.5]
    rec["ring"] = [0, 63, 127]
    rec["n"] = [[9, 8, 7]] * 3
    (tmp_path / "a.pcd").write_bytes(pcd_bytes(rec, data="ascii", trailing=b"\n\n"))
    rec["ring"] = [0, 40000, 1]
    (tmp_path / "b.pcd").write_bytes(pcd_bytes(rec, trailing=b"\x00" * 100))
    src = FolderSource(tmp_path)
    a, b = list(src)
    np.testing.assert_array_equal(a.xyz[:, 0], [1.5, 2.5, 3.5])
    np.testing.assert_array_equal(a.ring, [0, 63, 127])
    assert b.ring is None and len(b) == 3 and "ring dropped" in src.notes[0]


def test_kitti_empty_and_nan_bins_are_skipped(tmp_path):
    clouds = [np.ones((5, 4), np.float32), np.full((3, 4), np.nan, np.float32)] + [
        np.ones((6, 4), np.float32)
    ]
    root = write_kitti(tmp_path / "k", clouds)
    (root / "velodyne" / "000003.bin").write_bytes(b"")
    got = list(KittiSource(root))
    assert [s.reason if isinstance(s, SkippedMessage) else len(s) for s in got] == [
        5,
        "no finite points",
        6,
        "empty file",
    ]


def test_compressed_pcd_and_ply_through_open3d_damaged_ones_skipped(tmp_path):
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-5, 5, (40, 3))
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(xyz.astype(np.float32))
    assert o3d.t.io.write_point_cloud(str(tmp_path / "0.pcd"), pc, compressed=True)
    assert b"DATA binary_compressed" in (tmp_path / "0.pcd").read_bytes()[:300]
    write_cloud(tmp_path / "1.ply", xyz)
    (tmp_path / "2.ply").write_bytes(b"")
    (tmp_path / "3.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\ngarbage")
    got = list(FolderSource(tmp_path))
    np.testing.assert_allclose(got[0].xyz, xyz, atol=1e-6)
    np.testing.assert_allclose(got[1].xyz, xyz, atol=1e-6)
    assert [got[2].reason, got[3].reason] == ["empty file", "corrupt file"]


def test_zero_padded_frame_counters_are_frames_not_seconds():
    files = [Path(f"{i:010d}.pcd") for i in (0, 1, 2, 4)]  # one frame missing
    np.testing.assert_allclose(name_stamps(files)[0], [0.0, 0.1, 0.2, 0.4])
    seconds = [Path("1600000000.100.pcd"), Path("1600000000.200.pcd")]
    np.testing.assert_allclose(name_stamps(seconds)[0], [1600000000.1, 1600000000.2])


def test_folder_of_kitti_bins_directly(tmp_path):
    """``slam run DIR/velodyne``: the folder of .bin scans itself is a KITTI input; the
    sequence's times / poses / calib are read from its parent, as for ``slam run DIR``."""
    rng = np.random.default_rng(1)
    clouds = [rng.uniform(-20, 20, (50, 4)).astype(np.float32) for _ in range(3)]
    cam = np.tile(np.eye(4), (3, 1, 1))
    cam[:, 2, 3] = [0.0, 1.0, 2.0]  # along camera z
    tr = np.eye(4)
    tr[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    root = write_kitti(tmp_path / "07", clouds, times=[1.0, 1.1, 1.2], poses=cam, calib=tr)
    src = open_source(root / "velodyne")
    assert isinstance(src, KittiSource) and len(src) == 3
    assert "KITTI .bin folder" in src.description
    got = list(src)
    assert [s.stamp for s in got] == pytest.approx([1.0, 1.1, 1.2])
    np.testing.assert_array_equal(got[1].xyz, clouds[1][:, :3].astype(np.float64))
    np.testing.assert_allclose(src.ground_truth()[2][:3, 3], [2.0, 0.0, 0.0], atol=1e-9)
    # a bare folder of scans named by frame counter: 0.1 s apart, no ground truth
    bare = tmp_path / "scans"
    bare.mkdir()
    for i, pts in enumerate(clouds):
        pts.tofile(bare / f"{i + 10}.bin")
    src = open_source(bare)
    assert isinstance(src, KittiSource) and src.ground_truth() is None
    assert [s.stamp for s in src] == pytest.approx([1.0, 1.1, 1.2])
    # a times.txt that does not fit the scans is refused with what to do
    (bare / "times.txt").write_text("0.0\n")
    with pytest.raises(InputError, match="times.txt line per scan"):
        open_source(bare)


def test_slam_run_on_a_real_velodyne_folder(tmp_path):
    """``slam run SEQ/velodyne`` on the shared KITTI odometry scans runs (it was refused)
    and finds the HDL-64E's 64 beams."""
    import json

    from slam.cli import main

    out = tmp_path / "run"
    folder = shared_path("kitti_odometry", "05", "velodyne")
    assert main(["run", str(folder), "--out", str(out), "--max-frames", "3", "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 3 and metrics["skipped_frames"] == 0
    assert metrics["sensor"].startswith("inferred 64 beams") and "point layout" in metrics["sensor"]


def test_frame_period_stamps_numbered_scans(tmp_path):
    """nuScenes keyframes (0.pcd ... 38.pcd) are 2 Hz: ``source.frame_period`` 0.5 stamps
    them 0, 0.5, 1.0, ... (the default 0.1 s made a 10 Hz sequence of them), and the
    input notes say how the scans were stamped."""
    from slam.config import load_config
    from slam.errors import ConfigError

    clouds = shared_path("nuscenes_keyframes", "clouds")
    src = open_source(clouds, frame_period=0.5)
    assert isinstance(src, FolderSource) and len(src) == 39
    np.testing.assert_allclose(src.stamps, np.arange(39) * 0.5)
    assert src.notes == [
        "the file names are frame numbers, not stamps: scans are 0.5 s apart (2 Hz; "
        "--set source.frame_period=SECONDS for another rate)"
    ]
    np.testing.assert_allclose(open_source(clouds).stamps[:3], [0.0, 0.1, 0.2])
    # KITTI scans without times.txt, and the config field with its checks
    bins = tmp_path / "scans"
    bins.mkdir()
    for i in range(3):
        np.ones((4, 4), "<f4").tofile(bins / f"{i:06d}.bin")
    assert [s.stamp for s in KittiSource(bins, frame_period=0.25)] == [0.0, 0.25, 0.5]
    assert "0.25 s apart (4 Hz" in KittiSource(bins, frame_period=0.25).notes[0]
    assert load_config(None, ["source.frame_period=0.5"]).source.frame_period == 0.5
    assert load_config(None).source.frame_period == 0.1
    for bad in ("0", "-1", "abc", ".nan"):
        with pytest.raises(ConfigError, match="frame_period"):
            load_config(None, [f"source.frame_period={bad}"])
    # names that are stamps stay stamps whatever the period
    assert FolderSource(shared_path("hilti_indoor", "clouds"), frame_period=0.5).stamps[1] == 0.5
    stamped = tmp_path / "stamped"
    stamped.mkdir()
    for stem in ("100.25", "100.75"):
        write_cloud(stamped / f"{stem}.pcd", np.ones((3, 3)))
    src = FolderSource(stamped, frame_period=0.5)
    assert list(src.stamps) == [100.25, 100.75] and src.notes == []


def test_slam_run_frame_period_reaches_the_folder_reader(tmp_path):
    """``slam run FOLDER --set source.frame_period=0.5``: the run's stamps are 0.5 s apart."""
    from slam.cli import main
    from slam.io.trajectory import read_tum

    out = tmp_path / "run"
    clouds = shared_path("nuscenes_keyframes", "clouds")
    args = ["run", str(clouds), "--out", str(out), "--max-frames", "3", "--quiet"]
    assert main([*args, "--set", "source.frame_period=0.5"]) == 0
    stamps, _ = read_tum(out / "trajectory.tum")
    np.testing.assert_allclose(stamps, [0.0, 0.5, 1.0])
