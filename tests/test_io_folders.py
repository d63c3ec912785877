"""KITTI and PCD/PLY folder readers, map export, describe() on folders."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from slam.errors import InputError
from slam.io.folders import FolderSource, natural_key, stamps_from_names
from slam.io.info import describe
from slam.io.kitti import KittiSource
from slam.io.maps import write_map
from slam.io.source import open_source
from slam.types import SkippedMessage


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
    np.testing.assert_allclose(stamps_from_names(files), [1600000000.1234567, 1600000000.2234567])
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
