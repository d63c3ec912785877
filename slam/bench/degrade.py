"""Damaged inputs made from a good bag: what a misconfigured or failing driver and recorder
give (no ring/time fields, jittered, reordered or missing stamps, clock steps, empty, partial
or NaN clouds, a truncated file), with the association to the true stamps to judge a run."""

from __future__ import annotations

import bz2
from pathlib import Path

import numpy as np

from slam.io.carmen import open_text
from slam.mapping.grid2d import compose2d, inverse2d

GAP_AT = 150  # the first message of gap20's 2 s stall (a third into shorter bags)
JUMP_AT = 200  # where clockback's clock steps back, glitch's stamp jumps (or half-way)
VARIANTS = (
    "strip", "jitter", "drop5", "gap20", "swap", "reversed", "zerostamps", "clockback",
    "glitch", "empty3", "partial1", "nan30",
)  # fmt: skip


def _degrade(scans: list, variant: str, rng, true: dict[int, float]) -> tuple[list, str]:
    """The scans as ``variant`` damages them (in place where it can) and the cloud layout
    to write them with; ``true`` (id(scan) -> true stamp) gains the scans it creates."""
    gap_at, jump_at = min(GAP_AT, len(scans) // 3), min(JUMP_AT, len(scans) // 2)
    if variant == "strip":
        return scans, "xyzi"
    if variant == "jitter":
        for s in scans:
            s.stamp = float(s.stamp) + float(rng.uniform(-0.02, 0.02))
    elif variant == "drop5":
        scans = [s for i, s in enumerate(scans) if i % 5 != 4]
    elif variant == "gap20":  # the driver or the recorder stalled for 2 s
        scans = [s for i, s in enumerate(scans) if not gap_at <= i < gap_at + 20]
    elif variant == "swap":
        for k in range(0, len(scans) - 1, 10):
            scans[k], scans[k + 1] = scans[k + 1], scans[k]
    elif variant == "reversed":
        t0, t1 = scans[0].stamp, scans[-1].stamp
        for s in scans:
            s.stamp = t0 + (t1 - float(s.stamp))
    elif variant == "zerostamps":  # a driver that never sets header.stamp
        for s in scans:
            s.stamp = 0.0
    elif variant == "clockback":  # the sensor clock steps back 2.55 s (a PTP correction)
        for s in scans[jump_at:]:
            s.stamp = float(s.stamp) - 2.55  # not onto the earlier stamps: a unique match
    elif variant == "glitch":  # one header stamp 100 s in the future
        scans[jump_at].stamp = float(scans[jump_at].stamp) + 100.0
    elif variant == "empty3":  # the driver starting up: three clouds without a point
        for s in scans[:3]:
            s.xyz, s.intensity, s.ring, s.time = (
                np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.int16), np.zeros(0)
            )  # fmt: skip
    elif variant == "partial1":  # the first cloud holds only the sweep's last 36 degrees
        s = scans[0]
        az = np.arctan2(s.xyz[:, 1], s.xyz[:, 0])
        scans[0] = s.select(az > np.pi * 0.8)
        true[id(scans[0])] = true[id(s)]
    elif variant == "nan30":  # an organised driver: 30 % of the points are NaN (no return)
        for s in scans:
            s.xyz = s.xyz.copy()
            s.xyz[rng.random(len(s)) < 0.3] = np.nan
    else:
        raise ValueError(variant)
    return scans, "velodyne"


def rewrite_bag(src_bag: Path, out: Path, variant: str, seed: int = 0) -> tuple[Path, Path]:
    """The bag ``src_bag`` rewritten as a ``variant`` (one of :data:`VARIANTS`), and a .npy
    of (header stamp, true stamp, record time) of its messages (the association with the
    ground truth, whichever clock the run stamps with)."""
    from slam.io.source import open_source
    from slam.types import Scan

    scans = [s for s in open_source(src_bag) if isinstance(s, Scan)]
    rng = np.random.default_rng(seed)
    true = {id(s): float(s.stamp) for s in scans}
    t_sorted = sorted(true.values())
    scans, layout = _degrade(scans, variant, rng, true)
    # the record time: when the recorder got the message (50-60 ms after its true stamp)
    record = np.array(t_sorted[: len(scans)]) + 0.05 + rng.uniform(0.0, 0.01, len(scans))
    if variant in ("drop5", "gap20"):
        record = np.array(sorted(true[id(s)] for s in scans)) + 0.05
    stamp_map = out.with_suffix(".stamps.npy")
    np.save(
        stamp_map,
        np.array([(float(s.stamp), true[id(s)], r) for s, r in zip(scans, record, strict=True)]),
    )
    return _write_in_record_order(out, scans, layout, record), stamp_map


def _write_in_record_order(out: Path, scans: list, layout: str, record: np.ndarray) -> Path:
    """The scans as a ROS1 bag in the given order: header stamp ``scan.stamp``, record time
    ``record`` (s; the playback order)."""
    from slam.io.bag_writer import POINTCLOUD2, BagWriter
    from slam.io.pointcloud2 import encode_pointcloud2

    with BagWriter(out, "ros1", overwrite=True) as bag:
        bag.add_topic("/velodyne_points", POINTCLOUD2)
        for scan, t in zip(scans, record, strict=True):
            msg = encode_pointcloud2(scan, bag.typestore, frame_id="velodyne", layout=layout)
            bag.write("/velodyne_points", float(t), msg)
    return out


def truncate_bag(src_bag: Path, out: Path, keep: float = 0.6) -> Path:
    """The first ``keep`` of the bytes of ``src_bag`` (a recording killed: no index)."""
    raw = Path(src_bag).read_bytes()
    out.write_bytes(raw[: int(len(raw) * keep)])
    return out


def true_stamps(stamp_map: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    """The true stamps of a run's trajectory ``stamps`` from ``rewrite_bag``'s map: the
    run stamped with the header clock, the record clock or, having followed a clock step
    (urban-clockback), the true one, whichever column its stamps match best (the nearest
    entry of it; the median distance decides, ties go to the true clock)."""
    best = None
    for col in (1, 0, 2):
        order = np.argsort(stamp_map[:, col], kind="stable")
        ref = stamp_map[order, col]
        k = np.clip(np.searchsorted(ref, stamps), 1, max(len(ref) - 1, 1))
        k -= np.abs(ref[k - 1] - stamps) <= np.abs(ref[k] - stamps)  # the nearest
        err = float(np.median(np.abs(ref[k] - stamps)))
        if best is None or err < best[0]:
            best = (err, stamp_map[order[k], 1])
    return best[1]


def thin_carmen(src: Path, dst: Path, stride: int) -> Path:
    """A copy of the CARMEN log ``src`` whose ``FLASER`` lines keep every ``stride``-th beam
    (a 0.5 deg fan of 360 / 361 beams becomes the 1 deg, 180 / 181-beam scanner of the older
    logs); every other line is copied as it is. Written bz2-compressed to ``dst``."""
    if stride < 1:
        raise ValueError("stride must be >= 1")
    dst.parent.mkdir(parents=True, exist_ok=True)
    with open_text(src) as f, bz2.open(dst, "wt") as g:
        for line in f:
            parts = line.split()
            if len(parts) > 2 and parts[0] == "FLASER":
                n = int(parts[1])
                kept = parts[2 : 2 + n][::stride]
                line = " ".join(["FLASER", str(len(kept)), *kept, *parts[2 + n :]]) + "\n"
            g.write(line)
    return dst


def skew_carmen_odometry(
    src: Path, dst: Path, yaw_scale: float = 0.0, trans_scale: float = 0.0,
    yaw_noise_deg: float = 0.0, seed: int = 0,
) -> Path:  # fmt: skip
    """A copy of the CARMEN log ``src`` whose wheel odometry is worse: every ``FLASER``
    increment's heading change is scaled by ``1 + yaw_scale`` plus ``yaw_noise_deg`` (deg per
    scan, Gaussian; a heading that repeats exactly, a stalled reading, stays so), its
    translation by ``1 + trans_scale`` (the miscalibrated wheel base and radius of an older
    robot); the laser pose keeps its mount on the robot. Other lines are copied. Written
    bz2-compressed to ``dst``."""
    rng = np.random.default_rng(seed)
    dst.parent.mkdir(parents=True, exist_ok=True)
    prev = skewed = None
    with open_text(src) as f, bz2.open(dst, "wt") as g:
        for line in f:
            parts = line.split()
            if len(parts) > 2 and parts[0] == "FLASER":
                n = int(parts[1])
                head = 2 + n
                laser = np.array([float(v) for v in parts[head : head + 3]])
                odom = np.array([float(v) for v in parts[head + 3 : head + 6]])
                if prev is None:
                    skewed = odom.copy()
                else:
                    d = compose2d(inverse2d(prev), odom)
                    d[:2] *= 1.0 + trans_scale
                    if odom[2] != prev[2]:  # a heading that repeats stays stale (a stalled encoder)
                        d[2] = d[2] * (1.0 + yaw_scale) + np.deg2rad(yaw_noise_deg) * rng.normal()
                    skewed = compose2d(skewed, d)
                prev = odom
                new_laser = compose2d(skewed, compose2d(inverse2d(odom), laser))
                vals = [f"{v:.6f}" for v in (*new_laser, *skewed)]
                line = " ".join([*parts[:head], *vals, *parts[head + 6 :]]) + "\n"
            g.write(line)
    return dst
