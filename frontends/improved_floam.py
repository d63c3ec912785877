"""Improved FLOAM (paper 000, section 2.1, Figure 1): weighted density-adaptive SOR ->
curvature-corrected LOAM edge/plane features -> GICP scan-to-map on the features (with
per-point covariances, eqs. (1)-(5)) against an incrementally updated local map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from frontends.improved_floam_filter import Filtered, ScanFilter
from slam.deferred import Deferred, numba_threads
from slam.errors import ConfigError
from slam.features.curvature import covariance_curvature, kappa_from_neighbours
from slam.features.loam import FeatureConfig, extract_features, ring_from_elevation
from slam.features.thinning import thin_to_count, voxel_thin
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.mapping.stale_covariances import FreshCovarianceMap, mark_stale
from slam.odometry import CommonConfig, Estimate, ScanToMapFrontend
from slam.preprocess.sor import SorConfig
from slam.registration.gicp import (
    GicpConfig,
    GicpTarget,
    RegistrationResult,
    estimate_covariances,
    gicp_align,
)
from slam.registration.plausibility import PlausibilityConfig
from slam.types import Scan


class CovarianceSource(Enum):
    """Where a source feature's eq. (1) neighbours come from: the feature set itself, or
    the whole filtered scan voxel-downsampled to ``covariance_voxel``."""

    FEATURES = "features"
    SCAN = "scan"


class MapCovariance(Enum):
    """Covariances of new map points: from their k neighbours in the map (eq. (1) on the
    dense map, refreshed as it fills in), or the source covariances rotated into it."""

    MAP = "map"
    SCAN = "scan"


class MapRefresh(Enum):
    """Which map covariances are recomputed on insertion: the new points and their map
    neighbours, or only the new points."""

    NEIGHBOURS = "neighbours"
    NEW = "new"
    ON_USE = "on_use"  # neighbours flagged stale, recomputed when a registration reaches them


def _choice(kind: type[Enum], value: str, key: str) -> Enum:
    """``value`` as a member of ``kind``, or a ConfigError naming ``key`` and the choices."""
    try:
        return kind(value)
    except ValueError:
        names = " or ".join(repr(m.value) for m in kind)
        raise ConfigError(f"{key} must be {names}, got {value!r}") from None


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
    map_refresh_thread: the map refresh of scan n runs on a worker thread while scan n + 1 is
    filtered and its features found, and is waited for before scan n + 1 registers (the
    same poses as inline, ``slam.deferred``); false: inline.
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
    map_refresh_thread: bool = True
    filter_ahead: bool = True  # the next scan's stride and SOR on a worker thread
    max_registration_points: int = 8000
    max_scan_points: int = 140000
    min_ring_columns: int = 1024

    def __post_init__(self) -> None:
        self.strategies()  # the choices are checked here, at load
        if self.max_registration_points < 0:
            raise ConfigError("max_registration_points must be >= 0 (0 = no cap)")
        if self.max_scan_points < 0 or self.min_ring_columns < 0:
            raise ConfigError(
                "max_scan_points and min_ring_columns must be >= 0 (0 = no column stride / "
                "no floor on the columns kept)"
            )

    def strategies(self) -> tuple[CovarianceSource, MapCovariance, MapRefresh]:
        """The three strategy choices (kept as strings in the recipe) as enums."""
        return (
            _choice(CovarianceSource, self.covariance_source, "covariance_source"),
            _choice(MapCovariance, self.map_covariance, "map_covariance"),
            _choice(MapRefresh, self.map_refresh, "map_refresh"),
        )


@dataclass
class FeatureCloud:
    """Sensor-frame features (m) with their eq. (1) covariances: what the map receives.
    covs: of ``points[rows]`` (rows None: of every point); registered: the indices of the
    points registered (None: all)."""

    points: np.ndarray
    covs: np.ndarray
    rows: np.ndarray | None = None
    registered: np.ndarray | None = None

    def registration_source(self) -> tuple[np.ndarray, np.ndarray]:
        """The registered points and their covariances."""
        if self.registered is None:
            return self.points, self.covs
        covs = self.covs if self.rows is not None else self.covs[self.registered]
        return self.points[self.registered], covs

    def all_covs(self, sigma: float) -> np.ndarray:
        """(N, 3, 3) covariances of every point; isotropic ``sigma`` (m) where none was
        computed."""
        if self.rows is None:
            return self.covs
        out = np.tile(np.eye(3) * sigma**2, (len(self.points), 1, 1))
        out[self.rows] = self.covs
        return out


class ImprovedFloam(ScanToMapFrontend):
    """The paper's improved FLOAM front end (plugin name ``improved_floam``)."""

    Config = ImprovedFloamConfig

    def __init__(self, cfg: ImprovedFloamConfig | None = None):
        self.cfg = cfg or ImprovedFloamConfig()
        super().__init__(self.cfg)
        self._map = VoxelHashMap(self.cfg.map, with_covariances=True)
        self._fresh = FreshCovarianceMap(self._map, self._map_covariances)
        # the map covariances of scan n are refreshed while scan n + 1 is filtered
        self._map_job = Deferred(self.cfg.map_refresh_thread, "map-refresh")
        self._map_job_ms = 0.0  # the last refresh's own wall time
        self._cov_source, self._map_cov, self._refresh = self.cfg.strategies()
        # features are picked without kappa; the correction runs on the downsampled features
        self._features_no_kappa = replace(self.cfg.features, use_covariance_curvature=False)
        # stride and SOR before deskew, the next scan's on a worker thread meanwhile
        self._scan_filter = ScanFilter(self.cfg, threaded=self.cfg.filter_ahead)
        self._filtered: Filtered | None = None

    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        # the map refresh of the previous scan runs on the other core meanwhile
        with numba_threads(1 if self._map_job.pending else None):
            est = self._prepare(scan, T_pred, timings)
        if est.skipped is not None:
            return est
        src, covs = est.pending.registration_source()
        timings["map_wait_ms"] = self._map_job.wait() * 1e3
        timings["map_refresh_ms"] = self._map_job_ms
        t = time.perf_counter()
        if len(self._map) >= 10:
            est.result = self._align(src, covs, T_pred, wide)
            est.pose = est.result.T_target_source
        timings["registration_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def _prepare(self, scan: Scan, T_pred: np.ndarray, timings: dict) -> Estimate:
        """SOR, features and their covariances (``est.pending``): everything before the
        registration, none of it reading the map."""
        flt = self._filtered.moved_to(scan.xyz)  # the filter's decisions, deskewed points
        counts: dict = {"n_after_sor": int(len(flt.xyz))}
        if flt.stride is not None:
            counts.update(column_stride=flt.stride, n_after_stride=int(len(flt.raw)))
        est = Estimate(T_pred, filtered=flt.xyz, counts=counts)

        t = time.perf_counter()
        rings, fc = flt.rings, self.cfg.features
        if rings is None:  # a driver without a ring field: inferred once for both users
            rings = ring_from_elevation(flt.xyz, fc.n_beams, fc.fov_deg)
        rings = np.asarray(rings)
        e_idx, p_idx = self._feature_indices(flt, rings)
        counts.update(n_edges=int(len(e_idx)), n_planes=int(len(p_idx)))
        timings["features_ms"] = (time.perf_counter() - t) * 1e3
        if len(e_idx) + len(p_idx) < 10:
            est.skipped = f"too few features ({len(e_idx) + len(p_idx)})"
            return est

        t = time.perf_counter()
        est.pending = self._feature_cloud(flt.xyz, rings, e_idx, p_idx)
        counts["n_registered"] = int(len(est.pending.registration_source()[0]))
        timings["covariance_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def look_ahead(self, scan: Scan) -> None:
        self._scan_filter.ahead(scan)

    def _before_deskew(self, scan: Scan, work: Scan, timings: dict) -> None:
        self._filtered, waited = self._scan_filter.get(scan, work)
        timings.update(self._filtered.timings)
        timings["filter_wait_ms"] = waited * 1e3

    def _feature_indices(self, flt: Filtered, rings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Edge and plane indices into ``flt.xyz``: LOAM features voxel-thinned in place, then
        the curvature correction (paper 000, kappa = tr/||.||_F) on the features kept."""
        cfg, fc, xyz = self.cfg, self.cfg.features, flt.xyz
        feats = extract_features(xyz, rings, self._features_no_kappa, top_picks=False)
        e_idx = feats.edge_idx[voxel_thin(xyz, cfg.edge_voxel, feats.edge_idx)]
        p_idx = feats.plane_idx[voxel_thin(xyz, cfg.plane_voxel, feats.plane_idx)]
        if not fc.use_covariance_curvature or len(e_idx) + len(p_idx) == 0:
            return e_idx, p_idx
        q = np.concatenate([e_idx, p_idx])
        nbh = flt.nbh
        if nbh is not None and nbh.idx.shape[1] >= min(fc.cov_k, len(flt.raw)):
            # the neighbourhoods SOR searched (raw cloud, self + k): no second k-NN
            q_raw = np.flatnonzero(flt.keep)[q]
            kappa = kappa_from_neighbours(flt.raw, q_raw, nbh.idx[q_raw, : fc.cov_k])
        else:
            kappa = covariance_curvature(xyz, fc.cov_k, query_idx=q)
        n_e = len(e_idx)
        e_idx = e_idx[~(kappa[:n_e] > fc.kappa_edge_max)]
        p_idx = p_idx[~(kappa[n_e:] > fc.kappa_plane_max)]
        return e_idx, p_idx

    def _feature_cloud(
        self, xyz: np.ndarray, rings: np.ndarray, e_idx: np.ndarray, p_idx: np.ndarray
    ) -> FeatureCloud:
        """The features with their covariances (eq. (1), ring-aware supports) and, above
        ``max_registration_points``, the density-aware subset that is registered; with map
        covariances from the map only the registered points need theirs."""
        cfg, rc = self.cfg, self.cfg.registration
        src = np.concatenate([xyz[e_idx], xyz[p_idx]])
        src_idx = np.concatenate([e_idx, p_idx])
        ref_idx = src_idx
        if self._cov_source is CovarianceSource.SCAN:
            ref_idx = np.concatenate([voxel_thin(xyz, cfg.covariance_voxel), src_idx])
        reg = None
        if cfg.max_registration_points and len(src) > cfg.max_registration_points:
            n_e = len(e_idx)
            keep_e, keep_p = thin_to_count(
                [src[:n_e], src[n_e:]],
                [cfg.edge_voxel, cfg.plane_voxel],
                cfg.max_registration_points,
            )
            reg = np.concatenate([keep_e, n_e + keep_p])
        rows = reg if self._map_cov is MapCovariance.MAP else None
        covs = estimate_covariances(
            xyz[ref_idx],
            rc.k_covariance,
            rc.lambda_reg,
            rc.covariance_mode,
            query=src if rows is None else src[rows],
            plane_epsilon=rc.plane_epsilon,
            line_ratio=rc.line_ratio,
            labels=rings[ref_idx],
            span_distance=rc.span_distance,
            threads=rc.threads,
        )
        return FeatureCloud(src, covs, rows, reg)

    def _align(
        self, src: np.ndarray, covs: np.ndarray, T_pred: np.ndarray, wide: bool
    ) -> RegistrationResult:
        """GICP against the map (its voxel hash answers the neighbour queries) from
        ``T_pred``; ``wide``: a coarse pass with a wider search first."""
        rc = self.cfg.registration
        tree = self._fresh if self._refresh is MapRefresh.ON_USE else self._map
        target = GicpTarget(self._map.points, self._map.covs, tree=tree)
        T0 = T_pred
        if wide:  # tracking lost: coarse pass from the prediction with a wider search
            d = rc.max_correspondence * self.cfg.recovery_correspondence_factor
            coarse = replace(rc, max_correspondence=d)
            T0 = gicp_align(src, target, T_pred, coarse, source_covs=covs).T_target_source
        return gicp_align(src, target, T0, rc, source_covs=covs)

    @property
    def map(self) -> VoxelHashMap:
        """The local map, once its pending covariance refresh is done."""
        self._map_job.wait()
        self._fresh.refresh()
        return self._map

    def close(self) -> None:
        """Finish the pending jobs and stop the worker threads."""
        self._map_job.close()
        self._scan_filter.close()

    def _map_size(self) -> int:
        return len(self._map)

    def _insert(self, est: Estimate[FeatureCloud], timings: dict) -> None:
        cfg, rc = self.cfg, self.cfg.registration
        self._map_job.wait()
        fc, T = est.pending, est.pose
        R = T[:3, :3]
        from_map = self._map_cov is MapCovariance.MAP
        if from_map:  # the map computes the new rows' covariances below: no rotated copies
            rotated = np.broadcast_to(np.eye(3), (len(fc.points), 3, 3))
        else:
            rotated = np.einsum("ij,njk,lk->nil", R, fc.covs, R)
        n_new = self._map.add(fc.points @ R.T + T[:3, 3], rotated, T[:3, 3])
        if not (from_map and n_new):
            return
        if len(self._map) < rc.k_covariance:  # too few points for eq. (1): the source's
            acc = self._map.last_accepted
            covs = fc.all_covs(cfg.plane_voxel)[acc]
            self._map.covs[len(self._map) - n_new :] = np.einsum("ij,njk,lk->nil", R, covs, R)
        else:
            self._map_job.submit(lambda: self._timed_refresh(n_new))

    def _timed_refresh(self, n_new: int) -> None:
        t = time.perf_counter()
        with numba_threads(1):  # the calling thread filters the next scan meanwhile
            self._refresh_map_covariances(n_new)
        self._map_job_ms = (time.perf_counter() - t) * 1e3

    def _refresh_map_covariances(self, n_new: int) -> None:
        """Eq. (1) on the map: the ``n_new`` newest points and (``map_refresh`` neighbours)
        every map point having one of them among its k neighbours get their covariance
        (re)computed from the current map."""
        rc = self.cfg.registration
        n_old = len(self._map) - n_new
        new = np.arange(n_old, len(self._map))
        pts = self._map.points
        _, nb = self._map.query(pts[new], k=rc.k_covariance)
        dirty, nb_dirty = new, nb
        if self._refresh is MapRefresh.ON_USE:
            # the old points among the new points' neighbours wait for their first use
            old = nb[nb < n_old]
            mark_stale(self._map.covs, old)
        elif self._refresh is MapRefresh.NEIGHBOURS:
            # the old points among the new points' neighbours; the new ones (the last rows)
            # reuse the query above
            mark = np.zeros(n_old, dtype=bool)
            mark[nb[nb < n_old]] = True
            old = np.flatnonzero(mark)  # np.unique(nb[nb < n_old]) without its hash pass
            _, nb_old = self._map.query(pts[old], k=rc.k_covariance)
            dirty = np.concatenate([old, new])
            nb_dirty = np.concatenate([nb_old.reshape(-1, nb.shape[1]), nb])
        self._map.covs[dirty] = self._map_covariances(dirty, nb_dirty)

    def _map_covariances(
        self, rows: np.ndarray, neighbours: np.ndarray | None = None
    ) -> np.ndarray:
        """Eq. (1) for map ``rows`` from their k nearest map points (queried when not given)."""
        rc, pts = self.cfg.registration, self._map.points
        if neighbours is None:
            _, neighbours = self._map.query(pts[rows], k=rc.k_covariance)
        return estimate_covariances(
            pts,
            rc.k_covariance,
            rc.lambda_reg,
            rc.covariance_mode,
            query=pts[rows],
            plane_epsilon=rc.plane_epsilon,
            line_ratio=rc.line_ratio,
            threads=rc.threads,
            neighbours=neighbours,
        )
