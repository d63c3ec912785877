"""The scan-to-map front ends' shared frame loop, now in ``slam.odometry``: importable from
here for plugins written against earlier versions."""

from slam.odometry import CommonConfig, Estimate, ScanToMapFrontend

__all__ = ["CommonConfig", "Estimate", "ScanToMapFrontend"]
