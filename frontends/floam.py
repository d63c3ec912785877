"""Traditional FLOAM (the baseline of paper 000): no SOR, LOAM edge/plane features,
point-to-edge and point-to-plane scan-to-map matching against edge and plane local maps.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from slam.errors import ConfigError
from slam.features.loam import FeatureConfig, extract_features
from slam.features.scatter import ScatterConfig
from slam.features.thinning import thin_to_count, voxel_thin
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.odometry import CommonConfig, Estimate, ScanToMapFrontend
from slam.odometry.config import check_positive
from slam.odometry.open_road import OpenRoad, OpenRoadScan, feature_scatter
from slam.registration.feature_icp import FeatureIcpConfig, MapTreeCache, feature_icp_align
from slam.registration.ground_plane import (
    FixedNormals,
    GroundPlaneConfig,
    enough_beams,
    fit_ground,
    on_ground,
)
from slam.types import Scan


@dataclass
class EdgesAndPlanes:
    """Sensor-frame edge and plane features (m) of one scan: what the maps receive; in the
    open-road mode (``road``) also its scatter points."""

    edges: np.ndarray
    planes: np.ndarray
    road: OpenRoadScan | None = None


def _edge_map() -> LocalMapConfig:
    return LocalMapConfig(voxel_size=0.2, max_points_per_voxel=2)


def _plane_map() -> LocalMapConfig:
    return LocalMapConfig(voxel_size=0.4, max_points_per_voxel=2)


def _ground() -> GroundPlaneConfig:
    # raw returns (no SOR) at up to 30 m lie up to 0.2 m off the fitted plane (motorway at
    # 9 m/s, first step 0.68 m for 0.91 m with a 0.1 m band, 0.86 m with 0.2 m)
    return GroundPlaneConfig(band=0.2)


@dataclass
class FloamConfig(CommonConfig):
    """FLOAM settings. edge_voxel/plane_voxel (m): feature thinning before matching
    (FLOAM's map_resolution 0.4 -> 0.2 m edges / 0.4 m planes); edge_map/plane_map: the
    two local maps. max_registration_points: above this many thinned features (dense 64-128
    beam scans: ~12k / ~18k) the ICP registers a density-aware subset of that many
    (``thin_to_count``: both voxels grown by the same factor), the maps still receive every
    feature; 0 = no cap, the default (7000, which 16-beam scans never reach, moved the
    HDL-64E urban APE 1.29 -> 1.56 cm over 60 frames, 10000 to 1.38 cm; OS-128 3.44 ->
    3.02 cm). ground: the scan's ground plane (``slam.registration.ground_plane``; sensors
    of ``ground.min_beams`` or more): edge features on it are dropped (the rings' noise, not
    edges) and plane features on it match along its normal only, so that the map's rings
    cannot hold the scan at rest (docs/paper000.md, "The ground's rings"). ground_edge_band
    (m): edges this close to the plane are dropped; kerbs stand higher and stay (0.2 m
    dropped them: nuScenes keyframes 39.9 -> 44.4 cm APE, 4 rejected; 0.1 m: 37.9 cm).
    scatter: the open-road mode (``slam.odometry.open_road``): on a road whose features all
    run along it, the points the features left out are registered too (point to point,
    their own map) and the ground is a plane on every sensor; ``at_start`` off
    (``open_road.feature_scatter``)."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    registration: FeatureIcpConfig = field(default_factory=FeatureIcpConfig)
    edge_map: LocalMapConfig = field(default_factory=_edge_map)
    plane_map: LocalMapConfig = field(default_factory=_plane_map)
    edge_voxel: float = 0.2
    plane_voxel: float = 0.4
    max_registration_points: int = 0
    ground: GroundPlaneConfig = field(default_factory=_ground)
    ground_edge_band: float = 0.1
    scatter: ScatterConfig = field(default_factory=feature_scatter)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, "frontend", ("edge_voxel", "plane_voxel"))
        if self.max_registration_points < 0:
            raise ConfigError("max_registration_points must be >= 0 (0 = no cap)")
        if self.ground_edge_band < 0:
            raise ConfigError(f"ground_edge_band must be >= 0 m, got {self.ground_edge_band}")


class Floam(ScanToMapFrontend):
    """FLOAM front end (plugin name ``floam``)."""

    Config = FloamConfig

    def __init__(self, cfg: FloamConfig | None = None):
        self.cfg = cfg or FloamConfig()
        super().__init__(self.cfg)
        self.edge_map = VoxelHashMap(self.cfg.edge_map)
        self.plane_map = VoxelHashMap(self.cfg.plane_map)
        self._edge_tree, self._plane_tree = MapTreeCache(), MapTreeCache()
        self.open_road = OpenRoad(self.cfg.scatter, empty_outside=True)

    def _registered(self, edges: np.ndarray, planes: np.ndarray):
        """The edges and planes the ICP registers: all of them, or above
        ``max_registration_points`` the density-aware subset of that many."""
        cap = self.cfg.max_registration_points
        if not cap or len(edges) + len(planes) <= cap:
            return edges, planes
        cfg = self.cfg
        ke, kp = thin_to_count([edges, planes], [cfg.edge_voxel, cfg.plane_voxel], cap)
        return edges[ke], planes[kp]

    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        cfg = self.cfg
        xyz = scan.xyz
        t = time.perf_counter()
        feats = extract_features(xyz, scan.ring, cfg.features, top_picks=False)
        e_idx = feats.edge_idx[voxel_thin(xyz, cfg.edge_voxel, feats.edge_idx)]
        p_idx = feats.plane_idx[voxel_thin(xyz, cfg.plane_voxel, feats.plane_idx)]
        ground_fit = fit_ground(xyz, cfg.ground) if cfg.ground.enabled else None
        candidates = np.zeros(len(xyz), dtype=bool)
        candidates[feats.edge_idx] = True
        candidates[feats.plane_idx] = True
        road = self.open_road.judge(
            xyz,
            scan.ring,
            candidates,
            ground_fit,
            cfg.ground.band,
            self.gate.n_trusted < 2,
        )
        # the ground as a plane on sensors of enough beams, and on any in the open-road mode
        plane = ground_fit if road.on or enough_beams(scan.ring, cfg.ground) else None
        edges, planes = xyz[e_idx], xyz[p_idx]
        if plane is not None:
            edges = edges[~on_ground(edges, plane, cfg.ground_edge_band)]
        road.plane = plane
        counts = {"n_after_sor": int(len(xyz)), "n_edges": int(len(edges))}
        counts["n_planes"] = int(len(planes))
        counts.update(
            horizontal_observability=road.observability,
            open_road=int(road.on),
            scatter_points=int(len(road.scatter)),
        )
        timings["features_ms"] = (time.perf_counter() - t) * 1e3
        if len(edges) + len(planes) < 10:
            skipped = f"too few features ({len(edges) + len(planes)})"
            return Estimate(T_pred, skipped=skipped, counts=counts)

        t = time.perf_counter()
        est = Estimate(T_pred, pending=EdgesAndPlanes(edges, planes, road), counts=counts)
        if len(self.edge_map) + len(self.plane_map) >= 10:
            # KD-trees (rebuilt when a map changed): FLOAM's bounded k=5 search reaches 1 m,
            # five 0.2 m voxels, where most outdoor edge points have no neighbours, and the
            # voxel hash would open up to 11^3 voxels for each of them
            e_map = self._edge_tree.target(self.edge_map)
            p_map = self._plane_tree.target(self.plane_map)
            s_map = self.open_road.target() if road.on else None
            e_reg, p_reg = self._registered(edges, planes)
            rc = cfg.registration
            if self.tracked_horizon is None:  # a search's start may be far off: cost may rise
                rc = replace(rc, least_cost=False)
            ground = None
            if plane is not None:
                ground = FixedNormals(on_ground(p_reg, plane, cfg.ground.band), plane[0])
            T0 = T_pred
            if wide:  # tracking lost: coarse pass from the prediction with a wider search
                f = cfg.recovery_correspondence_factor
                coarse = replace(
                    rc,
                    max_neighbor_distance=rc.max_neighbor_distance * f,
                    plane_threshold=rc.plane_threshold * f,
                )
                T0 = feature_icp_align(
                    e_reg, p_reg, e_map, p_map, T_pred, coarse, ground, road.scatter, s_map
                ).T_target_source
            est.result = feature_icp_align(
                e_reg, p_reg, e_map, p_map, T0, rc, ground, road.scatter, s_map
            )
            est.pose = est.result.T_target_source
            est.evidence = self.open_road.evidence(road, est.pose, rc.max_neighbor_distance)
        timings["registration_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def _scan_state(self) -> object:
        return self.open_road.state()

    def _restore_scan_state(self, state: object) -> None:
        self.open_road.restore(state)

    def _map_size(self) -> int:
        return len(self.edge_map) + len(self.plane_map)

    def _insert(self, est: Estimate[EdgesAndPlanes], timings: dict) -> None:
        f, T = est.pending, est.pose
        edges, planes = self.open_road.insert(f.road, f.edges, f.planes, T, self.cfg.ground.band)
        self.edge_map.add(edges, origin=T[:3, 3])
        self.plane_map.add(planes, origin=T[:3, 3])
