"""Voxel downsampling: the compiled pass keeps exactly the points of the numpy reference."""

import numpy as np
import pytest

from slam.preprocess.voxel import voxel_downsample, voxel_downsample_reference


@pytest.mark.parametrize("seed", range(4))
def test_voxel_downsample_equals_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-30, 30, (20000, 3)) * [1, 1, 0.1]
    xyz[:500] = xyz[500:1000]  # duplicates: ties go to the lowest index in both
    xyz[1000:1200] = np.round(xyz[1000:1200] / 0.4) * 0.4  # on voxel faces
    for voxel in (0.05, 0.4, 2.0):
        fast = voxel_downsample(xyz, voxel)
        ref = voxel_downsample_reference(xyz, voxel)
        assert np.array_equal(fast, ref), voxel
    one_per_voxel = voxel_downsample(xyz, 2.0)
    cells = np.floor(xyz[one_per_voxel] / 2.0)
    assert len(np.unique(cells, axis=0)) == len(one_per_voxel)  # one point per voxel
    assert len(one_per_voxel) == len(np.unique(np.floor(xyz / 2.0), axis=0))  # every voxel


def test_voxel_downsample_keeps_everything_without_a_voxel():
    xyz = np.random.default_rng(0).normal(size=(10, 3))
    assert np.array_equal(voxel_downsample(xyz, 0.0), np.arange(10))
    assert len(voxel_downsample(np.zeros((0, 3)), 0.1)) == 0
