"""Point-cloud preprocessing: statistical outlier removal and voxel downsampling."""

from slam.preprocess.sor import SorConfig, apply_sor, classic_sor, weighted_sor
from slam.preprocess.voxel import voxel_downsample

__all__ = ["SorConfig", "apply_sor", "classic_sor", "weighted_sor", "voxel_downsample"]
