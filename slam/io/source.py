"""One entry point for every input: ``open_source(path)`` guesses the reader from the path."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol, runtime_checkable

from slam.errors import InputError
from slam.types import Scan, SkippedMessage

ACCEPTED = (
    "a ROS1 .bag file, a ROS2 bag folder (metadata.yaml with .db3 or .mcap files), "
    "an .mcap file, a KITTI sequence folder (velodyne/*.bin) or a folder of KITTI .bin scans, "
    "a folder of .pcd/.ply files "
    "or a CARMEN 2D laser log (.clf, .clf.bz2)"
)


@runtime_checkable
class ScanSource(Protocol):
    """One item per message/file in record order, ``index`` 0, 1, 2, ...; ``len`` is the
    message/file count.

    Each item is a Scan, or a SkippedMessage(index, reason, detail) for a message/file that
    cannot become one (corrupt buffer, unknown datatype on x/y/z, empty file, no finite
    point, mostly points beyond ``slam.io.points.MAX_COORD_M``): ``reason`` is a short
    category to count (see ``slam.io.skips``), ``detail`` the full explanation, and
    iteration goes on with the next item. A readable scan is never empty. An unreadable
    OPTIONAL field (intensity, ring, time: unknown datatype, ring
    values beyond int16, non-finite times) is dropped from the scan and the scan kept;
    ``notes`` lists each such degradation once. Only an input that cannot be read at all
    (missing file, bag that cannot be opened, a truncated bag whose record iterator fails)
    raises InputError, from ``__init__`` or from the iteration. A source that has a second
    clock (bags: the record time) also offers ``use_stamps(mode, reorder_window)``
    (``slam.io.stamps``); the pipeline calls it with ``source.stamps``.
    """

    topic: str | None
    description: str
    notes: list[str]

    def __iter__(self) -> Iterator[Scan | SkippedMessage]: ...

    def __len__(self) -> int: ...


def open_source(
    path: str | Path, topic: str | None = None, frame_period: float | None = None
) -> ScanSource:
    """The reader for ``path``: bag (ROS1/ROS2 db3/mcap), KITTI folder, PCD/PLY folder or
    CARMEN log.

    ``topic`` only applies to bags, ``frame_period`` (s between numbered scans,
    ``source.frame_period``; None: its default) to folders (ignored otherwise). Raises
    InputError for paths of no accepted kind and TopicError when the topic is missing or
    ambiguous.
    """
    from slam.io.bags import BagSource, is_bag_path
    from slam.io.carmen import CarmenSource, is_carmen_path
    from slam.io.folders import FolderSource, is_cloud_dir
    from slam.io.kitti import KittiSource, is_kitti_dir

    path = Path(path)
    if not path.exists():
        raise InputError(f"input not found: {path}. Accepted: {ACCEPTED}")
    if is_bag_path(path):
        return BagSource(path, topic)
    if is_carmen_path(path):
        return CarmenSource(path)
    period = {} if frame_period is None else {"frame_period": frame_period}
    if is_kitti_dir(path):
        return KittiSource(path, **period)
    if is_cloud_dir(path):
        return FolderSource(path, **period)
    raise InputError(f"cannot read {path}: expected {ACCEPTED}")
