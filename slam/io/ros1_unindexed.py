"""ROS1 bags without a usable index, read record by record: a recording that was killed
(``.bag.active``: no index written) or a file cut short (copy or disk full: the index at
the end is gone). rosbags needs the index; ``rosbag reindex`` needs ROS. This reads every
complete message up to where the file ends, the same as a reindexed bag would give.

Format (ROS bag 2.0): ``#ROSBAG V2.0\\n``, then records of (uint32 header length, header
of ``name=value`` fields, uint32 data length, data); chunk records (op 5) hold connection
(op 7) and message (op 2) records, possibly bz2/lz4 compressed.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from rosbags.rosbag1.reader import (
    Header,
    ReaderError,
    RecordType,
    decompressors,
    read_uint32,
)
from rosbags.typesys.msg import normalize_msgtype

MAGIC = b"#ROSBAG V2.0\n"


@dataclass
class Stats:
    """What a sequential read found: where it stopped and why (None: the file's end)."""

    end: int = 0  # bytes of the file read as complete top-level records
    size: int = 0  # bytes of the file
    stop: str | None = None  # e.g. "inside a record"


def _records(src: BinaryIO) -> Iterator[tuple[Header, bytes, bool]]:
    """(header, data, complete) of each record of ``src`` up to the first incomplete one
    (yielded with ``complete`` False when its header was whole, then the end)."""
    while True:
        try:
            header = Header.read(src)
            size = read_uint32(src)
        except ReaderError:
            return
        data = src.read(size)
        yield header, data, len(data) == size
        if len(data) < size:
            return


def read_messages(
    path: str | Path, stats: Stats | None = None
) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, ROS2-style msgtype, record time ns, raw ROS1 bytes) of every complete
    message of the ROS1 bag ``path``, in file order, without its index. An uncompressed
    chunk cut short still gives its complete messages; ``stats`` says where it stopped."""
    path = Path(path)
    stats = stats if stats is not None else Stats()
    stats.size = path.stat().st_size
    conns: dict[int, tuple[str, str]] = {}
    with path.open("rb") as f:
        if f.readline() != MAGIC:
            raise ReaderError(f"{path} is not a ROS bag 2.0 file")
        for header, data, complete in _records(f):
            op = header.get_uint8("op")
            if not complete:
                stats.stop = "inside a record"
            if op == RecordType.CONNECTION and complete:
                _connection(header, data, conns)
            elif op == RecordType.CHUNK:
                compression = header.get_string("compression")
                if compression != "none":
                    if not complete:  # a cut compressed chunk: its messages are lost
                        return
                    data = decompressors[compression](data)
                for h, d, whole in _records(io.BytesIO(data)):
                    o = h.get_uint8("op")
                    if not whole:
                        break
                    if o == RecordType.CONNECTION:
                        _connection(h, d, conns)
                    elif o == RecordType.MSGDATA and h.get_uint32("conn") in conns:
                        yield *conns[h.get_uint32("conn")], h.get_time("time"), d
            elif op == RecordType.MSGDATA and complete:  # a bag written without chunks
                if header.get_uint32("conn") in conns:
                    yield *conns[header.get_uint32("conn")], header.get_time("time"), data
            if complete:
                stats.end = f.tell()
    if stats.end < stats.size and stats.stop is None:
        stats.stop = "inside a record"


def _connection(header: Header, data: bytes, conns: dict[int, tuple[str, str]]) -> None:
    """Note a connection record: its id -> (topic, msgtype)."""
    conn = header.get_uint32("conn")
    topic = header.get_string("topic")
    inner = Header.read(io.BytesIO(len(data).to_bytes(4, "little") + data))
    conns[conn] = (topic, normalize_msgtype(inner.get_string("type")))
