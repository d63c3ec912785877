"""Read scans from ROS bags: ROS1 ``.bag``, ROS2 ``.db3`` and ``.mcap``, via rosbags' AnyReader.

Topic choice: the given topic, else the only PointCloud2 topic, else the only LaserScan
topic; anything else raises TopicError listing the topics. A message that cannot be
deserialised or decoded is yielded as a SkippedMessage (its index, a reason, the detail)
and reading goes on; a bag that cannot be opened, or whose record iterator itself fails
(a truncated file), raises InputError naming the message index, so a caller can stop and
still save what it computed. A ROS1 bag without a usable index (a killed recording,
``.bag.active``, or a file cut short) is read record by record instead
(``slam.io.ros1_unindexed``): every complete message up to the cut, with a note, then
the InputError of the cut.
Scans are stamped with the header stamp or the record time (``BagSource.use_stamps``).
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from slam.errors import InputError, TopicError
from slam.io import mcap_unindexed, ros1_unindexed
from slam.io.pointcloud2 import decode_laserscan, decode_pointcloud2
from slam.io.points import Notes
from slam.io.skips import checked, skip
from slam.io.stamps import with_clock
from slam.types import Scan, SkippedMessage

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
LASERSCAN = "sensor_msgs/msg/LaserScan"
DECODERS: dict[str, Callable[..., Scan]] = {
    POINTCLOUD2: decode_pointcloud2,
    LASERSCAN: lambda msg, *, index, notes: decode_laserscan(msg, index=index),
}


@dataclass(frozen=True)
class TopicSummary:
    """One topic of a bag: name, ROS2-style type name, message count."""

    name: str
    msgtype: str
    count: int


def is_bag_path(path: Path) -> bool:
    """True for a ``.bag`` file, a ``.mcap`` file or a ROS2 bag directory."""
    if path.is_file():
        return path.suffix in (".bag", ".mcap", ".db3") or _is_active(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            p.suffix in (".db3", ".mcap") for p in path.iterdir()
        )
    return False


def _is_active(path: Path) -> bool:
    """A ROS1 recording still open (or killed): ``rosbag record`` writes ``x.bag.active``."""
    return path.name.endswith(".bag.active")


def _sequential_reader(path: Path) -> tuple[Path, Callable[..., Iterator], Any] | None:
    """For a bag rosbags cannot open: (file, record-by-record reader, deserialize) when it
    is a ROS1 bag file or a (folder with one) MCAP file whose end is missing, else None."""
    if _is_ros1_file(path):
        ts = get_typestore(Stores.ROS1_NOETIC)
        return path, ros1_unindexed.read_messages, ts.deserialize_ros1
    files = [path] if path.is_file() else sorted(path.glob("*.mcap")) if path.is_dir() else []
    if len(files) == 1 and mcap_unindexed.is_cut(files[0]):
        ts = get_typestore(Stores.ROS2_HUMBLE)
        return files[0], mcap_unindexed.read_messages, ts.deserialize_cdr
    return None


def _is_ros1_file(path: Path) -> bool:
    try:
        with path.open("rb") as f:
            return path.is_file() and f.read(len(ros1_unindexed.MAGIC)) == ros1_unindexed.MAGIC
    except OSError:
        return False


def _bag_kind(path: Path) -> str:
    if path.suffix == ".bag" or _is_active(path):
        return "ROS1 bag"
    if path.suffix == ".mcap" or any(path.glob("*.mcap")):
        return "ROS2 mcap bag"
    return "ROS2 sqlite3 bag"


def _write_metadata(bagdir: Path, files: list[Path], storage: str) -> None:
    """Write a rosbag2 metadata.yaml (version 5) for storage files that come without one."""
    from rosbags.rosbag2 import storage_mcap, storage_sqlite3

    cls = storage_mcap.McapReader if storage == "mcap" else storage_sqlite3.Sqlite3Reader
    counts: dict[tuple[str, str], int] = {}
    start, end = 2**63 - 1, 0
    for f in files:
        reader = cls(f)
        reader.open()
        try:
            for c in reader.connections:
                key = (c.topic, c.msgtype)
                counts[key] = counts.get(key, 0) + int(c.msgcount)
            if reader.metadata.message_count:
                start = min(start, reader.metadata.start_time)
                end = max(end, reader.metadata.end_time)
        finally:
            reader.close()
    if end == 0:
        start = 0
    duration = max(end - start, 0)
    topics = "".join(
        f"    - topic_metadata:\n        name: {t}\n        type: {m}\n"
        f"        serialization_format: cdr\n        offered_qos_profiles: ''\n"
        f"      message_count: {n}\n"
        for (t, m), n in counts.items()
    )
    names = "".join(f"    - {f.name}\n" for f in files)
    (bagdir / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 5\n"
        f"  storage_identifier: {storage}\n  relative_file_paths:\n{names}"
        f"  duration:\n    nanoseconds: {duration}\n"
        f"  starting_time:\n    nanoseconds_since_epoch: {start}\n"
        f"  message_count: {sum(counts.values())}\n"
        f"  topics_with_message_count:\n{topics if topics else '    []'}\n"
        "  compression_format: ''\n  compression_mode: ''\n"
    )


@contextlib.contextmanager
def _bag_dir(path: Path) -> Iterator[Path]:
    """The path AnyReader can open: ROS2 storage files without metadata.yaml get a temporary one."""
    if path.suffix == ".bag" or (path.is_dir() and (path / "metadata.yaml").is_file()):
        yield path
        return
    if path.is_file() and (path.parent / "metadata.yaml").is_file():
        yield path.parent
        return
    files = [path] if path.is_file() else sorted(path.glob("*.mcap")) or sorted(path.glob("*.db3"))
    if not files:
        raise InputError(f"{path}: no .bag, .db3 or .mcap file found")
    storage = "mcap" if files[0].suffix == ".mcap" else "sqlite3"
    tmp = Path(tempfile.mkdtemp(prefix="slam_bag_"))
    try:
        for f in files:
            (tmp / f.name).symlink_to(f.resolve())
        _write_metadata(tmp, [tmp / f.name for f in files], storage)
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _reindex(path: Path) -> str:
    return f"rosbag reindex {path}" if path.suffix == ".bag" else f"ros2 bag reindex {path}"


@contextlib.contextmanager
def open_reader(path: str | Path) -> Iterator[AnyReader]:
    """An open AnyReader on ``path``; any failure to open becomes an InputError."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"bag not found: {path}")
    try:
        with _bag_dir(path) as bag:
            default = Stores.ROS1_NOETIC if bag.suffix == ".bag" else Stores.ROS2_HUMBLE
            reader = AnyReader([bag], default_typestore=get_typestore(default))
            reader.open()
    except InputError:
        raise
    except Exception as exc:  # rosbags raises many types (ReaderError, struct.error, apsw ...)
        raise InputError(
            f"cannot open {_bag_kind(path)} {path}: {exc or type(exc).__name__} "
            f"(the file may be truncated or corrupt; try `{_reindex(path)}`)"
        ) from exc
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def list_topics(reader: AnyReader) -> list[TopicSummary]:
    """Topics of an open reader, sorted by name."""
    return [
        TopicSummary(name, info.msgtype or "?", int(info.msgcount))
        for name, info in sorted(reader.topics.items())
    ]


def format_topics(topics: list[TopicSummary]) -> str:
    """A multi-line table of topics for error messages."""
    if not topics:
        return "  (no topics)"
    width = max(len(t.name) for t in topics)
    return "\n".join(f"  {t.name:<{width}}  {t.msgtype}  ({t.count} msgs)" for t in topics)


def choose_topic(topics: list[TopicSummary], topic: str | None, where: str) -> TopicSummary:
    """The topic to read (see module doc); TopicError lists the candidates otherwise."""
    if topic is not None:
        for t in topics:
            if t.name == topic:
                if t.msgtype not in DECODERS:
                    raise TopicError(
                        f"topic {topic} in {where} has type {t.msgtype}; supported types are "
                        f"{sorted(DECODERS)}. Topics:\n{format_topics(topics)}"
                    )
                return t
        raise TopicError(f"topic {topic} not found in {where}. Topics:\n{format_topics(topics)}")
    for msgtype in (POINTCLOUD2, LASERSCAN):
        found = [t for t in topics if t.msgtype == msgtype]
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            kind = msgtype.rsplit("/", 1)[-1]
            raise TopicError(
                f"{where} has {len(found)} {kind} topics; choose one with --topic. "
                f"Topics:\n{format_topics(topics)}"
            )
    raise TopicError(
        f"{where} has no sensor_msgs/PointCloud2 or LaserScan topic. Topics:\n"
        f"{format_topics(topics)}"
    )


class BagSource:
    """Scans of one PointCloud2 or LaserScan topic of a bag, in record order.

    Iterating opens the bag anew, so a source can be iterated several times. ``notes``
    collects, once each, the degradations met so far (an optional field dropped, ...).
    ``stamps``: the clock of ``Scan.stamp`` (``slam.io.stamps``): "header" (default),
    "record" (the bag's record time) or "auto"; set with :meth:`use_stamps`.
    """

    stamps: str = "header"
    reorder_window: int = 0  # the reorder buffer behind this source ("auto" judges with it)

    def use_stamps(self, mode: str, reorder_window: int = 0) -> None:
        """Stamp scans with the ``mode`` clock ("auto" | "header" | "record")."""
        self.stamps, self.reorder_window = mode, reorder_window

    def __init__(self, path: str | Path, topic: str | None = None) -> None:
        self.path = Path(path)
        self._notes = Notes()
        # (file, reader, deserialize) of a bag read record by record (no index / no end)
        self._unindexed: tuple[Path, Callable[..., Iterator], Any] | None = None
        try:
            if _is_active(self.path):
                raise InputError(f"{self.path}: a recording that was not closed (no index)")
            with open_reader(self.path) as reader:
                if reader.message_count == 0:
                    raise InputError(f"{self.path} contains no messages")
                self.topics = list_topics(reader)
        except InputError as exc:
            self._unindexed = _sequential_reader(self.path)
            if self._unindexed is None:
                raise
            self.topics = self._read_unindexed(exc)
        chosen = choose_topic(self.topics, topic, str(self.path))
        if chosen.count == 0:
            raise InputError(f"topic {chosen.name} in {self.path} contains no messages")
        self.topic: str | None = chosen.name
        self.msgtype = chosen.msgtype
        self._count = chosen.count
        self.description = (
            f"{_bag_kind(self.path)} {self.path}, topic {chosen.name} "
            f"({chosen.msgtype.rsplit('/', 1)[-1]}, {chosen.count} msgs)"
        )

    def _read_unindexed(self, exc: InputError) -> list[TopicSummary]:
        """The topics of a ROS1 bag rosbags cannot open (no index: a killed recording, a
        file cut short), from reading it record by record; noted once."""
        stats = ros1_unindexed.Stats()
        counts: dict[tuple[str, str], int] = {}
        file, read, _ = self._unindexed
        try:
            for topic, msgtype, _, _ in read(file, stats):
                counts[(topic, msgtype)] = counts.get((topic, msgtype), 0) + 1
        except Exception as err:  # noqa: BLE001 - then the first error is the one to report
            raise InputError(f"{exc} (reading it record by record failed too: {err})") from exc
        if not counts:
            raise InputError(f"{exc} (reading it record by record found no message)") from exc
        cut = f" (the file's {stats.size} bytes end {stats.stop})" if stats.stop else ""
        self._notes.add(
            f"{self.path} has no usable index (a recording that was not closed, or a file cut "
            f"short): read record by record, {sum(counts.values())} messages{cut}"
        )
        return [TopicSummary(t, m, n) for (t, m), n in sorted(counts.items())]

    @property
    def notes(self) -> list[str]:
        return self._notes.lines

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[Scan | SkippedMessage]:
        if self.stamps == "header":
            return (item for item, _ in self._messages())
        where = f"{self.path} (topic {self.topic})"
        return with_clock(
            self._messages(), self.stamps, self.reorder_window, where, self._notes.add
        )

    def _messages(self) -> Iterator[tuple[Scan | SkippedMessage, float]]:
        """(scan or skipped message, record time s) in record order."""
        if self._unindexed is not None:
            yield from self._unindexed_messages()
            return
        decode = DECODERS[self.msgtype]
        with open_reader(self.path) as reader:
            conns = [c for c in reader.connections if c.topic == self.topic]
            messages = reader.messages(connections=conns)
            index = 0
            while True:
                try:
                    item = next(messages, None)
                except Exception as exc:
                    raise self._bad(index, exc) from exc
                if item is None:
                    return
                conn, record_ns, raw = item
                record = record_ns * 1e-9
                where = f"{self.path} message {index} on {self.topic}"
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    scan = decode(msg, index=index, notes=self._notes)
                    n_raw = len(msg.ranges) if self.msgtype == LASERSCAN else msg.height * msg.width
                except Exception as exc:  # any decoding failure costs this message only
                    yield skip(index, exc, where), record
                else:
                    yield checked(scan, int(n_raw), where), record
                index += 1

    def _unindexed_messages(self) -> Iterator[tuple[Scan | SkippedMessage, float]]:
        """The same from a bag read record by record (``slam.io.ros1_unindexed``,
        ``slam.io.mcap_unindexed``)."""
        decode = DECODERS[self.msgtype]
        file, read, deserialize = self._unindexed
        index = 0
        stats = ros1_unindexed.Stats()
        for topic, msgtype, record_ns, raw in read(file, stats):
            if topic != self.topic:
                continue
            where = f"{self.path} message {index} on {self.topic}"
            try:
                msg = deserialize(raw, msgtype)
                scan = decode(msg, index=index, notes=self._notes)
                n_raw = len(msg.ranges) if self.msgtype == LASERSCAN else msg.height * msg.width
            except Exception as exc:  # any decoding failure costs this message only
                yield skip(index, exc, where), record_ns * 1e-9
            else:
                yield checked(scan, int(n_raw), where), record_ns * 1e-9
            index += 1
        if stats.stop:  # what a truncated indexed bag gives too: the caller keeps the rest
            raise InputError(
                f"{self.path} is cut short: read error at its end, byte {stats.size} "
                f"({stats.stop}; a copy that did not finish, a recording that was killed): "
                f"the {index} messages on {self.topic} before the cut were read"
            )

    def _bad(self, index: int, exc: Exception) -> InputError:
        return InputError(
            f"{self.path}: cannot read message {index} on {self.topic}: "
            f"{exc or type(exc).__name__} (the bag may be truncated or corrupt)"
        )


def first_message(reader: AnyReader, topic: str) -> Any | None:
    """The first deserialised message on ``topic`` of an open reader (None if it has none)."""
    conns = [c for c in reader.connections if c.topic == topic]
    for conn, _, raw in reader.messages(connections=conns):
        return reader.deserialize(raw, conn.msgtype)
    return None
