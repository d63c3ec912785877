"""Factor-graph LiDAR SLAM: plugin front ends, GTSAM back ends, Scan Context loops."""

__version__ = "0.1.0"
