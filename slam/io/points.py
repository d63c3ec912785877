"""Per-point attributes shared by every reader: the one point validator, per-point time
units, ring range, and :func:`assemble_scan` that turns decoded columns into a Scan.

PointCloud2 messages, PCD/PLY files and KITTI .bin files all go through here, so a NaN
coordinate, a coordinate of 3e38 m, a time field in microseconds or a uint16 ring of 40000
are treated the same whatever the container.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.io.skips import ABSURD_POINTS, FrameError
from slam.types import Scan

INTENSITY_NAMES = ("intensity", "reflectivity", "i")
RING_NAMES = ("ring", "channel", "line")
TIME_NAMES = ("time", "t", "timestamp", "offset_time")

# A sweep of a spinning LiDAR lasts ~0.05-0.2 s: the unit of a per-point time field is the
# one (s, ms, us, ns) that puts the field's span nearest this value (log scale).
NOMINAL_SWEEP_S = 0.1
# An offset of the earliest point from the header stamp above this is an unknown epoch
# (time since boot, ...): the header stamp is kept.
MAX_SWEEP_S = 2.0
# Time values above this many seconds are absolute (since the epoch, > ~11 days).
ABSOLUTE_MIN_S = 1.0e6
SCALES = (1.0, 1e-3, 1e-6, 1e-9)
_UNITS = {1.0: "s", 1e-3: "ms", 1e-6: "us", 1e-9: "ns"}
_INT16 = np.iinfo(np.int16)
# A scan is in the sensor frame and no lidar returns from beyond ~2 km: a coordinate above
# this (m) is garbage (float32 max, uninitialised memory), not a return.
MAX_COORD_M = 1.0e4
# More than this fraction of a cloud's finite points beyond MAX_COORD_M: a damaged message.
MAX_ABSURD_FRACTION = 0.5


def finite_mask(*columns: np.ndarray) -> np.ndarray:
    """Rows where every column is finite (a scan's points: ``point_mask``).

    Each column is (N,) or (N, k); (N, 3) xyz or three (N,) x, y, z columns give the same
    mask (per-column is ~4x faster on structured records than ``isfinite(xyz).all(1)``).
    """
    keep: np.ndarray | None = None
    for col in columns:
        ok = np.isfinite(col)
        if ok.ndim > 1:
            ok = ok.all(axis=tuple(range(1, ok.ndim)))
        if keep is None:
            keep = ok
        else:
            keep &= ok
    if keep is None:
        raise ValueError("finite_mask needs at least one column")
    return keep


def point_mask(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Rows whose x, y, z (N,) are finite and within +-``MAX_COORD_M`` m: THE validator of
    a scan's points (no return: NaN/inf; garbage: a coordinate far beyond any lidar's
    reach). One comparison per column, about the cost of ``finite_mask``."""
    masks = []
    for col in (x, y, z):
        if col.dtype.kind == "f":
            masks.append(np.abs(col) <= MAX_COORD_M)  # NaN and inf compare False
        else:  # abs() of an integer column's minimum wraps
            masks.append((col <= MAX_COORD_M) & (col >= -MAX_COORD_M))
    keep = masks[0]
    keep &= masks[1]
    keep &= masks[2]
    return keep


def _absurd_points(
    x: np.ndarray, y: np.ndarray, z: np.ndarray, keep: np.ndarray, notes: Notes | None
) -> None:
    """Note points dropped for a coordinate beyond ``MAX_COORD_M``; raise FrameError when
    they are most of the cloud's finite points (a damaged message, not a few stray bytes)."""
    n_kept = int(np.count_nonzero(keep))
    n_finite = int(np.count_nonzero(finite_mask(x, y, z)))
    absurd = n_finite - n_kept
    if not absurd:
        return
    if absurd > MAX_ABSURD_FRACTION * n_finite:
        raise FrameError(
            ABSURD_POINTS,
            f"{absurd} of its {n_finite} points with finite coordinates lie beyond "
            f"{MAX_COORD_M:g} m, where no lidar has returns: damaged data",
        )
    if notes is not None:
        notes.add(
            f"points with a coordinate beyond {MAX_COORD_M:g} m (no lidar's returns: "
            f"damaged data) dropped"
        )


def finite_points(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` as (N, 3) float64 without the rows that hold a NaN or inf."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    keep = finite_mask(xyz)
    return xyz if keep.all() else xyz[keep]


@dataclass(frozen=True)
class TimeField:
    """How a per-point time field was read: name, unit scale to seconds, absolute?"""

    name: str
    scale: float
    absolute: bool

    @property
    def unit(self) -> str:
        return _UNITS.get(self.scale, f"x{self.scale:g} s")

    def describe(self) -> str:
        return f"{self.name} ({self.unit}, {'absolute' if self.absolute else 'relative'})"


def guess_time_unit(name: str, values: np.ndarray, *, integer: bool) -> TimeField:
    """Unit (s, ms, us, ns) and absolute/relative of finite per-point times ``values``.

    The unit is the one whose span (max - min) is nearest a 0.1 s sweep on a log scale,
    for integer and float fields alike (a 0.1 s sweep is 1e5 in us, 1e8 in ns). Without a
    span (one point, or all equal) the magnitude decides for epoch-like values (1.7e18 ns,
    1.7e15 us, 1.7e12 ms), else integers are taken as ns and floats as s. Absolute: the
    earliest time in s is above ``ABSOLUTE_MIN_S``.
    """
    if values.size == 0:
        return TimeField(name, 1e-9 if integer else 1.0, False)
    vmin = float(values.min())
    span = float(values.max()) - vmin
    if span > 0.0 and np.isfinite(span):
        err = [abs(np.log10(span * s / NOMINAL_SWEEP_S)) for s in SCALES]
        scale = SCALES[int(np.argmin(err))]
    elif abs(vmin) > 1e17:
        scale = 1e-9
    elif abs(vmin) > 1e14:
        scale = 1e-6
    elif abs(vmin) > 1e11:
        scale = 1e-3
    else:
        scale = 1e-9 if integer else 1.0
    return TimeField(name, scale, vmin * scale > ABSOLUTE_MIN_S)


def normalise_time(raw: np.ndarray, spec: TimeField, stamp: float) -> tuple[np.ndarray, float]:
    """Per-point times (raw units, finite) -> (s from the earliest point, scan stamp in s).

    The scan's stamp becomes the time of its earliest point (the deskew reference): the
    absolute time itself, or ``stamp`` + the earliest relative time when that offset is
    below ``MAX_SWEEP_S`` (a driver stamping the sweep end with times -0.1..0 s); larger
    relative offsets are an unknown epoch and ``stamp`` is kept.
    """
    t = np.array(raw, dtype=np.float64)  # a copy: callers' buffers stay untouched
    if t.size == 0:
        return t, float(stamp)
    t0 = float(t.min())
    t -= t0
    if spec.scale != 1.0:
        t *= spec.scale
    offset = t0 * spec.scale
    if spec.absolute:
        return t, offset
    if abs(offset) < MAX_SWEEP_S:
        return t, float(stamp) + offset
    return t, float(stamp)


def ring_int16(values: np.ndarray) -> np.ndarray | None:
    """Ring (beam) indices as int16, or None when a value is not an int16 (> 32767 from a
    uint16/uint32 field, negative beyond -32768, non-finite or fractional floats): such a
    field is not a beam index, and wrapping it would mix beams."""
    v = np.asarray(values)
    if v.size == 0:
        return v.astype(np.int16)
    if v.dtype.kind == "f":
        if not finite_mask(v).all() or not np.array_equal(v, np.round(v)):
            return None
    if v.min() < _INT16.min or v.max() > _INT16.max:
        return None
    return v.astype(np.int16)


def pick(names: tuple[str, ...], available: object) -> str | None:
    """The first of ``names`` present in ``available`` (a dict or a set of field names)."""
    for name in names:
        if name in available:  # type: ignore[operator]
            return name
    return None


class Notes:
    """Degradations of an input noted once each (e.g. "field ring dropped: ..."), in order."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def add(self, line: str) -> None:
        if line not in self.lines:
            self.lines.append(line)


def assemble_scan(
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    *,
    stamp: float,
    index: int,
    intensity: np.ndarray | None = None,
    ring: tuple[str, np.ndarray] | None = None,
    time: tuple[str, np.ndarray] | None = None,
    notes: Notes | None = None,
) -> Scan:
    """Decoded columns (N,) -> Scan with valid points only (``point_mask``: finite, within
    ``MAX_COORD_M`` m; see ``slam.types.Scan``).

    Points beyond ``MAX_COORD_M`` are dropped with a line in ``notes``, and FrameError
    (``ABSURD_POINTS``) raised when they are most of the finite points: the readers skip
    such a message. ``ring``/``time`` are (field name, values). A ring that is not int16
    and times that are not finite on the kept points are dropped from the scan, with a line
    in ``notes``; per-point time is converted by :func:`guess_time_unit` (unit from all
    points' finite times) and :func:`normalise_time` (on the kept points).
    """
    keep = point_mask(x, y, z)
    all_ok = bool(keep.all())
    if not all_ok:
        _absurd_points(x, y, z, keep, notes)
    xyz = np.empty((keep.shape[0] if all_ok else int(keep.sum()), 3), dtype=np.float64)
    for k, col in enumerate((x, y, z)):
        xyz[:, k] = col if all_ok else col[keep]

    def kept(col: np.ndarray) -> np.ndarray:
        return col if all_ok else col[keep]

    with np.errstate(over="ignore"):  # float64 intensities beyond float32 become inf
        out_i = None if intensity is None else kept(intensity).astype(np.float32)
    out_r = None
    if ring is not None:
        out_r = ring_int16(kept(ring[1]))
        if out_r is None and notes is not None:
            notes.add(
                f"field {ring[0]!r} holds values that are not int16 beam indices "
                f"(e.g. > 32767): ring dropped"
            )
    out_t = None
    if time is not None:
        name, raw = time
        integer = raw.dtype.kind in "iub"
        every = raw.astype(np.float64)
        values = kept(every)
        if integer or finite_mask(values).all():
            # the unit from every point's time (no-return points too): the span of the
            # whole sweep, even when few points kept a finite coordinate
            known = every if integer else every[finite_mask(every)]
            spec = guess_time_unit(name, known, integer=integer)
            out_t, stamp = normalise_time(values, spec, stamp)
        elif notes is not None:
            notes.add(f"field {name!r} has non-finite per-point times: time dropped")
    return Scan(stamp=float(stamp), xyz=xyz, intensity=out_i, ring=out_r, time=out_t, index=index)
