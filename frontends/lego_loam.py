"""LeGO-LOAM (Shan and Englot 2018), the baseline of paper 001: range-image ground marking
and segmentation -> LOAM features of the segmented cloud (edges from non-ground segments
only, planes from the ground and the segments) -> two-step Levenberg-Marquardt ([roll,
pitch, z] from the ground, [yaw, x, y] from the edges) -> 6-DoF scan-to-map refinement
(LeGO's mapping) against edge and plane local maps. No preprocessing.

The two LeGO stages (scan-to-scan odometry at 10 Hz, scan-to-map mapping at 2 Hz) are one
here: the two-step solve starts from the constant-velocity prediction against the local
maps and the refinement follows at once, at every frame (the framework's front ends are
scan-to-map). Curvature, NMS and sector picks are the framework's LOAM features
(``slam.features.loam``) run on the segmented cloud, whose dropped clusters no longer
produce edges.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from slam.errors import ConfigError
from slam.features.loam import FeatureConfig, extract_features, ring_from_elevation
from slam.features.range_image_segmentation import Segmentation, SegmentationConfig, segment
from slam.features.scatter import ScatterConfig
from slam.features.thinning import thin_to_count, voxel_thin
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.odometry import CommonConfig, Estimate, ScanToMapFrontend
from slam.odometry.config import check_positive
from slam.odometry.open_road import OpenRoad, OpenRoadScan, feature_scatter
from slam.registration.feature_icp import FeatureTarget, MapTreeCache
from slam.registration.ground_plane import (
    FixedNormals,
    GroundPlaneConfig,
    enough_beams,
    fit_ground,
    on_ground,
)
from slam.registration.two_step import TwoStepConfig, two_step_align, weak_translation
from slam.types import Scan


@dataclass
class LegoFeatureConfig:
    """Segmentation + features. edge_voxel / plane_voxel / ground_voxel (m): thinning of
    each feature set before matching and insertion into the maps."""

    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    edge_voxel: float = 0.2
    plane_voxel: float = 0.4
    ground_voxel: float = 0.2


@dataclass
class LegoFeatures:
    """Sensor-frame feature sets of one sweep: ground (plane points on the ground), edges
    (non-ground), planes (non-ground), each voxel-thinned; ``segmented``: (N,) bool mask of
    the points kept by the segmentation; ``seg``: the segmentation itself; ``candidates``:
    (N,) bool mask of every edge or plane candidate before thinning (the rest is scatter:
    ``slam.odometry.open_road``)."""

    ground: np.ndarray
    edges: np.ndarray
    planes: np.ndarray
    segmented: np.ndarray
    seg: Segmentation
    candidates: np.ndarray


def lego_features(
    xyz: np.ndarray,
    ring: np.ndarray,
    cfg: LegoFeatureConfig | None = None,
    *,
    ground: np.ndarray | None = None,
) -> LegoFeatures:
    """LeGO-LOAM's feature extraction of one sweep: segmentation (``ground`` (N,) bool from
    elsewhere replaces the slope test), then LOAM curvature features on the segmented cloud;
    edges must not be ground (LeGO-LOAM), ground plane points and non-ground plane points
    are kept apart for the two-step matching."""
    cfg = cfg or LegoFeatureConfig()
    seg = segment(xyz, ring, cfg.segmentation, ground=ground)
    keep = np.flatnonzero(seg.segmented)
    f = extract_features(xyz[keep], np.asarray(ring)[keep], cfg.features)
    e = keep[f.edge_idx]
    p = keep[f.plane_idx]
    candidates = np.zeros(len(xyz), dtype=bool)
    candidates[e] = True
    candidates[p] = True
    e = e[~seg.ground[e]]
    g, pl = p[seg.ground[p]], p[~seg.ground[p]]

    def thin(idx: np.ndarray, voxel: float) -> np.ndarray:
        pts = xyz[idx]
        return pts[voxel_thin(pts, voxel)] if len(pts) else pts.reshape(0, 3)

    return LegoFeatures(
        ground=thin(g, cfg.ground_voxel),
        edges=thin(e, cfg.edge_voxel),
        planes=thin(pl, cfg.plane_voxel),
        segmented=seg.segmented,
        seg=seg,
        candidates=candidates,
    )


@dataclass
class EdgesAndPlanes:
    """Sensor-frame features (m) the maps receive: edges, and the ground and non-ground
    plane points together (LeGO's surface map); in the open-road mode (``road``) also the
    scan's scatter points."""

    edges: np.ndarray
    planes: np.ndarray
    road: OpenRoadScan | None = None


def _edge_map() -> LocalMapConfig:
    return LocalMapConfig(voxel_size=0.2, max_points_per_voxel=2)


def _plane_map() -> LocalMapConfig:
    return LocalMapConfig(voxel_size=0.4, max_points_per_voxel=2)


def _ground_plane() -> GroundPlaneConfig:
    # raw returns (no SOR) at up to 30 m lie up to 0.2 m off the fitted plane; on the 32-beam
    # nuScenes keyframes (2 Hz, 1-5 m apart) LeGO's few edges need what the rings hold
    # (lego_loam 138 -> 229 cm APE with the plane, lego_lpb 91 -> 96 cm), hence 64 beams
    return GroundPlaneConfig(band=0.2, min_beams=64)


@dataclass
class LegoLoamConfig(CommonConfig):
    """LeGO-LOAM settings: segmentation, features, thinning (see ``LegoFeatureConfig``), the
    two-step matcher and the edge / plane local maps (the plane map holds ground and
    non-ground plane points, LeGO's surface map).

    max_surface_points: above this many ground + plane points (dense 64-128 beam scans:
    ~27k) the matching uses a density-aware subset of that many (``thin_to_count``: both
    voxels grown by the same factor; edges are all kept), the maps still receive every
    feature; 0 = no cap, LeGO-LOAM's default (8000 moved its HDL-64E urban APE 1.87 -> 2.35
    cm over 60 frames, OS-128 4.57 -> 4.48 cm; LeGO-LOAM-LPB uses 8000).
    ground_plane: the scan's fitted ground plane (``slam.registration.ground_plane``;
    sensors of ``ground_plane.min_beams`` or more): ground points on it match along its
    normal, so that the map's ground rings cannot hold the scan at rest (simulated motorway
    started at 9 m/s: first steps 0.16 / -0.09 / -0.29 m for 0.91 m without it;
    docs/paper001.md, "The ground's rings").
    scatter: the open-road mode (``slam.odometry.open_road``): on a road whose features all
    run along it, the points the segmentation dropped (vegetation, clutter) are matched too
    (point-to-point, their own map; in the second step and the refinement) and the ground
    is a plane on every sensor; ``at_start`` off (``open_road.feature_scatter``)."""

    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    edge_voxel: float = 0.2
    plane_voxel: float = 0.4
    ground_voxel: float = 0.2
    registration: TwoStepConfig = field(default_factory=TwoStepConfig)
    edge_map: LocalMapConfig = field(default_factory=_edge_map)
    plane_map: LocalMapConfig = field(default_factory=_plane_map)
    max_surface_points: int = 0
    ground_plane: GroundPlaneConfig = field(default_factory=_ground_plane)
    scatter: ScatterConfig = field(default_factory=feature_scatter)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, "frontend", ("edge_voxel", "plane_voxel", "ground_voxel"))
        if self.max_surface_points < 0:
            raise ConfigError("max_surface_points must be >= 0 (0 = no cap)")

    def feature_config(self) -> LegoFeatureConfig:
        return LegoFeatureConfig(
            self.segmentation, self.features, self.edge_voxel, self.plane_voxel, self.ground_voxel
        )


class LegoLoam(ScanToMapFrontend):
    """LeGO-LOAM front end (plugin name ``lego_loam``)."""

    Config = LegoLoamConfig

    def __init__(self, cfg: LegoLoamConfig | None = None):
        self.cfg = cfg or self.Config()
        super().__init__(self.cfg)
        self.edge_map = self._new_map(self.cfg.edge_map)
        self.plane_map = self._new_map(self.cfg.plane_map)
        self._edge_tree, self._plane_tree = MapTreeCache(), MapTreeCache()
        self.open_road = OpenRoad(self.cfg.scatter)

    # ------------------------------------------------------------------ hooks for LPB
    def _new_map(self, cfg: LocalMapConfig):
        return VoxelHashMap(cfg)

    def _targets(self) -> tuple[FeatureTarget, FeatureTarget]:
        return self._edge_tree.target(self.edge_map), self._plane_tree.target(self.plane_map)

    def _features(self, scan: Scan, counts: dict, timings: dict) -> tuple[Scan, LegoFeatures]:
        """Preprocessing (none in LeGO-LOAM) and features of the cropped, deskewed scan;
        the preprocessing's scalar diagnostics go to ``counts``."""
        t = time.perf_counter()
        ring = self._ring(scan)
        feats = lego_features(scan.xyz, ring, self.cfg.feature_config())
        timings["features_ms"] = (time.perf_counter() - t) * 1e3
        return scan, feats

    def _ground_plane_odom(self) -> tuple[np.ndarray, float] | None:
        """The previous frame's ground plane in the odometry frame (LPB), None here."""
        return None

    def _ground_residual_points(self) -> np.ndarray | None:
        """The points of the ground residual (LPB), None here."""
        return None

    def _ground_plane(self) -> np.ndarray | None:
        """This scan's ground plane [nx, ny, nz, d] in the sensor frame (LPB), None here."""
        return None

    # ------------------------------------------------------------------ the frame
    def _ring(self, scan: Scan) -> np.ndarray:
        if scan.ring is not None:
            return np.asarray(scan.ring)
        return ring_from_elevation(scan.xyz, self.cfg.features.n_beams, self.cfg.features.fov_deg)

    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        counts: dict = {}
        scan, f = self._features(scan, counts, timings)
        counts.update(
            n_edges=int(len(f.edges)),
            n_planes=int(len(f.planes) + len(f.ground)),
            n_ground=int(len(f.ground)),
            n_clusters=f.seg.n_clusters,
            n_segmented=int(f.segmented.sum()),
        )
        est = Estimate(
            T_pred,
            filtered=scan.xyz[f.segmented],
            ground_plane=self._ground_plane(),
            counts=counts,
        )
        if len(f.edges) + len(f.planes) + len(f.ground) < 10:
            est.skipped = f"too few features ({len(f.edges) + len(f.planes)})"
            return est
        t = time.perf_counter()
        rings = self._ring(scan)
        gc = self.cfg.ground_plane
        ground_fit = fit_ground(scan.xyz, gc) if gc.enabled else None
        road = self.open_road.judge(
            scan.xyz,
            rings,
            f.candidates,
            ground_fit,
            gc.band,
            self.gate.n_trusted < 2,
        )
        # the ground as a plane on sensors of enough beams, and on any in the open-road mode
        road.plane = ground_fit if road.on or enough_beams(rings, gc) else None
        counts.update(
            horizontal_observability=road.observability,
            open_road=int(road.on),
            scatter_points=int(len(road.scatter)),
        )
        est.pending = EdgesAndPlanes(f.edges, np.concatenate([f.ground, f.planes]), road)
        if len(self.edge_map) + len(self.plane_map) >= 10:
            reg = self._registered(f)
            fixed = None
            if road.plane is not None:
                fixed = FixedNormals(on_ground(reg.ground, road.plane, gc.band), road.plane[0])
            beams = int(rings.max()) + 1 if len(rings) else 0
            est.result = self._align(
                reg, T_pred, wide, self._iterations(scan), fixed, beams, road.scatter
            )
            est.pose = est.result.T_target_source
            rc = self.cfg.registration
            if rc.degenerate_ratio > 0:  # translation axes kept from the prediction
                counts["remapped_axes"] = len(weak_translation(est.result.H, rc.degenerate_ratio))
            est.evidence = self.open_road.evidence(road, est.pose, rc.max_neighbor_distance)
        timings["registration_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def _registered(self, f: LegoFeatures) -> LegoFeatures:
        """The features the matching uses: all, or above ``max_surface_points`` ground +
        plane points a density-aware subset of that many of them (every edge kept)."""
        cap, cfg = self.cfg.max_surface_points, self.cfg
        if not cap or len(f.ground) + len(f.planes) <= cap:
            return f
        kg, kp = thin_to_count([f.ground, f.planes], [cfg.ground_voxel, cfg.plane_voxel], cap)
        return replace(f, ground=f.ground[kg], planes=f.planes[kp])

    def _iterations(self, scan: Scan) -> int:
        """The refinement's iteration cap: ``max_iterations`` per ``iteration_period`` of the
        sweep period (the stamp gap before the period is known), 1-5 times."""
        rc = self.cfg.registration
        period = self.clock.period() or self.clock.since_last(scan.stamp)
        if not period or rc.iteration_period <= 0:
            return rc.max_iterations
        return rc.max_iterations * int(np.clip(round(period / rc.iteration_period), 1, 5))

    def _align(
        self,
        f: LegoFeatures,
        T_pred: np.ndarray,
        wide: bool,
        iterations: int,
        fixed: FixedNormals | None = None,
        beams: int = 0,
        scatter: np.ndarray | None = None,
    ):
        """Two-step LM and 6-DoF refinement against the maps from ``T_pred`` (a coarse pass
        with a wider search first when ``wide``), at most ``iterations`` LM iterations;
        ``fixed``: the ground points on the scan's ground plane and its normal; ``beams``:
        the sensor's (the cut of what moved needs ``outlier_min_beams``, or the open-road
        mode); ``scatter``: the mode's points (sensor frame), matched against their map."""
        cfg = self.cfg
        e_map, p_map = self._targets()
        open_road = scatter is not None and len(scatter) > 0
        s_map = self.open_road.target() if open_road else None
        more = {"scatter_xyz": scatter, "scatter_map": s_map}
        rc = replace(cfg.registration, max_iterations=iterations)
        # on fewer beams the cut took the few terms that hold a corridor along it; on an open
        # road the scatter points hold the pose along it, and the traffic's edges and planes
        # pulled a 16-beam motorway start backwards (0.63 m in one step)
        if beams < rc.outlier_min_beams and not open_road:
            rc = replace(rc, outlier_sigmas=0.0)
        plane = self._ground_plane_odom()
        g_res = self._ground_residual_points()
        T0 = T_pred
        if wide:  # tracking lost: a coarse pass from the prediction with a wider search
            k = cfg.recovery_correspondence_factor
            coarse = replace(
                rc,
                max_neighbor_distance=rc.max_neighbor_distance * k,
                plane_threshold=rc.plane_threshold * k,
            )
            T0 = two_step_align(
                f.ground, f.edges, f.planes, e_map, p_map, T_pred, coarse, plane,
                ground_residual_xyz=g_res, ground_normal=fixed, settle=True, **more,
            ).T_target_source  # fmt: skip
        # a start that is not the tracked prediction (first motion, lost) settles first
        return two_step_align(
            f.ground, f.edges, f.planes, e_map, p_map, T0, rc, plane,
            ground_residual_xyz=g_res, ground_normal=fixed,
            settle=self.tracked_horizon is None, **more,
        )  # fmt: skip

    def _map_size(self) -> int:
        return len(self.edge_map) + len(self.plane_map)

    def _scan_state(self) -> object:
        return self.open_road.state()

    def _restore_scan_state(self, state: object) -> None:
        self.open_road.restore(state)

    def _insert(self, est: Estimate[EdgesAndPlanes], timings: dict) -> None:
        f, T = est.pending, est.pose
        band = self.cfg.ground_plane.band
        self._add_features(*self.open_road.insert(f.road, f.edges, f.planes, T, band), T[:3, 3])

    def _add_features(self, edges: np.ndarray, planes: np.ndarray, origin: np.ndarray) -> None:
        """Edges and plane points (odometry frame) into their maps; ``origin``: the sensor."""
        self.edge_map.add(edges, origin=origin)
        self.plane_map.add(planes, origin=origin)
