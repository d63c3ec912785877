"""Bird's-eye-view start of a loop registration: occupancy images of the non-ground points,
FFT cross-correlation over a few yaws around the guess, the best shift within the search
radius (two passes of one street may lie 10-20 m apart; Scan Context gives only a yaw)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.loop.angles import yaw_matrix


def _bev_image(xy: np.ndarray, cell: float, half: int) -> np.ndarray:
    """Binary occupancy (2 half, 2 half) of points ``xy`` (N, 2) on a grid centred at 0."""
    ij = np.floor(xy / cell).astype(np.int64) + half
    ok = np.all((ij >= 0) & (ij < 2 * half), axis=1)
    img = np.zeros((2 * half, 2 * half), dtype=np.float64)
    img[ij[ok, 0], ij[ok, 1]] = 1.0
    return img


def _above_ground(points: np.ndarray) -> np.ndarray:
    """Points more than 0.5 m above the scan's ground level (its 5th height percentile):
    walls, poles, parked cars: what fixes a horizontal position (the ground does not)."""
    z = points[:, 2]
    return points[z > np.percentile(z, 5) + 0.5]


@dataclass(frozen=True)
class BevTarget:
    """The target's bird's-eye-view occupancy spectrum, computed once per verification and
    shared by every yaw and start searched against it. half: image half-size (cells);
    size: FFT size per axis (>= image size + search cells, so the circular correlation equals
    the linear one for every shift searched); reach: which FFT indices are shifts within the
    search radius."""

    spectrum: np.ndarray
    cell: float
    half: int
    size: int
    shifts: np.ndarray
    reach: np.ndarray


def bev_target(target: np.ndarray, search: float, cell: float = 0.5) -> BevTarget:
    """Prepare the target side of :func:`bev_translation` (above-ground points, ``cell`` m)."""
    import scipy.fft  # here: only a verification needs it (0.04 s of every start)

    half = int(np.ceil((search + 30.0) / cell))  # image covers +-(search + 30) m
    reach_cells = int(np.floor(search / cell))
    # zero padding of reach_cells suffices: corr[t] only needs x + t in [-reach, n + reach)
    size = int(scipy.fft.next_fast_len(2 * half + reach_cells + 1, real=True))
    img = _bev_image(_above_ground(target)[:, :2], cell, half)
    shifts = np.fft.fftfreq(size, 1.0 / size).astype(np.int64)  # index -> signed shift
    return BevTarget(
        scipy.fft.rfft2(img, s=(size, size)), cell, half, size, shifts,
        np.abs(shifts) <= reach_cells,
    )  # fmt: skip


def bev_translation(
    target: np.ndarray,
    source: np.ndarray,
    yaw: float,
    search: float,
    cell: float = 0.5,
    yaw_offsets_deg: tuple[float, ...] = (0.0,),
    prepared: BevTarget | None = None,
) -> tuple[np.ndarray, float]:
    """A 4x4 start T_target_source from a bird's-eye-view correlation, and its peak share.

    The above-ground points of both clouds become occupancy images (``cell`` m); for each
    yaw ``yaw + offset`` the rotated source image is cross-correlated with the target's by
    FFT and the best shift within ``search`` m is taken; the yaw and shift of the highest
    peak win (ties: the first offset, the first shift in FFT order; the correlation of two
    binary images is an integer count, rounded so ties do not hinge on FFT round-off).
    peak share: correlation peak / occupied source cells (0-1). ``prepared``: the target's
    :func:`bev_target` for the same search and cell (computed here when None).
    """
    import scipy.fft

    bt = prepared if prepared is not None else bev_target(target, search, cell)
    src = _above_ground(source)
    n, half, cell = bt.size, bt.half, bt.cell
    outside = ~bt.reach
    best = (-1.0, 0.0, 0, 0, 1.0)
    for off in yaw_offsets_deg:
        y = yaw + np.radians(off)
        c, s = np.cos(y), np.sin(y)
        xy = src[:, :2] @ np.array([[c, s], [-s, c]])
        img = _bev_image(xy, cell, half)
        occupied = max(float(img.sum()), 1.0)
        # corr[t] = sum_x target[x + t] * source[x]
        spec = bt.spectrum * np.conj(scipy.fft.rfft2(img, s=(n, n)))
        corr = np.rint(scipy.fft.irfft2(spec, s=(n, n)))
        corr[outside, :] = -1.0
        corr[:, outside] = -1.0
        i, j = np.unravel_index(int(np.argmax(corr)), corr.shape)
        if corr[i, j] > best[0]:
            best = (float(corr[i, j]), y, int(bt.shifts[i]), int(bt.shifts[j]), occupied)
    peak, y, di, dj, occupied = best
    return yaw_matrix(y, np.array([di * cell, dj * cell, 0.0])), peak / occupied
