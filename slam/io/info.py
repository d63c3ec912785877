"""``slam info``: what an input holds (topics, types, counts, rates, point-cloud fields)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import InputError
from slam.io.pointcloud2 import POINTFIELD_NAMES, pointcloud2_time_field
from slam.types import Scan


def _rate_hz(stamps_ns: list[int]) -> float | None:
    """Mean message rate (Hz) from record times, None with fewer than two messages."""
    if len(stamps_ns) < 2:
        return None
    span = (max(stamps_ns) - min(stamps_ns)) * 1e-9
    return (len(stamps_ns) - 1) / span if span > 0 else None


def _cloud_info(msg: Any) -> dict[str, Any]:
    tf = pointcloud2_time_field(msg)
    return {
        "fields": [
            {
                "name": f.name,
                "datatype": POINTFIELD_NAMES.get(int(f.datatype), str(f.datatype)),
                "offset": int(f.offset),
                "count": int(f.count),
            }
            for f in msg.fields
        ],
        "points": int(msg.height) * int(msg.width),
        "height": int(msg.height),
        "width": int(msg.width),
        "point_step": int(msg.point_step),
        "is_bigendian": bool(msg.is_bigendian),
        "frame_id": str(msg.header.frame_id),
        "time_field": None if tf is None else tf.name,
        "time_unit": None if tf is None else tf.unit,
        "time_absolute": None if tf is None else tf.absolute,
    }


def describe_bag(path: str | Path) -> dict[str, Any]:
    """Summary of a bag: kind, duration (s), message count and one entry per topic.

    ``topics`` maps each name to type, count, rate_hz (from record times); PointCloud2 topics
    also get, from their first message, ``fields`` (name/datatype/offset/count), ``points``,
    ``point_step``, ``frame_id`` and the detected ``time_field``/``time_unit``/``time_absolute``.
    Reads every record once but deserialises only those first clouds.
    """
    from slam.io.bags import _sequential_reader

    path = Path(path)
    try:
        return _describe_indexed(path)
    except InputError:
        seq = _sequential_reader(path) if path.exists() else None
        if seq is None:
            raise
        return _describe_sequential(path, seq)


def _describe_indexed(path: Path) -> dict[str, Any]:
    """:func:`describe_bag` through rosbags (a bag with its index)."""
    from slam.io.bags import POINTCLOUD2, _bag_kind, list_topics, open_reader

    with open_reader(path) as reader:
        topics = list_topics(reader)
        times: dict[str, list[int]] = {t.name: [] for t in topics}
        first: dict[str, Any] = {}
        try:
            for conn, t_ns, raw in reader.messages():
                times[conn.topic].append(t_ns)
                if conn.msgtype == POINTCLOUD2 and conn.topic not in first:
                    first[conn.topic] = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise InputError(f"{path}: cannot read all messages: {exc}") from exc
        count = reader.message_count
    all_ns = [t for ts in times.values() for t in ts]
    start = min(all_ns) * 1e-9 if all_ns else None
    duration = (max(all_ns) - min(all_ns)) * 1e-9 if all_ns else 0.0
    out_topics: dict[str, dict[str, Any]] = {}
    for t in topics:
        entry: dict[str, Any] = {"type": t.msgtype, "count": t.count}
        entry["rate_hz"] = _rate_hz(times[t.name])
        if t.name in first:
            try:
                entry.update(_cloud_info(first[t.name]))
            except InputError as exc:
                entry["error"] = str(exc)
        out_topics[t.name] = entry
    return {
        "path": str(path),
        "format": _bag_kind(path),
        "message_count": int(count),
        "start": start,
        "duration": float(duration),
        "topics": out_topics,
    }


def _describe_sequential(path: Path, seq: tuple[Path, Any, Any]) -> dict[str, Any]:
    """:func:`describe_bag` of a bag without a usable index (a ROS1 bag cut short, a killed
    recording's ``.bag.active``, an MCAP without its end), read record by record as
    ``slam run`` reads it: every complete message, and a note saying so."""
    from slam.io.bags import POINTCLOUD2, _bag_kind

    data_file, read_messages, deserialize = seq
    times: dict[str, list[int]] = {}
    types: dict[str, str] = {}
    first: dict[str, Any] = {}
    try:
        for topic, msgtype, t_ns, raw in read_messages(data_file):
            times.setdefault(topic, []).append(int(t_ns))
            types[topic] = msgtype
            if msgtype == POINTCLOUD2 and topic not in first:
                first[topic] = deserialize(raw, msgtype)
    except Exception as exc:  # a damaged record before the cut
        raise InputError(f"{path}: cannot read it record by record: {exc}") from exc
    out_topics: dict[str, dict[str, Any]] = {}
    for name, ts in times.items():
        entry: dict[str, Any] = {"type": types[name], "count": len(ts), "rate_hz": _rate_hz(ts)}
        if name in first:
            try:
                entry.update(_cloud_info(first[name]))
            except InputError as exc:
                entry["error"] = str(exc)
        out_topics[name] = entry
    all_ns = [t for ts in times.values() for t in ts]
    return {
        "path": str(path),
        "format": _bag_kind(path),
        "message_count": len(all_ns),
        "start": min(all_ns) * 1e-9 if all_ns else None,
        "duration": (max(all_ns) - min(all_ns)) * 1e-9 if all_ns else 0.0,
        "topics": out_topics,
        "note": "no usable index (cut short or still recording): read record by record, "
        "every complete message counted",
    }


def _stamps_to_cut(source: Any) -> tuple[Scan | None, np.ndarray]:
    """The first scan of ``source`` and the stamps (s) of all; a log cut short
    (``source.cut``) gives those before the cut."""
    from slam.errors import InputError

    first, stamps = None, []
    try:
        for item in source:
            if isinstance(item, Scan):
                first = item if first is None else first
                stamps.append(item.stamp)
    except InputError:
        if not getattr(source, "cut", ""):
            raise
    return first, np.asarray(stamps, dtype=float)


def describe(path: str | Path) -> dict[str, Any]:
    """Summary of any accepted input (see ``slam.io.source.ACCEPTED``) as a plain dict.

    Bags: see :func:`describe_bag`. KITTI/PCD folders: format, scan count, rate and the
    first scan's point count and attributes.
    """
    from slam.io.bags import is_bag_path
    from slam.io.source import open_source

    path = Path(path)
    if path.exists() and is_bag_path(path):
        return describe_bag(path)
    source = open_source(path)
    if hasattr(source, "stamps"):
        stamps = np.asarray(source.stamps, dtype=float)
        first = next((s for s in source if isinstance(s, Scan)), None)
    else:  # a log (CARMEN) knows its stamps only by reading its scans
        first, stamps = _stamps_to_cut(source)
    rate = None
    if stamps.size > 1 and stamps[-1] > stamps[0]:
        rate = (stamps.size - 1) / (stamps[-1] - stamps[0])
    return {
        "path": str(path),
        "format": source.description,
        "message_count": len(source),
        "start": float(stamps[0]) if stamps.size else None,
        "duration": float(stamps[-1] - stamps[0]) if stamps.size else 0.0,
        "rate_hz": rate,
        "first_scan": None
        if first is None
        else {
            "points": len(first),
            "intensity": first.intensity is not None,
            "ring": first.ring is not None,
            "time": first.time is not None,
        },
    }
