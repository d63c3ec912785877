"""The open-road mode of the feature front ends (floam, LeGO-LOAM): their scatter points.

On an open road the LOAM features run along the road and hold the scan at the pose the map
was made from (``slam.features.scatter``). In the mode, a front end also registers the
points its feature selection left out, off the ground (vegetation, clutter), against a map
of their own, point to point (``feature_icp``, ``two_step``); what moves with the car (the
traffic) enters no map before a second scan confirms it (``slam.mapping.second_sighting``).
improved_floam has its own: its GICP registers the scatter points against its one map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.features.scatter import (
    ALONG_ROAD,
    OpenRoadGate,
    ScatterConfig,
    horizontal_observability,
    scatter_points,
)
from slam.features.thinning import voxel_thin
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.mapping.second_sighting import SecondSighting
from slam.registration.covariances import add_beam_angle_noise, estimate_covariances
from slam.registration.feature_icp import FeatureTarget, MapTreeCache
from slam.registration.ground_plane import on_ground
from slam.registration.se3 import transform

# how the gate judges a scan's features: improved_floam's covariances (``GicpConfig``:
# k = 10, 1 cm point noise, ring supports spanned within 2 m, 0.05 deg beam noise) of one
# feature per 0.2 m (its edge voxel), an even subsample of 500 (a statistic of the scan)
_JUDGED = 500
_JUDGE_VOXEL = 0.2
_COV_K = 10
_SPAN = 2.0
_REGULARISATION = 1e-6 + 0.01**2  # m^2
_BEAM_NOISE = np.radians(0.05)


def feature_scatter() -> ScatterConfig:
    """The mode's settings in the feature front ends: improved_floam's, without ``at_start``.
    A scan built in the mode before the motion is known carries a start at speed off the
    open road in improved_floam; here such starts fail either way (docs/robustness.md), and
    on real starts it cost (KITTI 04 floam RPE 2.08 -> 2.20 cm per frame, nuScenes lego_lpb
    APE 23.4 -> 35.1 cm)."""
    return ScatterConfig(at_start=False)


def scatter_map() -> LocalMapConfig:
    """The scatter points' map: one point per 0.5 m voxel per scan, a few scans deep."""
    return LocalMapConfig(voxel_size=0.5, max_points_per_voxel=4)


@dataclass
class OpenRoadScan:
    """One scan's part of the mode: whether it is on, the scatter points (M, 3, sensor
    frame; empty when off), the feature ``observability`` the gate was given
    (``horizontal_observability``) and the scan's ground plane (n, d) or None."""

    on: bool
    scatter: np.ndarray
    observability: float
    plane: tuple[np.ndarray, float] | None


def feature_observability(
    xyz: np.ndarray,
    rings: np.ndarray | None,
    candidates: np.ndarray,
    plane: tuple[np.ndarray, float] | None,
    band: float,
) -> float:
    """``horizontal_observability`` of a scan's feature ``candidates`` ((N,) bool over
    ``xyz``) off the ground ``plane`` (farther than ``band`` m), judged as improved_floam
    judges its features: one per 0.2 m voxel, eq. (1) of paper 000 among them (k = 10,
    supports on one scan line spanned across the ``rings``), the beam's angular noise
    added; up to 500 of them. Covariances among all points instead, the dense near field
    dominates: a simulated corridor then looked like a motorway (0.03-0.06 both)."""
    idx = np.flatnonzero(candidates)
    idx = idx[voxel_thin(xyz, _JUDGE_VOXEL, idx)]
    if len(idx) < _COV_K:
        return 1.0
    pts = xyz[idx]
    rows = np.arange(len(pts))
    if plane is not None:
        rows = rows[~on_ground(pts, plane, band)]
    if len(rows) < 3:
        return 1.0
    rows = rows[:: max(1, len(rows) // _JUDGED)]
    labels = None if rings is None else np.asarray(rings)[idx]
    covs = estimate_covariances(
        pts, _COV_K, _REGULARISATION, "raw", query=pts[rows], labels=labels, span_distance=_SPAN
    )
    return horizontal_observability(add_beam_angle_noise(pts[rows], covs, _BEAM_NOISE))


class OpenRoad:
    """The mode's state in a feature front end: the gate (``OpenRoadGate``), the scatter
    points' map and the second sighting that keeps the traffic out of every map.
    ``empty_outside``: a trusted scan outside the mode empties the scatter map (floam: a map
    of where the mode was last on paired nothing where it came on again, 500 m on, and its
    unpaired points halved the inlier share). Not in the LeGO front ends: on the simulated
    building, where their mode is on for 68 % of the scans in short stretches, the map of a
    few scans before is of the same corridor, and emptying it cost lego_loam 3.40 -> 5.95 m."""

    def __init__(
        self, cfg: ScatterConfig, map_cfg: LocalMapConfig | None = None, empty_outside: bool = False
    ):
        self.cfg = cfg
        self.empty_outside = empty_outside
        self.gate = OpenRoadGate(cfg)
        self.map = VoxelHashMap(map_cfg or scatter_map())
        self._tree = MapTreeCache()
        self._sighting = SecondSighting(cfg.confirm_distance, cfg.confirm_height)

    def judge(
        self,
        xyz: np.ndarray,
        rings: np.ndarray | None,
        candidates: np.ndarray,
        plane: tuple[np.ndarray, float] | None,
        band: float,
        starting: bool,
    ) -> OpenRoadScan:
        """Record the scan's flag with the gate and build its part of the mode: on when the
        gate was on (the first scan of a run judged by itself), or ``starting`` (the motion
        not known yet, ``scatter.at_start`` in ``auto``). ``rings``: (N,) beam of each point
        or None; ``candidates`` (N,) bool: every edge or plane candidate of ``xyz`` before
        thinning: the gate judges their shapes, the rest off the ground is the scatter."""
        first, on = self.gate.unjudged, self.gate.on
        seen = 1.0
        if self.cfg.mode == "auto":
            seen = feature_observability(xyz, rings, candidates, plane, band)
            self.gate.update(seen < ALONG_ROAD)
            on = (self.gate.on if first else on) or (starting and self.cfg.at_start)
        scatter = np.zeros((0, 3))
        if on:
            scatter = xyz[scatter_points(xyz, candidates, plane, self.cfg)]
        return OpenRoadScan(on, scatter, seen, plane)

    def target(self) -> FeatureTarget | None:
        """The scatter map for ``feature_icp_align`` (None while it is empty)."""
        return self._tree.target(self.map) if len(self.map) else None

    def evidence(self, part: OpenRoadScan, T: np.ndarray, distance: float):
        """(pairs, RMSE m) of the scatter points at pose ``T`` against their map (nearest
        within ``distance`` m): a start is judged by them (``Estimate.evidence``); None
        outside the mode or before the map has points."""
        if not (part.on and len(part.scatter) and len(self.map)):
            return None
        d, _ = self.map.query(transform(T, part.scatter), distance_upper_bound=distance)
        d = d[np.isfinite(d)]
        return int(len(d)), float(np.sqrt(np.mean(d**2))) if len(d) else np.inf

    def insert(
        self,
        part: OpenRoadScan,
        edges: np.ndarray,
        planes: np.ndarray,
        T: np.ndarray,
        band: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Put a trusted scan's scatter points into their map at pose ``T`` and return its
        ``edges`` and ``planes`` (sensor frame) in the odometry frame, for the front end's
        maps: in the mode only what a second scan confirms and the ground (within ``band``
        m of the scan's plane); outside it every point, and with ``empty_outside`` the
        scatter map is emptied."""
        sensor = np.concatenate([edges, planes, part.scatter])
        world = sensor @ T[:3, :3].T + T[:3, 3]
        keep = self._kept(part, world, sensor, band)
        cuts = np.cumsum([len(edges), len(planes)])
        (e, p, s), (k_e, k_p, k_s) = np.split(world, cuts), np.split(keep, cuts)
        if len(s):
            self.map.add(s[k_s], origin=T[:3, 3])
        elif not part.on and self.empty_outside:  # seen where the mode was last on
            self.map.clear()
        return e[k_e], p[k_p]

    def _kept(self, part: OpenRoadScan, world: np.ndarray, sensor: np.ndarray, band: float):
        """(N,) which of a scan's points (``world``: odometry frame; ``sensor``: the same in
        the sensor frame) enter the maps: in the mode those a second scan confirms and the
        ground; every point outside it."""
        if not (part.on and self.cfg.confirm_distance > 0):
            self._sighting.reset()
            return np.ones(len(world), dtype=bool)
        ground = np.zeros(len(world), dtype=bool)
        if part.plane is not None:
            ground = on_ground(sensor, part.plane, band)
        return self._sighting.keep(world, ground)

    def state(self) -> object:
        """What ``judge`` changes, for a front end that registers one scan several times."""
        return self.gate.state()

    def restore(self, state: object) -> None:
        self.gate.restore(state)
