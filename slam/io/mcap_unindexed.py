"""ROS2 MCAP files without their end (a ``ros2 bag record`` that was killed, a copy cut
short), read record by record: rosbags needs the footer; ``ros2 bag reindex`` needs ROS 2.
Every complete message up to where the file ends, as a reindexed file would give.

Format (MCAP 0): magic ``\\x89MCAP0\\r\\n``, then records of (uint8 opcode, uint64 length,
content): schema (3), channel (4), message (5), chunk (6: schemas, channels and messages,
possibly lz4/zstd compressed); the summary and footer at the end are not needed.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from rosbags.rosbag2.storage_mcap import DECOMPRESSORS

from slam.io.ros1_unindexed import Stats

MAGIC = b"\x89MCAP0\r\n"


def is_cut(path: Path) -> bool:
    """True for an MCAP file that starts as one but does not end with the magic."""
    try:
        with path.open("rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                return False
            f.seek(-len(MAGIC), 2)
            return f.read() != MAGIC
    except OSError:
        return False


def _string(rec: BinaryIO) -> str:
    (n,) = struct.unpack("<I", rec.read(4))
    return rec.read(n).decode()


def _records(src: BinaryIO) -> Iterator[tuple[int, bytes, bool]]:
    """(opcode, content, complete) of each record up to the first incomplete one."""
    while True:
        head = src.read(9)
        if len(head) < 9:
            return
        op, size = struct.unpack("<BQ", head)
        data = src.read(size)
        yield op, data, len(data) == size
        if len(data) < size:
            return


def read_messages(
    path: str | Path, stats: Stats | None = None
) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, msgtype, log time ns, raw CDR bytes) of every complete message of the MCAP
    file ``path``, in file order, without its summary or footer. An uncompressed chunk cut
    short still gives its complete messages; ``stats`` says where it stopped."""
    path = Path(path)
    stats = stats if stats is not None else Stats()
    stats.size = path.stat().st_size
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}

    def parse(op: int, data: bytes) -> tuple[str, str, int, bytes] | None:
        rec = io.BytesIO(data)
        if op == 0x03:
            (sid,) = struct.unpack("<H", rec.read(2))
            schemas[sid] = _string(rec)
        elif op == 0x04:
            cid, sid = struct.unpack("<HH", rec.read(4))
            channels[cid] = (_string(rec), schemas.get(sid, ""))
        elif op == 0x05 and len(data) >= 22:
            cid, _, log_time, _ = struct.unpack("<HIQQ", rec.read(22))
            if cid in channels and channels[cid][1]:
                return (*channels[cid], log_time, data[22:])
        return None

    with path.open("rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise ValueError(f"{path} is not an MCAP file")
        for op, data, complete in _records(f):
            if not complete:
                stats.stop = "inside a record"
            if op == 0x06:
                rec = io.BytesIO(data)
                _, _, raw_size, _ = struct.unpack("<QQQI", rec.read(28))
                compression = _string(rec)
                (n,) = struct.unpack("<Q", rec.read(8))
                inner = rec.read(n)
                if compression:
                    if not complete:  # a cut compressed chunk: its messages are lost
                        return
                    inner = DECOMPRESSORS[compression](inner, raw_size)
                for o, d, whole in _records(io.BytesIO(inner)):
                    if not whole:
                        break
                    msg = parse(o, d)
                    if msg is not None:
                        yield msg
            elif complete:
                if op == 0x02:  # the footer: the file was whole after all
                    break
                msg = parse(op, data)
                if msg is not None:
                    yield msg
            if complete:
                stats.end = f.tell()
    if stats.end < stats.size and stats.stop is None:
        stats.stop = "inside a record"
