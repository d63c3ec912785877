"""Warm-up: load (or, on the very first run, compile) the numba kernels a recipe uses before
the first real frame is timed, by running a throwaway front end over a few synthetic scans.

Without it the first frame carries every kernel's load from the on-disk cache (or its
compilation, with an empty cache) and is 10-100x slower than the next ones. The synthetic
scans take both of the pipeline's paths: a driver with ring and time fields (int16 rings, as
the bag readers give), and a KITTI-style cloud without them, its rings and times filled from
the beam layout as ``Pipeline`` does (``slam.sensor``). Nothing of the throwaway front end
is kept; the caller's front end, map and state are untouched.

Measured (``benchmarks/bench_frontends.py --first-frame [--cold]``, default recipe, fresh
processes, machine under load 16-22 on 2 cores, wall / CPU ms): warm numba cache, corridor
first frame 1268 / 429 -> 108 / 38 with the warm-up (which takes 2.1 s / 0.63 s CPU), urban
HDL-64 2074 / 314 -> 1585 / 257 (warm-up 4.8 s / 0.72 s CPU); empty cache (first run), urban
HDL-64: the first frame compiles for 41.9 s CPU (then 2.4 s and 0.5 s on frames 2 and 3),
with the warm-up the warm-up takes 55 s CPU (both scan paths) and frame 1 201 ms CPU.
Without the start-in-motion search (``without_start_search``) the warm-up of
``improved_floam_loop`` with a warm cache takes 0.25-0.39 s CPU instead of 1.09-1.28 s.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from slam.errors import SlamError
from slam.types import Scan

log = logging.getLogger(__name__)

# 16 beams over -15..+15 deg (a VLP-16), 600 columns: 9.6k points per scan
WARM_BEAMS = 16
WARM_COLUMNS = 600
WARM_FRAMES = 3  # the first frame builds the map, the next ones register against it


def _box_ranges(dirs: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(N,) distance (m) along unit rays dirs (N, 3) from origins (N, 3) to the inside of a
    24 x 14 x 4 m room with two 1 m pillars (what gives LOAM edges and GICP a fix)."""
    lo = np.array([-12.0, -7.0, -1.5])
    hi = np.array([12.0, 7.0, 2.5])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(dirs > 0, (hi - origin) / dirs, np.inf)
        t_lo = np.where(dirs < 0, (lo - origin) / dirs, np.inf)
    t = np.minimum(t_hi, t_lo).min(axis=1)
    for cx, cy in ((4.0, 2.0), (-5.0, -3.0)):  # pillars: axis-aligned 1 x 1 m boxes
        b_lo = np.array([cx - 0.5, cy - 0.5, -1.5]) - origin
        b_hi = np.array([cx + 0.5, cy + 0.5, 2.5]) - origin
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = b_lo / dirs, b_hi / dirs
        near = np.nanmax(np.minimum(t1, t2), axis=1)
        far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (near <= far) & (near > 0)
        t = np.where(hit, np.minimum(t, near), t)
    return t


def synthetic_scans(
    frames: int = WARM_FRAMES, beams: int = WARM_BEAMS, columns: int = WARM_COLUMNS
) -> list[Scan]:
    """Scans of a spinning lidar moving at 2 m/s along x in a room (0.2 m per 0.1 s sweep,
    each point seen from where the sensor was at its time): xyz float64, stored beam by beam
    in firing order from the seam, intensity float32, ring int16, time float64 (s from the
    sweep start)."""
    el = np.radians(np.linspace(-15.0, 15.0, beams))
    az = np.linspace(0.0, 2 * np.pi, columns, endpoint=False)
    e, a = np.meshgrid(el, az, indexing="ij")  # (beams, columns): beam by beam
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    ring = np.repeat(np.arange(beams, dtype=np.int16), columns)
    t = np.tile(az / (2 * np.pi) * 0.1, beams)
    rng = np.random.default_rng(0)
    scans = []
    for f in range(frames):
        origin = np.zeros((len(dirs), 3))
        origin[:, 0] = 0.2 * f + 2.0 * t  # the sensor's position when each point was seen
        r = _box_ranges(dirs, origin) + rng.normal(0.0, 0.005, len(dirs))
        xyz = dirs * r[:, None]
        intensity = rng.uniform(0, 100, len(xyz)).astype(np.float32)
        scans.append(Scan(0.1 * f, xyz, intensity, ring.copy(), t.copy(), index=f))
    return scans


def without_start_search(frontend_section: dict[str, Any]) -> dict[str, Any]:
    """``frontend_section`` with the start-in-motion search off (``start_max_speed`` 0) where
    the front end has one. The search registers the second scan from every speed guess
    (0.45 s CPU per warm-up pass with the default 9 guesses, 0.04 s without); it calls the
    same kernels as any registration, so the warm-up loads the same kernels without it
    (checked with NUMBA_DEBUG_CACHE: 20 kernels either way)."""
    import dataclasses

    from slam import plugins

    name = frontend_section.get("name") if isinstance(frontend_section, dict) else None
    if not name:
        return frontend_section
    cls = plugins.load("slam.frontends", name)
    config_cls = getattr(cls, "Config", None)
    if config_cls is None or not dataclasses.is_dataclass(config_cls):
        return frontend_section
    if "start_max_speed" not in {f.name for f in dataclasses.fields(config_cls)}:
        return frontend_section
    return {**frontend_section, "start_max_speed": 0.0}


def warm_up(frontend_section: Any) -> float:
    """Run a throwaway front end built from ``frontend_section`` (the config's frontend
    section, as ``Pipeline`` instantiates it, start search off: ``without_start_search``)
    over the synthetic scans, with and without ring/time fields; returns the seconds it
    took. Errors of the synthetic data (a recipe that rejects it) are logged, never raised:
    the warm-up only saves time."""
    from slam import plugins
    from slam.sensor.beam_table import estimate_beams

    t0 = time.perf_counter()
    scans = synthetic_scans()
    try:
        frontend_section = without_start_search(frontend_section)
        fe = plugins.instantiate("slam.frontends", frontend_section, "frontend")
        for scan in scans:
            fe.process(scan)
        # a driver without ring and time: both from the beam layout, as Pipeline fills them
        beams = estimate_beams([s.xyz for s in scans])
        fe = plugins.instantiate("slam.frontends", frontend_section, "frontend")
        for s in scans:
            ring, t = beams.fill(s.xyz, 0.1, ring=True, time=bool(beams.layout))
            fe.process(Scan(s.stamp, s.xyz, s.intensity, ring, t, index=s.index))
    except (SlamError, ValueError, IndexError) as exc:  # pragma: no cover - recipe-dependent
        log.info("warm-up stopped early: %s", exc)
    return time.perf_counter() - t0
