"""Factor-graph LiDAR SLAM: plugin front ends, GTSAM back ends, Scan Context loops."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("pyslam-graph")
except PackageNotFoundError:  # a source tree on sys.path without an install
    __version__ = "0.2.0"
