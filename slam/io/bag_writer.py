"""Write real ROS bags (ROS1 .bag, ROS2 sqlite3 .db3 or mcap directories) with rosbags.

Used by the simulator and the tests, so every reader path is exercised on files that
ROS tools could open too.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from slam.errors import InputError
from slam.io.pointcloud2 import (
    LAYOUTS,
    encode_laserscan,
    encode_pointcloud2,
    stamp_to_sec_nsec,
)
from slam.types import Scan

FORMATS = ("ros1", "ros2", "mcap")
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
LASERSCAN = "sensor_msgs/msg/LaserScan"


class BagWriter:
    """Minimal multi-topic bag writer; a context manager.

    fmt "ros1" writes a ``.bag`` file, "ros2" a directory with a sqlite3 ``.db3`` file,
    "mcap" a ROS2 directory with an ``.mcap`` file. Message record time = stamp given
    to :meth:`write` (s). ``overwrite`` removes an existing target first.
    """

    def __init__(self, path: str | Path, fmt: str = "ros1", *, overwrite: bool = False) -> None:
        if fmt not in FORMATS:
            raise InputError(f"unknown bag format {fmt!r}; choose one of {list(FORMATS)}")
        self.path = Path(path)
        self.fmt = fmt
        if self.path.exists():
            if not overwrite:
                raise InputError(f"{self.path} exists already; remove it or choose another path")
            if self.path.is_dir():
                shutil.rmtree(self.path)
            else:
                self.path.unlink()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            self._writer: Any = Writer(self.path)
            self._serialize = self.typestore.serialize_ros1
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.typestore = get_typestore(Stores.ROS2_HUMBLE)
            self._writer = Writer(self.path, version=8, storage_plugin=plugin)
            self._serialize = self.typestore.serialize_cdr
        self._connections: dict[str, Any] = {}
        self._open = False

    def __enter__(self) -> BagWriter:
        self._writer.open()
        self._open = True
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close()

    def close(self) -> None:
        if self._open:
            self._writer.close()
            self._open = False

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Register ``topic`` with a ROS2-style type name (``sensor_msgs/msg/PointCloud2``)."""
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.typestore
            )

    def write(self, topic: str, stamp: float, msg: Any) -> None:
        """Serialize and write ``msg`` on ``topic`` with record time ``stamp`` (s)."""
        self.add_topic(topic, msg.__msgtype__)
        conn = self._connections[topic]
        sec, nsec = stamp_to_sec_nsec(stamp)
        data = self._serialize(msg, msg.__msgtype__)
        self._writer.write(conn, sec * 1_000_000_000 + nsec, data)


def write_pointcloud_bag(
    path: str | Path,
    scans: Iterable[Scan],
    *,
    topic: str = "/velodyne_points",
    frame_id: str = "velodyne",
    fmt: str = "ros1",
    layout: str = "velodyne",
    overwrite: bool = False,
) -> Path:
    """Write ``scans`` as sensor_msgs/PointCloud2 on ``topic``; header stamp = scan.stamp.

    layout: one of ``LAYOUTS`` (velodyne, ouster, hesai, livox, xyz64). Missing
    intensity/ring/time are written as zeros. Returns the bag path (file or directory).
    """
    if layout not in LAYOUTS:
        raise InputError(f"unknown point layout {layout!r}; choose one of {sorted(LAYOUTS)}")
    with BagWriter(path, fmt, overwrite=overwrite) as bag:
        bag.add_topic(topic, POINTCLOUD2)
        for seq, scan in enumerate(scans):
            msg = encode_pointcloud2(scan, bag.typestore, frame_id=frame_id, layout=layout, seq=seq)
            bag.write(topic, scan.stamp, msg)
    return Path(path)


def write_laserscan_bag(
    path: str | Path,
    stamps: Iterable[float],
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_max: float,
    *,
    range_min: float = 0.0,
    time_increment: float = 0.0,
    scan_time: float = 0.0,
    intensities: np.ndarray | None = None,
    topic: str = "/scan",
    frame_id: str = "laser",
    fmt: str = "ros1",
    overwrite: bool = False,
) -> Path:
    """Write sensor_msgs/LaserScan messages: ``ranges`` (N, B) m, one row per stamp (s).

    Use inf/NaN or a value outside [range_min, range_max] for "no return".
    """
    stamps = np.asarray(list(stamps), dtype=np.float64)
    ranges = np.atleast_2d(np.asarray(ranges, dtype=np.float32))
    if ranges.shape[0] != stamps.shape[0]:
        raise InputError(f"{ranges.shape[0]} range rows for {stamps.shape[0]} stamps")
    if intensities is not None:
        intensities = np.atleast_2d(np.asarray(intensities, dtype=np.float32))
    with BagWriter(path, fmt, overwrite=overwrite) as bag:
        bag.add_topic(topic, LASERSCAN)
        for i, stamp in enumerate(stamps):
            msg = encode_laserscan(
                bag.typestore,
                float(stamp),
                ranges[i],
                angle_min=angle_min,
                angle_increment=angle_increment,
                range_max=range_max,
                range_min=range_min,
                time_increment=time_increment,
                scan_time=scan_time,
                intensities=None if intensities is None else intensities[i],
                frame_id=frame_id,
                seq=i,
            )
            bag.write(topic, float(stamp), msg)
    return Path(path)
