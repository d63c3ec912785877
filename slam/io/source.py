"""One entry point for every input: ``open_source(path)`` guesses the reader from the path."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol, runtime_checkable

from slam.errors import InputError
from slam.types import Scan

ACCEPTED = (
    "a ROS1 .bag file, a ROS2 bag folder (metadata.yaml with .db3 or .mcap files), "
    "an .mcap file, a KITTI sequence folder (velodyne/*.bin) or a folder of .pcd/.ply files"
)


@runtime_checkable
class ScanSource(Protocol):
    """Scans in time order with ``index`` 0, 1, 2, ...; ``len`` is the message/file count.

    Scans empty after NaN removal are still yielded (length 0): the pipeline decides.
    """

    topic: str | None
    description: str

    def __iter__(self) -> Iterator[Scan]: ...

    def __len__(self) -> int: ...


def open_source(path: str | Path, topic: str | None = None) -> ScanSource:
    """The reader for ``path``: bag (ROS1/ROS2 db3/mcap), KITTI folder or PCD/PLY folder.

    ``topic`` only applies to bags (ignored otherwise). Raises InputError for paths of no
    accepted kind and TopicError when the topic is missing or ambiguous.
    """
    from slam.io.bags import BagSource, is_bag_path
    from slam.io.folders import FolderSource, is_cloud_dir
    from slam.io.kitti import KittiSource, is_kitti_dir

    path = Path(path)
    if not path.exists():
        raise InputError(f"input not found: {path}. Accepted: {ACCEPTED}")
    if is_bag_path(path):
        return BagSource(path, topic)
    if is_kitti_dir(path):
        return KittiSource(path)
    if is_cloud_dir(path):
        return FolderSource(path)
    raise InputError(f"cannot read {path}: expected {ACCEPTED}")
