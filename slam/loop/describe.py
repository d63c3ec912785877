"""Keyframe descriptors for the loop search: Scan Context or SC++, on a geometry fixed once
per run (from the first keyframes when on auto), stored in the search database."""

from __future__ import annotations

import logging

import numpy as np

from slam.loop.config import DescriptorConfig, SearchConfig
from slam.loop.scan_context import ScanContextParams, scan_context
from slam.loop.scan_context_pp import (
    CartesianIndex,
    ScanContextPPParams,
    cartesian_context,
    polar_context,
)
from slam.loop.search import ScanContextDatabase
from slam.types import Keyframe

log = logging.getLogger(__name__)


def auto_descriptor_params(clouds: list[np.ndarray], d: DescriptorConfig) -> ScanContextParams:
    """Descriptor geometry from the sensor's first keyframes, so one default fits rooms,
    streets and plazas.

    max_radius: 1.2 x the 99th percentile of the horizontal ranges pooled over ``clouds``,
    rounded up to 5 m, in [10, 80] m (the sensor's reach in this scene: a corridor gets
    ~15-25 m, a street 60-75 m, an open plaza the outdoor Scan Context's 80 m; pooled,
    because one scan can stand in a short street). lidar_height: median over the keyframes
    of the ground's depth below the sensor (2nd percentile of z), >= 0. Fixed for the whole
    run so that all descriptors share one grid.
    """
    pts = [np.asarray(c, dtype=float)[:, :3] for c in clouds if len(c) >= 10]
    if not pts:
        radius, height = 80.0, 2.0
    else:
        r = np.concatenate([np.hypot(c[:, 0], c[:, 1]) for c in pts])
        r99 = float(np.percentile(r, 99))
        radius = float(np.clip(5.0 * np.ceil(1.2 * r99 / 5.0), 10.0, 80.0))
        height = max(0.0, float(np.median([-np.percentile(c[:, 2], 2) for c in pts])))
    if d.max_radius > 0:
        radius = d.max_radius
    if d.lidar_height >= 0:
        height = d.lidar_height
    return ScanContextParams(d.rings, d.sectors, radius, height)


class Describer:
    """Describes each keyframe and stores it in ``db``. With the geometry on auto, the first
    auto_keyframes keyframes are buffered, pooled to fix it, then described (stored, never
    queried). SC++ also keeps the Cartesian contexts in ``cc_index``."""

    def __init__(self, d: DescriptorConfig, search: SearchConfig, db: ScanContextDatabase):
        self.cfg, self.search, self.db = d, search, db
        self.sc_params: ScanContextParams | None = None  # fixed after auto_keyframes
        if d.max_radius > 0 and d.lidar_height >= 0:
            self.sc_params = ScanContextParams(d.rings, d.sectors, d.max_radius, d.lidar_height)
        self.cc_index: CartesianIndex | None = None  # SC++ only, once the geometry is fixed
        self._pending: list[Keyframe] = []  # keyframes waiting for the auto geometry

    def add(self, kf: Keyframe) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(polar descriptor, CC or None) of ``kf``, stored; None while buffering."""
        if self.sc_params is not None:
            return self._describe(kf)
        self._pending.append(kf)
        if len(self._pending) >= self.cfg.auto_keyframes:
            self._fix_geometry()
        return None

    def _fix_geometry(self) -> None:
        """Fix the Scan Context geometry from the buffered keyframes and describe them."""
        self.sc_params = auto_descriptor_params([k.cloud for k in self._pending], self.cfg)
        log.info(
            "scan context: max_radius %.0f m, lidar_height %.2f m (auto, %d keyframes)",
            self.sc_params.max_radius, self.sc_params.lidar_height, len(self._pending),
        )  # fmt: skip
        for k in self._pending:
            self._describe(k)
        self._pending = []

    def _pp_params(self) -> ScanContextPPParams:
        d, sc = self.cfg, self.sc_params
        return ScanContextPPParams(
            sc.rings, sc.sectors, sc.max_radius, sc.lidar_height, d.ground_clearance,
            d.cc_rows, d.cc_cols, d.cc_lateral, d.cc_longitudinal,
            d.lateral_shifts, d.longitudinal_shifts,
        )  # fmt: skip

    def _describe(self, kf: Keyframe) -> tuple[np.ndarray, np.ndarray | None]:
        """Scan Context, or SC++'s polar context (non-ground points) and Cartesian context."""
        if self.cfg.kind == "scan_context":
            desc, cc = scan_context(kf.cloud, self.sc_params), None
        else:
            if self.cc_index is None:
                self.cc_index = CartesianIndex(
                    self._pp_params(), self.search.top_k, self.search.rebuild_every
                )
            p = self.cc_index.p
            desc, cc = polar_context(kf.cloud, p), cartesian_context(kf.cloud, p)
            self.cc_index.add(cc)
        self.db.add(kf.id, kf.stamp, desc)
        return desc, cc
