"""CARMEN laser logs (``.clf``, ``.clf.bz2``, ``.log``): the 2D laser recordings of real
robots (Intel Research Lab, FR079, MIT-CSAIL in ``../shared/data/laser2d``).

Each ``FLASER`` line is one front-laser scan::

    FLASER n r_1 .. r_n  x y theta  odom_x odom_y odom_theta  timestamp host logger_timestamp

ranges in metres over a 180 deg fan in front of the robot, starting at -90 deg (the
robot's right); ``x y theta`` is the laser pose and ``odom_*`` the robot's wheel odometry
(m, rad). A scan becomes a :class:`Scan` in the laser frame (x forward, y left, z = 0,
ring 0): readings at the sensor's maximum range (no return) or below ``min_range`` are
dropped; the wheel odometry rides along as ``Scan.odom``. The trajectory files are written
in the convention of the Freiburg relations (Kuemmerle et al. 2009; their evaluator reads
the robot pose and the ipc timestamp of each laser line): the robot's poses, the laser's
mount on the robot (``laser = robot o mount``, the same on every line of a raw log:
FR079's laser sits 4 cm behind the robot's centre, Intel's and MIT-CSAIL's on it) taken
off (``CarmenSource.output_trajectory``). ``ROBOTLASER1`` lines
(``start_angle fov resolution max_range ...``) are read the
same way when a log has no FLASER. Other lines (ODOM, PARAM, comments) are ignored. A
damaged line costs that scan (a :class:`SkippedMessage`), not the run; a compressed log cut
short gives the scans before the cut, then stops as a truncated bag does. Logs whose clock
jumps (Intel: single stamps ~1 s ahead, so the next ones look 631 times out of order) keep
file order: the stamps outside the longest increasing run are interpolated between their
neighbours in it for the run, with a note; the trajectory files carry the log's own stamps
(the ipc timestamp of each laser line, which the relations are given at).
"""

from __future__ import annotations

import bisect
import bz2
import gzip
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.errors import InputError
from slam.io.skips import CORRUPT_MESSAGE, EMPTY_MESSAGE
from slam.types import Scan, SkippedMessage

SUFFIXES = (".clf", ".clf.bz2", ".clf.gz", ".carmen", ".carmen.bz2", ".log.bz2", ".log")
MIN_RANGE = 0.02  # m: below this a reading is a dropout
NO_RETURN_MARGIN = 0.05  # m: readings within this of the log's largest are "no return"
MOUNT_LINES = 200  # laser lines read to find the laser's mount on the robot
MOUNT_TOL_M = 1e-3  # m: lines that disagree on the mount by more have no fixed mount
MOUNT_TOL_RAD = 1e-3  # rad: the same for its heading


@dataclass(frozen=True)
class LaserRecord:
    """One laser line: ranges (m), beam angles (rad, laser frame), laser pose and wheel
    odometry (x, y, theta in m, m, rad), stamp (s), max range (m; inf when unknown)."""

    ranges: np.ndarray
    angles: np.ndarray
    pose: np.ndarray
    odom: np.ndarray
    stamp: float
    max_range: float


def fan_angles(n: int) -> np.ndarray:
    """Beam angles (rad) of an ``n``-beam 180 deg CARMEN fan starting at -90 deg: 181/361
    beams include both ends (1 / 0.5 deg), 180/360 beams step 180/n deg."""
    step = np.pi / (n - 1) if n % 2 == 1 else np.pi / n
    return -np.pi / 2 + step * np.arange(n)


def is_carmen_path(path: Path) -> bool:
    """A file named like a CARMEN log (``*.clf``, ``*.clf.bz2``, ``*.carmen``, ``*.log``)."""
    name = path.name.lower()
    return path.is_file() and any(name.endswith(s) for s in SUFFIXES)


def open_text(path: Path):
    """A text log, read through bz2 / gzip by its suffix (undecodable bytes replaced)."""
    name = path.name.lower()
    if name.endswith(".bz2"):
        return bz2.open(path, "rt", errors="replace")
    if name.endswith(".gz"):
        return gzip.open(path, "rt", errors="replace")
    return open(path, errors="replace")


def parse_flaser(fields: list[str]) -> LaserRecord:
    """``FLASER`` fields (without the tag). Raises ValueError on a damaged line."""
    n = int(fields[0])
    if n <= 1 or len(fields) < n + 8:
        raise ValueError(f"FLASER with {n} ranges has only {len(fields) - 1} values")
    values = np.asarray(fields[1 : n + 8], dtype=np.float64)
    ranges = values[:n]
    pose, odom, stamp = values[n : n + 3], values[n + 3 : n + 6], float(values[n + 6])
    return LaserRecord(ranges, fan_angles(n), pose, odom, stamp, np.inf)


def parse_robotlaser(fields: list[str]) -> LaserRecord:
    """``ROBOTLASER1`` fields (without the tag): type start_angle fov resolution max_range
    accuracy remission_mode n r_1..r_n n_rem rem_1.. laser_x y theta robot_x y theta ...
    timestamp host logger_timestamp."""
    start, _fov, res, max_range = (float(v) for v in fields[1:5])
    n = int(fields[7])
    ranges = np.asarray(fields[8 : 8 + n], dtype=np.float64)
    n_rem = int(fields[8 + n])
    rest = fields[9 + n + n_rem :]
    pose = np.asarray(rest[0:3], dtype=np.float64)
    odom = np.asarray(rest[3:6], dtype=np.float64)
    stamp = float(rest[-3])
    if len(ranges) != n or len(pose) != 3 or len(odom) != 3:
        raise ValueError("ROBOTLASER1 line is cut short")
    return LaserRecord(ranges, start + res * np.arange(n), pose, odom, stamp, max_range)


PARSERS = {"FLASER": parse_flaser, "ROBOTLASER1": parse_robotlaser}


def mount_matrix(mount: np.ndarray) -> np.ndarray:
    """The 4x4 T_robot_laser of a mount (x, y, theta: m, m, rad)."""
    x, y, t = (float(v) for v in mount)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    T[:2, 3] = x, y
    return T


def laser_mount(poses: np.ndarray, odom: np.ndarray) -> np.ndarray:
    """The laser's pose on the robot (x, y, theta: m, m, rad in the robot's frame) from the
    logged laser poses and robot poses (K, 3) of a log's lines: laser = robot o mount.
    Zero (the laser at the robot's pose) when the lines disagree by more than 1 mm /
    1 mrad (the two poses from different sources, e.g. a corrected laser pose beside raw
    odometry, as the simulator writes), when the mount is within that of the robot's
    pose, or when no line gives both."""
    ok = np.all(np.isfinite(poses), axis=1) & np.all(np.isfinite(odom), axis=1)
    if not ok.any():
        return np.zeros(3)
    p, o = poses[ok], odom[ok]
    c, s = np.cos(o[:, 2]), np.sin(o[:, 2])
    d = p[:, :2] - o[:, :2]
    m = np.column_stack(
        [
            c * d[:, 0] + s * d[:, 1],
            -s * d[:, 0] + c * d[:, 1],
            np.angle(np.exp(1j * (p[:, 2] - o[:, 2]))),
        ]
    )
    mount = np.median(m, axis=0)
    spread = np.abs(m - mount).max(axis=0)
    if spread[:2].max() > MOUNT_TOL_M or spread[2] > MOUNT_TOL_RAD:
        return np.zeros(3)
    if np.abs(mount[:2]).max() <= MOUNT_TOL_M and abs(mount[2]) <= MOUNT_TOL_RAD:
        return np.zeros(3)  # within the tolerance of the robot's pose: on it
    return mount


def _stamp_field(rest: str) -> float:
    """The ipc timestamp of a laser line (third field from the end); NaN when damaged."""
    parts = rest.split()
    try:
        return float(parts[-3])
    except (ValueError, IndexError):
        return np.nan


def repaired_stamps(stamps: np.ndarray) -> np.ndarray:
    """``stamps`` made strictly increasing in file order: the longest strictly increasing
    subsequence is kept, every other stamp (a clock jump, a NaN) is interpolated linearly
    in line index between its kept neighbours (extrapolated at the ends)."""
    n = len(stamps)
    if n == 0:
        return stamps.copy()
    idx = np.flatnonzero(np.isfinite(stamps))
    tails: list[float] = []  # patience sorting: smallest tail of each run length
    tail_at: list[int] = []
    parent = np.full(n, -1)
    for i in idx:
        k = bisect.bisect_left(tails, stamps[i])
        if k == len(tails):
            tails.append(stamps[i])
            tail_at.append(i)
        else:
            tails[k], tail_at[k] = stamps[i], i
        parent[i] = tail_at[k - 1] if k else -1
    keep = []
    i = tail_at[-1] if tail_at else -1
    while i >= 0:
        keep.append(i)
        i = parent[i]
    keep = np.array(keep[::-1], dtype=int)
    out = stamps.copy()
    if len(keep) < 2:  # no usable clock: 10 Hz from the first stamp
        start = stamps[keep[0]] if len(keep) else 0.0
        return start + 0.1 * (np.arange(n) - (keep[0] if len(keep) else 0))
    lost = np.setdiff1d(np.arange(n), keep)
    slope = (stamps[keep[-1]] - stamps[keep[0]]) / (keep[-1] - keep[0])
    inside = (lost > keep[0]) & (lost < keep[-1])
    out[lost[inside]] = np.interp(lost[inside], keep, stamps[keep])
    out[lost[~inside]] = stamps[keep[0]] + slope * (lost[~inside] - keep[0])
    return out


def records_to_scan(rec: LaserRecord, index: int, max_range: float) -> Scan:
    """The scan of one record: valid readings as points in the laser frame (z = 0)."""
    limit = min(max_range, rec.max_range) - NO_RETURN_MARGIN
    keep = np.isfinite(rec.ranges) & (rec.ranges > MIN_RANGE) & (rec.ranges < limit)
    r, a = rec.ranges[keep], rec.angles[keep]
    xyz = np.column_stack([r * np.cos(a), r * np.sin(a), np.zeros_like(r)])
    odom = rec.odom if np.all(np.isfinite(rec.odom)) else None
    return Scan(
        stamp=rec.stamp,
        xyz=xyz,
        ring=np.zeros(len(r), dtype=np.int16),
        index=index,
        odom=None if odom is None else odom.copy(),
    )


class CarmenSource:
    """Scans of a CARMEN log in file order (the laser lines of one kind: FLASER, or
    ROBOTLASER1 when the log has no FLASER), in the laser frame. ``mount``: the laser's
    pose on the robot (x, y, theta; :func:`laser_mount` of the first lines). After an
    iteration, ``odometry`` (N, 3) holds the wheel odometry and ``laser_poses`` the logged
    laser poses (x, y, theta) of every laser line read, in order."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"CARMEN log not found: {self.path}")
        self.topic: str | None = None
        self.notes: list[str] = []
        self.cut = ""  # why a compressed log stops early (its file cut short); "" when whole
        self._tag, self._count, self._max_seen = self._survey()
        self.description = f"CARMEN log {self.path} ({self._count} {self._tag} scans)"
        if self.cut:
            self.description += f", cut short after scan {self._count}"
            self._note(
                f"{self.path} is cut short ({self.cut}): the {self._count} {self._tag} scans "
                "before the cut are read"
            )
        if np.any(self.mount != 0):
            x, y, t = self.mount
            self._note(
                f"laser mounted at x {x:+.3f} m, y {y:+.3f} m, {np.degrees(t):+.2f} deg on the "
                "robot: the trajectory files give the robot's poses"
            )
        if self._repaired:
            self._note(
                f"{self._repaired} laser stamps out of order in the log (a clock jump); "
                "those scans are kept in file order, stamped between their neighbours"
            )
        self.odometry = np.zeros((0, 3))
        self.laser_poses = np.zeros((0, 3))

    def _survey(self) -> tuple[str, int, float]:
        """Which laser tag the log holds, how many scans, and its largest reading (the
        sensor's "no return" value when the log has no max-range parameter). A log whose
        compressed stream ends early (a copy cut short) holds the scans before the cut
        (``cut`` says why); iterating it then stops there with an InputError."""
        counts = dict.fromkeys(PARSERS, 0)
        stamps: dict[str, list[float]] = {tag: [] for tag in PARSERS}
        firsts: dict[str, list[str]] = {tag: [] for tag in PARSERS}
        largest = 0.0
        try:
            with open_text(self.path) as fh:
                for line in fh:
                    tag, _, rest = line.partition(" ")
                    if tag in counts:
                        counts[tag] += 1
                        stamps[tag].append(_stamp_field(rest))
                        if counts[tag] <= MOUNT_LINES:
                            firsts[tag].append(rest)
                        if tag == "FLASER" and counts[tag] <= 200:
                            parts = rest.split()
                            try:
                                n = int(parts[0])
                                largest = max(largest, max(float(v) for v in parts[1 : n + 1]))
                            except (ValueError, IndexError):
                                pass
        except (OSError, EOFError) as exc:  # a compressed log cut short: read up to the cut
            if any(counts.values()):
                self.cut = str(exc)
            elif isinstance(exc, EOFError):
                raise InputError(f"{self.path} is cut short before its first scan: {exc}") from exc
            else:
                raise InputError(f"cannot read CARMEN log {self.path}: {exc}") from exc
        except UnicodeError as exc:
            raise InputError(f"cannot read CARMEN log {self.path}: {exc}") from exc
        tag = "FLASER" if counts["FLASER"] else "ROBOTLASER1"
        if counts[tag] == 0:
            raise InputError(
                f"{self.path}: no FLASER or ROBOTLASER1 lines; is it a CARMEN laser log?"
            )
        self.mount = self._mount(PARSERS[tag], firsts[tag])
        raw = np.asarray(stamps[tag], dtype=np.float64)
        self._log_stamps = raw
        self._stamps = repaired_stamps(raw)
        self._repaired = int(np.sum(self._stamps != raw))
        return tag, counts[tag], largest

    @staticmethod
    def _mount(parse, lines: list[str]) -> np.ndarray:
        """:func:`laser_mount` of the given laser lines (damaged ones left out)."""
        poses, odom = [], []
        for rest in lines:
            try:
                rec = parse(rest.split())
            except (ValueError, IndexError):
                continue
            poses.append(rec.pose)
            odom.append(rec.odom)
        return laser_mount(np.asarray(poses).reshape(-1, 3), np.asarray(odom).reshape(-1, 3))

    def __len__(self) -> int:
        return self._count

    def output_stamps(self, stamps: np.ndarray) -> np.ndarray:
        """The log's own stamp of each scan stamped ``stamps`` in the run: a stamp the reader
        repaired (out of order in the log) goes back to the log's, the stamp the Freiburg
        relations and their evaluator match a laser line by (Intel: 787 of 13631 scans, by
        0.6 s median); stamps the reader did not give are returned unchanged."""
        stamps = np.asarray(stamps, dtype=np.float64)
        if not len(self._stamps):
            return stamps.copy()
        k = np.clip(np.searchsorted(self._stamps, stamps), 0, len(self._stamps) - 1)
        hit = self._stamps[k] == stamps
        log = self._log_stamps[k]
        return np.where(hit & np.isfinite(log), log, stamps)

    def robot_poses(self, poses: np.ndarray) -> np.ndarray:
        """The robot's poses (N, 4, 4) of the laser's ``poses``: T_world_robot =
        T_world_laser o mount^-1."""
        return np.asarray(poses, dtype=np.float64) @ np.linalg.inv(mount_matrix(self.mount))

    def output_trajectory(
        self, stamps: np.ndarray, poses: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """A run's trajectory (laser poses at the run's stamps) as the files give it: the
        robot's poses at the log's own stamps, the convention of the Freiburg relations."""
        return self.output_stamps(stamps), self.robot_poses(poses)

    def _note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)

    def __iter__(self) -> Iterator[Scan | SkippedMessage]:
        parse = PARSERS[self._tag]
        # SICK scanners report "no return" as their maximum (80-82 m in these logs)
        max_range = self._max_seen if self._max_seen > 50.0 else np.inf
        odom, poses = [], []
        index = 0
        try:
            with open_text(self.path) as fh:
                for line_no, line in enumerate(fh, start=1):
                    tag, _, rest = line.partition(" ")
                    if tag != self._tag:
                        continue
                    where = f"{self.path}:{line_no}"
                    try:
                        rec = parse(rest.split())
                    except (ValueError, IndexError) as exc:
                        yield SkippedMessage(index, CORRUPT_MESSAGE, f"{where}: {exc}")
                        index += 1
                        continue
                    scan = records_to_scan(rec, index, max_range)
                    if index < len(self._stamps) and np.isfinite(self._stamps[index]):
                        scan.stamp = float(self._stamps[index])
                    odom.append(rec.odom)
                    poses.append(rec.pose)
                    index += 1
                    if len(scan) == 0:
                        yield SkippedMessage(scan.index, EMPTY_MESSAGE, f"{where}: no valid range")
                        continue
                    yield scan
        except (OSError, EOFError) as exc:  # a truncated .bz2: stop like a truncated bag
            raise InputError(f"{self.path} is cut short after {index} scans: {exc}") from exc
        finally:
            self.odometry = np.asarray(odom).reshape(-1, 3)
            self.laser_poses = np.asarray(poses).reshape(-1, 3)
