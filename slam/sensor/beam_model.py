"""The beam model of a spinning lidar: its elevation table and the ring and per-point time it
fills into every scan (``BeamModel.fill``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import InputError
from slam.sensor.layout import elevation_deg, forward_from_azimuth, layout_rings_polar, layout_seam


@dataclass(frozen=True)
class BeamModel:
    """Beam elevation table of a spinning lidar and what depends on it.

    elevations_deg: (B,) ascending beam elevations (deg) seen from the sensor origin, ring r
    = elevations_deg[r]. layout: True when the clouds are stored beam by beam (``ring_of``
    then reads the rings from the point order); seam_rad: the azimuth (rad) where their
    turns begin. max_range: 99th percentile of the ranges (m)
    of the scans it was estimated from (e.g. Scan Context's radius). source: "ring field",
    "point layout", "column order" or "elevation histogram". column_rings: for clouds stored
    column by column with B points per column, the ring of position i % B (None otherwise).
    """

    elevations_deg: np.ndarray
    layout: bool = False
    seam_rad: float | None = None
    max_range: float = 0.0
    source: str = "elevation histogram"
    column_rings: np.ndarray | None = None  # column order: (B,) ring of each position

    @property
    def n_beams(self) -> int:
        return int(len(self.elevations_deg))

    @property
    def fov_deg(self) -> tuple[float, float]:
        """(lowest, highest) beam elevation (deg)."""
        return float(self.elevations_deg[0]), float(self.elevations_deg[-1])

    @property
    def vertical_resolution_deg(self) -> float:
        """Median angle (deg) between adjacent beams (0 for a single beam)."""
        if self.n_beams < 2:
            return 0.0
        return float(np.median(np.diff(self.elevations_deg)))

    def ring_of(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) int16 beam index of each point (0 = lowest). Stored beam by beam with this
        model's beam count: the order's azimuth turns; otherwise the nearest beam elevation.
        Points without an azimuth (at the origin, range <= 1 mm, or not finite: drivers
        write (0, 0, 0) for a missing return) do not count for the layout; they get the
        nearest beam elevation."""
        return self.fill(xyz, 0.0, time=False)[0]

    def time_of(self, xyz: np.ndarray, period_s: float) -> np.ndarray | None:
        """(N,) per-point time (s from the sweep start, in [0, period_s)) of a beam-by-beam
        cloud without a time field, or None when the cloud carries no usable order.

        Assumes each beam's points are stored in firing order and its sweep begins at the
        seam (true for organised Ouster clouds and the simulator's KITTI-style HDL-64E):
        t = (azimuth advanced from the seam) / (2 pi) * period_s.
        """
        return self.fill(xyz, period_s, ring=False)[1]

    def fill(
        self, xyz: np.ndarray, period_s: float, *, ring: bool = True, time: bool = True
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(ring, time): ``ring_of(xyz)`` and ``time_of(xyz, period_s)`` in one pass, the
        azimuth, elevation and stored-order test computed once (what a driver without ring
        and time fields costs per scan). ring / time False: that one is not computed (None).
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
        want_time = time and self.layout and self.seam_rad is not None and period_s > 0
        if not (ring or want_time):
            return None, None
        elev = elevation_deg(xyz) if ring else None
        ring_out = time_out = None
        if self.layout and len(xyz):
            az = np.arctan2(xyz[:, 1], xyz[:, 0])
            valid = np.einsum("ij,ij->i", xyz, xyz) > 1e-6  # False for NaN too
            every = bool(valid.all())
            az_v = az if every else az[valid]
            rho = np.hypot(xyz[:, 0], xyz[:, 1])
            fa = forward_from_azimuth(az_v, rho if every else rho[valid])
            if ring and fa is not None:
                elev_v = elev if every else elev[valid]
                seam = self.seam_rad
                if seam is None:
                    seam = layout_seam(xyz if every else xyz[valid])
                r = None if seam is None else layout_rings_polar(az_v, elev_v, seam, fa)
                if r is not None and int(r.max()) + 1 == self.n_beams:
                    if every:
                        ring_out = r
                    else:
                        ring_out = self._nearest_beam(elev)
                        ring_out[valid] = r
            if want_time and fa is not None:
                phase = (fa[1] * (az - self.seam_rad)) % (2 * np.pi)
                time_out = phase / (2 * np.pi) * period_s
        if ring and ring_out is None and self.column_rings is not None:
            b = len(self.column_rings)
            if len(xyz) % b == 0:
                ring_out = np.tile(self.column_rings, len(xyz) // b)
        if ring and ring_out is None:
            ring_out = self._nearest_beam(elev)
        return ring_out, time_out

    def _nearest_beam(self, elev: np.ndarray) -> np.ndarray:
        """(N,) int16 ring of the nearest beam elevation to each elevation (deg)."""
        mid = 0.5 * (self.elevations_deg[1:] + self.elevations_deg[:-1])
        return np.searchsorted(mid, elev).astype(np.int16)

    def describe(self) -> str:
        """One line for the log, e.g. 'inferred 64 beams, +2.8..-23.6 deg, ...'."""
        lo, hi = self.fov_deg
        verb = "read" if self.source == "ring field" else "inferred"
        if self.n_beams == 1:  # a 2D laser: no vertical layout to speak of
            return f"planar scanner (one beam), 99 % of returns within {self.max_range:.0f} m"
        return (
            f"{verb} {self.n_beams} beams, {hi:+.1f}..{lo:+.1f} deg "
            f"(median spacing {self.vertical_resolution_deg:.2f} deg, from the {self.source}), "
            f"99 % of returns within {self.max_range:.0f} m"
        )
