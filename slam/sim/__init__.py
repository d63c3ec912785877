"""Simulator: a ray-cast spinning LiDAR (VLP-16, HDL-32E, HDL-64E, OS1-128) driving through
indoor/outdoor scenes, from a corridor to a car-speed urban drive.

Writes real bags (via :mod:`slam.io.bag_writer`) plus TUM ground truth; the data of the
demo and of every end-to-end test.
"""

from slam.sim.cache import SIM_VERSION, cache_root, ensure_sequence
from slam.sim.lidar import LidarModel, ScanTruth, simulate_scan, simulate_scan_truth
from slam.sim.registry import SCENES
from slam.sim.scene import Pedestrian, Scene
from slam.sim.sensors import DEFAULT_SENSOR, SENSORS, SensorSpec, get_sensor
from slam.sim.simulate import (
    SimResult,
    effective_model,
    iter_scans,
    load_result,
    make_scene,
    simulate,
)

__all__ = [
    "DEFAULT_SENSOR",
    "SCENES",
    "SENSORS",
    "SIM_VERSION",
    "LidarModel",
    "Pedestrian",
    "Scene",
    "ScanTruth",
    "SensorSpec",
    "SimResult",
    "cache_root",
    "effective_model",
    "ensure_sequence",
    "get_sensor",
    "iter_scans",
    "load_result",
    "make_scene",
    "simulate",
    "simulate_scan",
    "simulate_scan_truth",
]
