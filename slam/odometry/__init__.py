"""Scan-to-map odometry: the frame loop the 3D front ends share and the small objects it
composes (sweep clock, motion model, tracking gate, map-insert and keyframe policies)."""

from slam.odometry.config import CommonConfig
from slam.odometry.estimate import Estimate
from slam.odometry.scan_to_map import ScanToMapFrontend

__all__ = ["CommonConfig", "Estimate", "ScanToMapFrontend"]
