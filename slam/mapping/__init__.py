"""Local maps for scan-to-map registration."""

from slam.mapping.local_map import LocalMapConfig, VoxelHashMap, voxel_hash

__all__ = ["LocalMapConfig", "VoxelHashMap", "voxel_hash"]
