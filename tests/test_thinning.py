"""Voxel thinning by the hashed kernel keeps exactly the points of voxel_downsample."""

import numpy as np
import pytest

from slam.errors import InputError
from slam.features.thinning import voxel_thin
from slam.preprocess.voxel import voxel_downsample, voxel_downsample_reference


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("voxel", [0.05, 0.2, 0.4, 3.0])
def test_same_points_as_voxel_downsample(seed, voxel):
    rng = np.random.default_rng(seed)
    n = 5000
    xyz = rng.normal(0, 8.0, (n, 3)) * [1, 1, 0.2]
    xyz[: n // 10] = xyz[n // 10 : 2 * (n // 10)]  # exact duplicates: ties
    xyz[:50] = np.round(xyz[:50] / voxel) * voxel  # points on voxel faces
    ref = voxel_downsample_reference(xyz, voxel)
    np.testing.assert_array_equal(voxel_thin(xyz, voxel), ref)
    np.testing.assert_array_equal(voxel_downsample(xyz, voxel), ref)
    sub = np.sort(rng.choice(n, n // 3, replace=False))
    np.testing.assert_array_equal(voxel_thin(xyz, voxel, sub), voxel_downsample(xyz[sub], voxel))
    assert 1 < len(voxel_thin(xyz, voxel, sub)) < len(sub)


def test_real_64_beam_scan_same_as_voxel_downsample(tmp_path):
    import tarfile

    from shared_data import shared_path

    from slam.io.folders import cloud_files, read_cloud

    with tarfile.open(shared_path("kitti_raw_drive", "data_1.tar.xz"), "r:xz") as tar:
        member = sorted(m for m in tar.getnames() if m.endswith(".pcd"))[0]
        tar.extract(member, tmp_path, filter="data")
    xyz = read_cloud(cloud_files(tmp_path / member.split("/")[0])[0]).xyz
    assert len(xyz) > 100_000
    for voxel in (0.15, 0.4):
        np.testing.assert_array_equal(voxel_thin(xyz, voxel), voxel_downsample(xyz, voxel))


def test_edge_cases():
    xyz = np.random.default_rng(0).normal(size=(20, 3))
    np.testing.assert_array_equal(voxel_thin(xyz, 0.0), np.arange(20))
    assert len(voxel_thin(xyz, 0.5, np.empty(0, dtype=np.int64))) == 0
    assert list(voxel_thin(xyz, 1e3)) == list(voxel_downsample(xyz, 1e3))
    with pytest.raises(InputError):
        voxel_thin(xyz * 1e10, 1e-12)
    with pytest.raises(InputError):
        voxel_thin(xyz[:, :2], 0.1)


def test_thin_to_count_caps_dense_regions_first():
    """The cap thins the dense patch and keeps the sparse line (inputs already thinned at
    their voxel, as the feature sets are)."""
    from slam.features.thinning import thin_to_count

    rng = np.random.default_rng(3)
    g = np.arange(50) * 0.2 + 0.1
    dense = np.c_[np.repeat(g, 50), np.tile(g, 50), rng.normal(0, 0.01, 2500)]  # 1 per voxel
    sparse = np.c_[np.arange(200) * 2.0 + 20.0, np.zeros(200), np.zeros(200)]
    xyz = np.r_[dense, sparse]
    (keep,) = thin_to_count([xyz], [0.2], 1000)
    assert 850 < len(keep) <= 1000
    assert np.all(np.diff(keep) > 0)
    assert (keep >= 2500).sum() == 200  # every sparse point kept
    (every,) = thin_to_count([xyz], [0.2], 10_000)
    np.testing.assert_array_equal(every, np.arange(len(xyz)))
    # two parts grow coarser together: the fine line (0.05 m voxel) keeps its share
    line = np.c_[np.arange(1000) * 0.05, np.full(1000, 20.0), np.zeros(1000)]
    k_patch, k_line = thin_to_count([dense, line], [0.2, 0.05], 1500)
    assert 1200 < len(k_patch) + len(k_line) <= 1500
    assert 350 < len(k_line) < 750 and 700 < len(k_patch) < 1300
    with pytest.raises(InputError):
        thin_to_count([xyz], [0.2], 0)
    with pytest.raises(InputError):
        thin_to_count([xyz, line], [0.2], 100)
