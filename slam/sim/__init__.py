"""Simulator: a ray-cast 16-beam spinning LiDAR driving through indoor/outdoor scenes.

Writes real bags (via :mod:`slam.io.bag_writer`) plus TUM ground truth; the data of the
demo and of every end-to-end test.
"""

from slam.sim.cache import SIM_VERSION, cache_root, ensure_sequence
from slam.sim.lidar import LidarModel, ScanTruth, simulate_scan, simulate_scan_truth
from slam.sim.scene import Pedestrian, Scene
from slam.sim.scenes import SCENES
from slam.sim.simulate import (
    SimResult,
    effective_model,
    iter_scans,
    load_result,
    make_scene,
    simulate,
)

__all__ = [
    "SCENES",
    "SIM_VERSION",
    "LidarModel",
    "Pedestrian",
    "Scene",
    "ScanTruth",
    "SimResult",
    "cache_root",
    "effective_model",
    "ensure_sequence",
    "iter_scans",
    "load_result",
    "make_scene",
    "simulate",
    "simulate_scan",
    "simulate_scan_truth",
]
