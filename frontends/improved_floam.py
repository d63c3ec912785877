"""Improved FLOAM (paper 000, section 2.1, Figure 1): weighted density-adaptive SOR ->
curvature-corrected LOAM edge/plane features -> GICP scan-to-map on the features (with
per-point covariances, eqs. (1)-(5)) against an incrementally updated local map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from frontends.common import CommonConfig, Estimate, ScanToMapFrontend
from slam.errors import ConfigError
from slam.features.curvature import covariance_curvature, kappa_from_neighbours
from slam.features.loam import FeatureConfig, extract_features, ring_from_elevation
from slam.features.thinning import thin_to_count, voxel_thin
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.preprocess.column_stride import thin_scan
from slam.preprocess.sor import SorConfig, apply_sor, neighbourhoods
from slam.registration.gicp import GicpConfig, GicpTarget, estimate_covariances, gicp_align
from slam.registration.plausibility import PlausibilityConfig
from slam.types import Scan


def _improved_features() -> FeatureConfig:
    return FeatureConfig(use_covariance_curvature=True)


def _improved_plausibility() -> PlausibilityConfig:
    """The gate with a 0.1 m per-frame floor off the constant-velocity prediction (the
    common default is 0.3 m). GICP on a plain corridor with people walking along it crept
    0.1-0.3 m per frame along the corridor and the motion model fed it back until the
    estimate ran away (building_loop: 549 m APE; 5.55 m with 0.1 m). Unchanged on every
    README scene and sensor, the urban drive and KITTI-raw. Not the common default: with
    0.1 m LeGO-LOAM-LPB, whose fitness test already rejects ~7 % of the building's frames,
    lost 541 of 4412 and ran away (57 m), and FLOAM's S route went 4.68 -> 5.21 m."""
    return PlausibilityConfig(prediction_floor=0.1)


@dataclass
class ImprovedFloamConfig(CommonConfig):
    """Improved FLOAM settings. edge_voxel/plane_voxel (m) thin the feature sets before
    registration (the paper registers 800-1200 features per frame). covariance_source:
    "features" (default) = from the feature set itself (eq. (1) on the voxel-thinned feature
    cloud, whose neighbourhoods span several scan lines even on open ground); "scan" = from
    each feature's k neighbours in the whole filtered scan voxel-downsampled to
    ``covariance_voxel``. At car speed "scan" leaves the ground to single-ring supports
    (isotropic, no normal): the ground stops constraining pitch and height, and the urban
    drive climbed 8 m in 120 m (APE 7.86 m over 300 frames; "features" 0.41-0.53 m; park 2.8 ->
    2.1 cm, corridor 1.18 -> 1.19 cm, plaza 0.71 -> 0.81 cm over 300 frames). map_covariance:
    "map" = covariances of newly inserted map points, and of the map points near them,
    from their k neighbours in the map (the target "calculated identically", dense over
    many scans, refreshed as the map fills in; the default); "scan" = keep the source
    covariances rotated into the map frame. map_refresh: "neighbours" = the new points' map
    neighbours get their covariance recomputed too (default); "new" = only the new points
    (~20 % faster on outdoor maps; park 2.2 vs 2.6 cm, plaza 0.88 vs 0.77 cm APE over 300 frames).
    max_registration_points: when the thinned features exceed this many (dense 64-128 beam
    scans), GICP registers a density-aware subset of them (``thin_to_count``: edges and planes
    voxel-thinned again, both voxels grown by the same factor); their covariances still come
    from all the features and the map still receives all of them. 0 = register every feature.
    8000 leaves 16-beam scans alone (corridor ~600 features, park ~1900, urban drive ~5100)
    and registers ~62 % of a 64/128-beam scan's 11.7k / 12.4k (urban, first 100 frames, with
    predict_convergence: APE HDL-64 4.89 -> 4.92 cm, OS-128 4.11 -> 3.94 cm).

    max_scan_points / min_ring_columns: the column stride of scans denser than the sensors
    measured here (``slam.preprocess.column_stride``, before SOR: the paper's k=10 SOR of
    every raw point is the dearest stage). A scan of more than max_scan_points points keeps
    one point per s = ceil(n / max_scan_points) azimuth columns of each ring, every ring
    kept (vertical resolution unchanged, LOAM's along-ring curvature intact), the columns
    chosen by azimuth (never by storage order) and advancing one column per frame; s is
    capped so that each ring keeps >= min_ring_columns columns (1024 = 0.35 deg, the
    horizontal resolution of an OS1-128 in its 1024 mode, 3.9 cm APE over the first 100
    urban frames). 0 = never thin. The defaults touch only scans above 140k points, e.g. a
    128-beam sensor at 2048 columns (262k -> 131k points, 0.18 -> 0.35 deg); 16-beam
    (23-57k), 32-beam (69k) and 64-beam (120-133k) scans pass unchanged. Measured trade-off
    of thinning 64-beam scans (s = 2, 2083 -> 1041 columns, 0.17 -> 0.35 deg, all 64 rings):
    urban HDL-64E, first 100 frames, APE RMSE 4.9 -> 19.5 cm (11.2 cm with a fixed column
    choice) at 1.8x the frames/s, s = 3: 11.7 cm at 1.3x, no frame lost (s = 3 with a fixed
    column choice ran away when the car started: the standing scans had sampled the same
    azimuths, so the first moving residuals looked lost: 36.9 m); KITTI-raw, 22 real scans:
    per-frame motion vs small_gicp 0.69 -> 1.42 cm mean (max 1.86 -> 3.16) at 4.4x the
    frames/s; OS1-128 thinned 1024 -> 512 columns (min_ring_columns 500), first 100 urban
    frames, front-end position error at the end 7.8 -> 19.8 cm, largest step error 2.6 ->
    10.1 cm at 1.7x (why the floor is 1024). Thin poles and kerbs lose their edge features
    at 0.35 deg: opt in with
    ``max_scan_points: 70000`` where speed matters more than the last centimetres.

    Source covariances know the scan lines (rings) of their support: on open ground a
    16-beam ring is a thin arc, a feature's k neighbours lie on that ring alone, and eq. (1)
    on them claims a sharp "normal" towards the next ring. The ring pattern moves with the
    sensor, so trusting it snapped every scan onto the map's rings (toward zero motion).
    A support from one ring borrows the nearest points of the other rings within
    ``registration.span_distance`` (eq. (1) then sees the surface across the rings); only
    where no other ring is that close is it isotropic at its extent (no trusted direction,
    see ``estimate_covariances``). Supports spanning rings keep eq. (1) as written. The map
    side is the dense map itself (many scans, many rings), so it needs no labels.
    """

    sor: SorConfig = field(default_factory=SorConfig)
    features: FeatureConfig = field(default_factory=_improved_features)
    plausibility: PlausibilityConfig = field(default_factory=_improved_plausibility)
    registration: GicpConfig = field(default_factory=GicpConfig)
    map: LocalMapConfig = field(default_factory=LocalMapConfig)
    edge_voxel: float = 0.2
    plane_voxel: float = 0.4
    covariance_source: str = "features"
    covariance_voxel: float = 0.25
    map_covariance: str = "map"
    map_refresh: str = "neighbours"
    max_registration_points: int = 8000
    max_scan_points: int = 140000
    min_ring_columns: int = 1024

    def __post_init__(self) -> None:
        if self.covariance_source not in ("scan", "features"):
            raise ConfigError("covariance_source must be 'scan' or 'features'")
        if self.map_covariance not in ("map", "scan"):
            raise ConfigError("map_covariance must be 'map' or 'scan'")
        if self.map_refresh not in ("neighbours", "new"):
            raise ConfigError("map_refresh must be 'neighbours' or 'new'")
        if self.max_registration_points < 0:
            raise ConfigError("max_registration_points must be >= 0 (0 = no cap)")
        if self.max_scan_points < 0 or self.min_ring_columns < 0:
            raise ConfigError(
                "max_scan_points and min_ring_columns must be >= 0 (0 = no column stride / "
                "no floor on the columns kept)"
            )


class ImprovedFloam(ScanToMapFrontend):
    """The paper's improved FLOAM front end (plugin name ``improved_floam``)."""

    Config = ImprovedFloamConfig

    def __init__(self, cfg: ImprovedFloamConfig | None = None):
        self.cfg = cfg or ImprovedFloamConfig()
        super().__init__(self.cfg)
        self.map = VoxelHashMap(self.cfg.map, with_covariances=True)
        # features are picked without kappa; the correction runs on the downsampled features
        self._features_no_kappa = replace(self.cfg.features, use_covariance_curvature=False)
        self._n_thinned = 0  # scans thinned by the column stride so far (its phase)

    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        cfg = self.cfg
        raw, raw_ring = scan.xyz, scan.ring
        n_scan, stride = len(raw), 1
        if cfg.max_scan_points and n_scan > cfg.max_scan_points:
            # a scan denser than the paper's sensor: one point per `stride` columns per ring
            t = time.perf_counter()
            if raw_ring is None:
                raw_ring = ring_from_elevation(raw, cfg.features.n_beams, cfg.features.fov_deg)
            kept, stride = thin_scan(
                raw, raw_ring, cfg.max_scan_points, cfg.min_ring_columns, self._n_thinned
            )
            self._n_thinned += 1
            if kept is not None:
                raw, raw_ring = raw[kept], np.asarray(raw_ring)[kept]
            timings["stride_ms"] = (time.perf_counter() - t) * 1e3
        t = time.perf_counter()
        # with the scan's rings: the exact range-image k-NN (same neighbours as a KD-tree)
        nbh = neighbourhoods(raw, cfg.sor.k, ring=raw_ring) if cfg.sor.enabled else None
        keep = apply_sor(raw, cfg.sor, nbh)
        # only what the features need (the scan is deskewed already: no time, no intensity)
        xyz, rings = raw, raw_ring
        if not keep.all():
            xyz = raw[keep]
            rings = None if rings is None else rings[keep]
        timings["sor_ms"] = (time.perf_counter() - t) * 1e3
        extras: dict = {"n_after_sor": int(len(xyz)), "_filtered_xyz": xyz}
        if n_scan > cfg.max_scan_points > 0:
            extras.update(column_stride=stride, n_after_stride=int(len(raw)))

        t = time.perf_counter()
        if rings is None:  # a driver without a ring field: inferred once for both users
            rings = ring_from_elevation(xyz, cfg.features.n_beams, cfg.features.fov_deg)
        rings = np.asarray(rings)
        feats = extract_features(
            xyz,
            rings,
            self._features_no_kappa,
            top_picks=False,
        )
        # thinned in place (no gathered copies): the points voxel_downsample would keep
        e_idx = feats.edge_idx[voxel_thin(xyz, cfg.edge_voxel, feats.edge_idx)]
        p_idx = feats.plane_idx[voxel_thin(xyz, cfg.plane_voxel, feats.plane_idx)]
        if cfg.features.use_covariance_curvature and len(e_idx) + len(p_idx) > 0:
            # curvature correction (paper 000, kappa = tr/||.||_F) on the features actually
            # used: one k-NN query of a few thousand points instead of the whole scan
            q = np.concatenate([e_idx, p_idx])
            k_cov = cfg.features.cov_k
            if nbh is not None and nbh.idx.shape[1] >= min(k_cov, len(raw)):
                # the neighbourhoods SOR searched (raw cloud, self + k): no second k-NN
                q_raw = np.flatnonzero(keep)[q]
                kappa = kappa_from_neighbours(raw, q_raw, nbh.idx[q_raw, :k_cov])
            else:
                kappa = covariance_curvature(xyz, k_cov, query_idx=q)
            n_e = len(e_idx)
            e_idx = e_idx[~(kappa[:n_e] > cfg.features.kappa_edge_max)]
            p_idx = p_idx[~(kappa[n_e:] > cfg.features.kappa_plane_max)]
        src = np.concatenate([xyz[e_idx], xyz[p_idx]])
        extras.update(n_edges=int(len(e_idx)), n_planes=int(len(p_idx)))
        timings["features_ms"] = (time.perf_counter() - t) * 1e3
        if len(src) < 10:
            extras["skipped"] = f"too few features ({len(src)})"
            return Estimate(T_pred, extras=extras)

        t = time.perf_counter()
        rc = cfg.registration
        src_idx = np.concatenate([e_idx, p_idx])
        if cfg.covariance_source == "scan":
            ref_idx = np.concatenate([voxel_thin(xyz, cfg.covariance_voxel), src_idx])
        else:
            ref_idx = src_idx
        # registration on at most max_registration_points of the features (density-aware
        # cap); the map still receives them all
        reg = None
        if cfg.max_registration_points and len(src) > cfg.max_registration_points:
            n_e = len(e_idx)
            keep_e, keep_p = thin_to_count(
                [src[:n_e], src[n_e:]],
                [cfg.edge_voxel, cfg.plane_voxel],
                cfg.max_registration_points,
            )
            reg = np.concatenate([keep_e, n_e + keep_p])
        # "map": the map recomputes the covariances of what it receives, so only the
        # registered points need theirs; "scan": the map keeps the source covariances
        only_reg = reg is not None and cfg.map_covariance == "map"
        covs = estimate_covariances(
            xyz[ref_idx],
            rc.k_covariance,
            rc.lambda_reg,
            rc.covariance_mode,
            query=src[reg] if only_reg else src,
            plane_epsilon=rc.plane_epsilon,
            line_ratio=rc.line_ratio,
            labels=rings[ref_idx],
            span_distance=rc.span_distance,
            threads=rc.threads,
        )
        if reg is None:
            src_reg, covs_reg, covs_map = src, covs, covs
        elif only_reg:
            src_reg, covs_reg = src[reg], covs
            # placeholders for the unregistered points: replaced by the map's eq. (1)
            covs_map = np.tile(np.eye(3) * cfg.plane_voxel**2, (len(src), 1, 1))
            covs_map[reg] = covs
        else:
            src_reg, covs_reg, covs_map = src[reg], covs[reg], covs
        extras["n_registered"] = int(len(src_reg))
        timings["covariance_ms"] = (time.perf_counter() - t) * 1e3

        t = time.perf_counter()
        est = Estimate(T_pred, extras=extras)
        if len(self.map) >= 10:
            # the map answers the nearest-neighbour queries through its voxel hash: no KD-tree
            target = GicpTarget(self.map.points, self.map.covs, tree=self.map)
            T0 = T_pred
            if wide:  # tracking lost: coarse pass from the prediction with a wider search
                d = rc.max_correspondence * cfg.recovery_correspondence_factor
                coarse = replace(rc, max_correspondence=d)
                T0 = gicp_align(src_reg, target, T_pred, coarse, source_covs=covs_reg)
                T0 = T0.T_target_source
            res = gicp_align(src_reg, target, T0, rc, source_covs=covs_reg)
            est = Estimate.from_registration(res, extras)
        est.pending = (src, covs_map)
        timings["registration_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def _map_size(self) -> int:
        return len(self.map)

    def _insert(self, est: Estimate, timings: dict) -> None:
        cfg, rc = self.cfg, self.cfg.registration
        src, covs = est.pending
        T = est.pose
        R = T[:3, :3]
        refresh = cfg.map_covariance == "map"
        if refresh:  # the map computes the new rows' covariances below: no rotated copies
            rotated = np.broadcast_to(np.eye(3), covs.shape)
        else:
            rotated = np.einsum("ij,njk,lk->nil", R, covs, R)
        n_new = self.map.add(src @ R.T + T[:3, 3], rotated, T[:3, 3])
        if refresh and n_new and len(self.map) < rc.k_covariance:  # too few points for eq. (1)
            acc = self.map.last_accepted
            self.map.covs[len(self.map) - n_new :] = np.einsum("ij,njk,lk->nil", R, covs[acc], R)
        if cfg.map_covariance == "map" and n_new and len(self.map) >= rc.k_covariance:
            # eq. (1) on the map: the new points and every map point having one of them among
            # its k neighbours get their covariance (re)computed from the current map
            n_old = len(self.map) - n_new
            new = np.arange(n_old, len(self.map))
            pts = self.map.points
            _, nb = self.map.query(pts[new], k=rc.k_covariance)
            dirty, nb_dirty = new, nb
            if cfg.map_refresh == "neighbours":
                # the old points among the new points' neighbours; the new ones (the last
                # rows) reuse the query above
                mark = np.zeros(n_old, dtype=bool)
                mark[nb[nb < n_old]] = True
                old = np.flatnonzero(mark)  # np.unique(nb[nb < n_old]) without its hash pass
                _, nb_old = self.map.query(pts[old], k=rc.k_covariance)
                dirty = np.concatenate([old, new])
                nb_dirty = np.concatenate([nb_old.reshape(-1, nb.shape[1]), nb])
            self.map.covs[dirty] = estimate_covariances(
                pts,
                rc.k_covariance,
                rc.lambda_reg,
                rc.covariance_mode,
                query=pts[dirty],
                plane_epsilon=rc.plane_epsilon,
                line_ratio=rc.line_ratio,
                threads=rc.threads,
                neighbours=nb_dirty,
            )
