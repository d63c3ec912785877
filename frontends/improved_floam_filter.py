"""Improved FLOAM's point filter (paper 000, section 2.3): the column stride of scans denser
than the paper's sensor, then the weighted SOR, judged on the cropped scan before deskew.

Neither step reads the motion estimate, so the next scan can be filtered on a worker thread
while the current one registers (``ScanFilter.ahead``); the result is the same either way.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from slam.deferred import Deferred, numba_threads
from slam.features.loam import ring_from_elevation
from slam.odometry.scan_to_map import crop
from slam.preprocess.column_stride import thin_scan
from slam.preprocess.sor import Neighbourhoods, apply_sor, neighbourhoods
from slam.types import Scan

if TYPE_CHECKING:
    from frontends.improved_floam import ImprovedFloamConfig


@dataclass
class Filtered:
    """A scan after the column stride and SOR. raw: the points SOR judged (after the
    stride), with their neighbourhoods ``nbh`` (None: SOR off) and the kept mask ``keep``;
    xyz / rings: the kept points and their rings (None: the driver gave none); stride: the
    column stride applied (None: the scan was not dense enough to try); kept: the rows of
    the cropped scan the stride kept (None: all)."""

    raw: np.ndarray
    keep: np.ndarray
    nbh: Neighbourhoods | None
    xyz: np.ndarray
    rings: np.ndarray | None
    stride: int | None
    kept: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def moved_to(self, xyz: np.ndarray) -> Filtered:
        """The same decisions on ``xyz``: the cropped scan's points after deskew (same rows)."""
        raw = xyz if self.kept is None else xyz[self.kept]
        kept = raw if self.keep.all() else raw[self.keep]
        return Filtered(
            raw, self.keep, self.nbh, kept, self.rings, self.stride, self.kept, self.timings
        )


def filter_scan(scan: Scan, cfg: ImprovedFloamConfig, phase: int) -> Filtered:
    """The column stride (``phase``: dense scans seen before, its column offset), then SOR
    with the exact range-image k-NN when the scan has rings. Pure: same scan, same answer."""
    raw, ring, stride, kept, timings = scan.xyz, scan.ring, None, None, {}
    if cfg.max_scan_points and len(raw) > cfg.max_scan_points:
        t = time.perf_counter()
        if ring is None:
            ring = ring_from_elevation(raw, cfg.features.n_beams, cfg.features.fov_deg)
        kept, stride = thin_scan(raw, ring, cfg.max_scan_points, cfg.min_ring_columns, phase)
        if kept is not None:
            raw, ring = raw[kept], np.asarray(ring)[kept]
        timings["stride_ms"] = (time.perf_counter() - t) * 1e3
    t = time.perf_counter()
    nbh = neighbourhoods(raw, cfg.sor.k, ring=ring) if cfg.sor.enabled else None
    keep = apply_sor(raw, cfg.sor, nbh)
    xyz, rings = raw, ring
    if not keep.all():
        xyz = raw[keep]
        rings = None if rings is None else rings[keep]
    timings["sor_ms"] = (time.perf_counter() - t) * 1e3
    return Filtered(raw, keep, nbh, xyz, rings, stride, kept, timings)


@dataclass
class _Entry:
    scan: Scan
    phase: int
    filtered: Filtered | None = None


class ScanFilter:
    """Filters each scan once, in stream order: ``ahead(scan)`` on a worker thread for the
    next scan, ``get(scan, work)`` when the scan is processed (inline if it was not sent
    ahead). The stride's phase is given out in that order, so the answers do not depend on
    the thread's timing."""

    def __init__(self, cfg: ImprovedFloamConfig, threaded: bool = True):
        self.cfg = cfg
        self._job = Deferred(threaded, "scan-filter")
        self._entries: list[_Entry] = []
        self._phase = 0

    def _next_phase(self, n_points: int) -> int:
        phase = self._phase
        if self.cfg.max_scan_points and n_points > self.cfg.max_scan_points:
            self._phase += 1  # the column offset advances once per dense scan
        return phase

    def ahead(self, scan: Scan) -> None:
        """Start filtering ``scan``, the one after the scan in hand."""
        c = self.cfg
        work = crop(scan, c.min_range, c.max_range)
        entry = _Entry(scan, self._next_phase(len(work)))
        self._entries = [*self._entries[-1:], entry]  # the scan in hand and this one

        def job() -> None:
            with numba_threads(1):  # the other threads register and map meanwhile
                entry.filtered = filter_scan(work, self.cfg, entry.phase)

        self._job.submit(job)

    def get(self, scan: Scan, work: Scan) -> tuple[Filtered, float]:
        """The filter of ``scan`` (``work``: its cropped points) and the seconds waited."""
        for entry in self._entries:
            if entry.scan is scan:
                waited = self._job.wait() if entry.filtered is None else 0.0
                return entry.filtered, waited
        self._entries = []
        return filter_scan(work, self.cfg, self._next_phase(len(work))), 0.0

    def close(self) -> None:
        self._job.close()
