"""LeGO-LOAM-LPB (paper 001, Figure 5): LeGO-LOAM with preprocessing and a ground
constraint.

Per frame: range/intensity jump outliers removed (3.1.1) -> RANSAC ground plane + least
squares refit (3.1.2; replaces LeGO's slope test, which is kept as the fallback when no
level plane is found) -> DBSCAN dynamic objects removed from the non-ground points by
centroid motion (3.1.3) -> LeGO-LOAM segmentation of the non-ground points and features ->
two-step LM with the ground residual E_ground (the current ground points against the plane
fitted on the previous trusted frame) in the final 6-DoF refinement (3.3) -> edge and plane
maps as incremental maps (3.4: insert only points not already represented, lazy deletion
of what leaves the window, no rebuild of the whole map).

Every block has ``enabled`` in the config (``outliers``, ``ground``, ``dynamics``,
``map``; ``registration.ground_weight: 0`` drops the ground residual), so the paper's
ablation is a config change. The fitted plane (sensor frame) is published as
``Odometry.ground_plane`` = [nx, ny, nz, d] (n.x + d = 0, d = sensor height, m), which
keyframes keep for the ground factor; its numbers (``ground_nx`` ... ``ground_d``,
``ground_rmse``) are in the frame's diagnostic counts.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from frontends.lego_loam import (
    EdgesAndPlanes,
    LegoFeatures,
    LegoLoam,
    LegoLoamConfig,
    lego_features,
)
from slam.errors import ConfigError, InputError
from slam.features.range_image_segmentation import SegmentationConfig
from slam.features.thinning import voxel_thin
from slam.mapping.incremental_map import IncrementalMap, IncrementalMapConfig
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.odometry import Estimate
from slam.preprocess.dynamics import DynamicsConfig, remove_dynamic
from slam.preprocess.ground import GroundPlane, RansacGroundConfig, fit_ground, split_ground
from slam.preprocess.jump_outliers import JumpOutlierConfig, jump_outlier_mask
from slam.registration.two_step import TwoStepConfig, plane_to_odom
from slam.types import Scan


@dataclass
class GroundSection(RansacGroundConfig):
    """RANSAC ground (see ``RansacGroundConfig``); enabled: False = LeGO-LOAM's slope test.
    band (m): points within this distance of the fitted plane are ground."""

    enabled: bool = True
    band: float = 0.15


@dataclass
class MapSection(IncrementalMapConfig):
    """The incremental maps (3.4). enabled: False = the voxel-hashed local maps of
    LeGO-LOAM (``edge_map``/``plane_map``). edge_spacing / plane_spacing (m): a new point is
    inserted only when no map point lies this close (the map's density, like the voxel
    caps); radius (m): points farther from the sensor are lazily deleted every
    ``prune_distance`` m of travel. index: "merged" (one KD-tree over the live points,
    rebuilt at the first query after the frame's insert: the same answers as the buckets,
    2.5x faster on these ~10^4-point maps queried ~20 times per insert) or "buckets"."""

    enabled: bool = True
    index: str = "merged"
    edge_spacing: float = 0.1
    plane_spacing: float = 0.2
    radius: float = 60.0
    prune_distance: float = 3.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if min(self.edge_spacing, self.plane_spacing) <= 0 or self.radius <= 0:
            raise ConfigError("map edge_spacing, plane_spacing and radius must be > 0")


def _lpb_registration() -> TwoStepConfig:
    # with the ground as a plane a cycle of pairs is convergence (``cycle_tolerance``): a
    # motorway start at 9 m/s rejected 2 of its first 5 frames without it
    return TwoStepConfig(ground_weight=0.2, cycle_tolerance=0.002)


def _lpb_segmentation() -> SegmentationConfig:
    return SegmentationConfig(enabled=False)


@dataclass
class LegoLpbConfig(LegoLoamConfig):
    """LeGO-LOAM-LPB settings: LeGO-LOAM's plus the four switchable blocks (paper 001).

    segmentation: off (the paper's preprocessing replaces LeGO's small-cluster removal).
    max_dynamic_fraction: when the dynamics block flags more than this share of a scan's
    points as moving, none is removed (``extras["dynamic_vetoed"]`` = 1).
    max_surface_points: the density-aware subset of a dense scan's ground + plane points
    that is matched (16-beam scans stay below it). Why: docs/paper001.md (Two-step settings)
    and docs/speed.md."""

    outliers: JumpOutlierConfig = field(default_factory=JumpOutlierConfig)
    ground: GroundSection = field(default_factory=GroundSection)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    max_dynamic_fraction: float = 0.1
    map: MapSection = field(default_factory=MapSection)
    registration: TwoStepConfig = field(default_factory=_lpb_registration)
    segmentation: SegmentationConfig = field(default_factory=_lpb_segmentation)
    max_surface_points: int = 8000


class IncrementalTarget:
    """An ``IncrementalMap`` as a matching target (``two_step.MapTarget``)."""

    def __init__(self, cfg: MapSection, spacing: float):
        self.map = IncrementalMap(cfg)
        self.cfg = cfg
        self.spacing = spacing
        self._pruned_at: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.map)

    def neighbours(
        self, queries: np.ndarray, k: int, *, max_distance: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]:
        d, ids = self.map.knn(queries, k, distance_upper_bound=max_distance)
        return d, self.map.points(ids)

    def add(self, points: np.ndarray, origin: np.ndarray) -> int:
        """Insert the points no map point is within ``spacing`` of (one k-NN query), after a
        lazy deletion of the points beyond ``radius`` once the sensor moved far enough."""
        moved = np.inf if self._pruned_at is None else np.linalg.norm(origin - self._pruned_at)
        if moved >= self.cfg.prune_distance:
            r = self.cfg.radius
            self.map.delete(box=(origin - r, origin + r), outside=True)
            self._pruned_at = np.asarray(origin, dtype=np.float64).copy()
        if len(points) == 0:
            return 0
        if len(self.map):
            d, _ = self.map.knn(points, 1)
            points = points[d[:, 0] > self.spacing]
        # one point per spacing cell among the new ones too
        cell = np.floor(points / self.spacing).astype(np.int64)
        _, first = np.unique(cell, axis=0, return_index=True)
        points = points[np.sort(first)]
        self.map.insert(points)
        return len(points)


class LegoLpb(LegoLoam):
    """LeGO-LOAM-LPB front end (plugin name ``lego_lpb``)."""

    Config = LegoLpbConfig

    def __init__(self, cfg: LegoLpbConfig | None = None):
        self.cfg = cfg or LegoLpbConfig()
        super().__init__(self.cfg)
        self._plane_now: GroundPlane | None = None
        self._plane_odom: tuple[np.ndarray, float] | None = None  # previous trusted frame's
        self._dyn_state: np.ndarray | None = None
        self._residual_xyz: np.ndarray | None = None  # inliers of this frame's plane fit

    # ------------------------------------------------------------------ maps
    def _new_map(self, cfg: LocalMapConfig):
        m = self.cfg.map
        if not m.enabled:
            return VoxelHashMap(cfg)
        spacing = m.edge_spacing if cfg is self.cfg.edge_map else m.plane_spacing
        return IncrementalTarget(m, spacing)

    def _targets(self):
        if self.cfg.map.enabled:
            return self.edge_map, self.plane_map
        return super()._targets()

    def _map_size(self) -> int:
        return len(self.edge_map) + len(self.plane_map)

    # ------------------------------------------------------------------ preprocessing
    def _features(self, scan: Scan, counts: dict, timings: dict) -> tuple[Scan, LegoFeatures]:
        cfg = self.cfg
        t = time.perf_counter()
        ring = self._ring(scan)
        n0 = len(scan)
        if cfg.outliers.enabled:
            keep = jump_outlier_mask(scan.xyz, scan.intensity, ring, cfg.outliers)
            scan, ring = scan.select(keep), ring[keep]
        counts["n_outliers"] = int(n0 - len(scan))
        timings["outliers_ms"] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        ground = self._fit_ground(scan, counts)
        timings["ground_ms"] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        scan, ring, ground = self._remove_dynamic(scan, ring, ground, counts)
        timings["dynamics_ms"] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        feats = lego_features(scan.xyz, ring, cfg.feature_config(), ground=ground)
        timings["features_ms"] = (time.perf_counter() - t) * 1e3
        if self._plane_now is not None:
            p = self._plane_now
            counts.update(
                ground_nx=float(p.normal[0]),
                ground_ny=float(p.normal[1]),
                ground_nz=float(p.normal[2]),
                ground_d=float(p.d),
                ground_rmse=float(p.rmse),
            )
        return scan, feats

    def _fit_ground(self, scan: Scan, counts: dict) -> np.ndarray | None:
        """RANSAC ground of the scan (3.1.2): the (N,) ground mask, None for LeGO's slope
        test (block off, or no level plane in view: ``ground_fallback`` = 1)."""
        cfg = self.cfg
        self._plane_now = None
        self._residual_xyz = None
        if not cfg.ground.enabled:
            return None
        try:
            self._plane_now = fit_ground(scan.xyz, cfg.ground, seed=self.n_frames)
        except InputError:
            counts["ground_fallback"] = 1
            return None
        ground = split_ground(scan.xyz, self._plane_now, cfg.ground.band)[0]
        inl = scan.xyz[self._plane_now.inliers]
        self._residual_xyz = inl[voxel_thin(inl, cfg.ground_voxel)]
        return ground

    def _remove_dynamic(
        self, scan: Scan, ring: np.ndarray, ground: np.ndarray | None, counts: dict
    ) -> tuple[Scan, np.ndarray, np.ndarray | None]:
        """DBSCAN dynamic objects among the non-ground points removed (3.1.3), unless more
        than ``max_dynamic_fraction`` of the scan is flagged (``dynamic_vetoed`` = 1)."""
        cfg = self.cfg
        n_dyn = 0
        if cfg.dynamics.enabled:
            g = ground if ground is not None else np.zeros(len(scan), dtype=bool)
            ng = np.flatnonzero(~g)
            # this scan in the previous one's frame: the constant-velocity prediction
            keep_ng, self._dyn_state = remove_dynamic(
                scan.xyz[ng], self._dyn_state, self.T_motion, cfg.dynamics
            )
            drop = ng[~keep_ng]
            n_dyn = len(drop)
            vetoed = n_dyn > cfg.max_dynamic_fraction * len(scan)
            counts["dynamic_vetoed"] = int(vetoed)
            if vetoed:
                n_dyn = 0
            if n_dyn:
                keep = np.ones(len(scan), dtype=bool)
                keep[drop] = False
                scan, ring = scan.select(keep), ring[keep]
                ground = None if ground is None else ground[keep]
                if self._plane_now is not None:
                    self._plane_now.inliers = self._plane_now.inliers[keep]
        counts["n_dynamic"] = int(n_dyn)
        return scan, ring, ground

    def _ground_plane(self) -> np.ndarray | None:
        p = self._plane_now
        return None if p is None else np.r_[p.normal, p.d]

    def _scan_state(self):
        return super()._scan_state(), self._dyn_state  # the tracker advances once per scan

    def _restore_scan_state(self, state) -> None:
        road, self._dyn_state = state
        super()._restore_scan_state(road)

    def _ground_plane_odom(self) -> tuple[np.ndarray, float] | None:
        return self._plane_odom if self._plane_now is not None else None

    def _ground_residual_points(self) -> np.ndarray | None:
        return self._residual_xyz

    def _add_features(self, edges: np.ndarray, planes: np.ndarray, origin: np.ndarray) -> None:
        if self.cfg.map.enabled:
            self.edge_map.add(edges, origin)
            self.plane_map.add(planes, origin)
        else:
            super()._add_features(edges, planes, origin)

    def _insert(self, est: Estimate[EdgesAndPlanes], timings: dict) -> None:
        super()._insert(est, timings)
        T = est.pose
        if self._plane_now is not None:  # the plane of this trusted frame, for the next one
            self._plane_odom = plane_to_odom(self._plane_now.normal, self._plane_now.d, T)
