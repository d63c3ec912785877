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
from slam.features.scatter import (
    ALONG_ROAD,
    OpenRoadGate,
    ScatterConfig,
    horizontal_observability,
    scatter_points,
)
from slam.features.thinning import thin_to_count, voxel_thin
from slam.mapping.local_map import LocalMapConfig, VoxelHashMap
from slam.mapping.second_sighting import SecondSighting
from slam.mapping.stale_covariances import FreshCovarianceMap, mark_stale
from slam.odometry import CommonConfig, Estimate, ScanToMapFrontend
from slam.odometry.config import check_positive
from slam.preprocess.sor import SorConfig
from slam.registration import kernels
from slam.registration.covariances import add_beam_angle_noise
from slam.registration.gicp import (
    GicpConfig,
    GicpTarget,
    RegistrationResult,
    estimate_covariances,
    gicp_align,
    robust_weights,
)
from slam.registration.ground_plane import (
    GroundPlaneConfig,
    enough_beams,
    fit_ground,
    flatten_ground,
    on_ground,
)
from slam.registration.plausibility import PlausibilityConfig, prediction_bound
from slam.registration.pose_prior import MotionPriorConfig, PosePrior
from slam.registration.se3 import transform
from slam.sensor.beam_calibration import BeamCalibration, BeamCalibrationConfig
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


def _improved_motion_prior() -> MotionPriorConfig:
    return MotionPriorConfig(enabled=True)


def _improved_plausibility() -> PlausibilityConfig:
    """The gate with a 0.1 m per-frame floor off the constant-velocity prediction (the common
    default is 0.3 m): GICP pulled along a plain corridor by people walking in it creeps
    unnoticed at 0.3 m (docs/robustness.md, "Pulled along a corridor")."""
    return PlausibilityConfig(prediction_floor=0.1)


@dataclass
class ImprovedFloamConfig(CommonConfig):
    """Improved FLOAM settings (paper 000); distances in m. Why the defaults: docs/paper000.md
    (GICP settings) and docs/speed.md (64 beams).

    edge_voxel / plane_voxel: voxel-thin the feature sets before registration (the paper
    registers 800-1200 features per frame).
    covariance_source: source covariances (eq. (1)) from the voxel-thinned "features"
    (default) or from the whole filtered "scan" voxel-downsampled to covariance_voxel.
    map_covariance: new map points get eq. (1) from their neighbours in the "map" (default)
    or keep the "scan" covariances rotated into the map.
    map_refresh: recompute the new points, and their map neighbours "on_use" (default: flagged
    stale, recomputed when a registration first reaches them, ``slam.mapping.stale_covariances``)
    or at once ("neighbours"), or the "new" points only. map_refresh_thread: refresh the
    map of scan n on a worker thread while scan n + 1 is prepared (same poses as inline).
    filter_ahead: the column stride and SOR of scan n + 1 (judged before deskew) run on a
    worker thread while scan n registers (same poses as inline, ``ScanFilter``).
    max_registration_points: above this many thinned features GICP registers a
    density-aware subset (``thin_to_count``); covariances and the map still use all (0 = all).
    coarse_points: the coarse pass of a wide search (first motion, lost tracking) registers
    every s-th of them, at most this many (0 = all); the fine pass registers all.
    max_scan_points / min_ring_columns: a scan of more points keeps one point per
    s = ceil(n / max_scan_points) azimuth columns of each ring, every ring kept, at least
    min_ring_columns per ring (``slam.preprocess.column_stride``, before SOR; 0 = never).
    motion_prior: the tracked constant-velocity prediction as a Gaussian prior of GICP
    (``slam.registration.pose_prior``): it holds the directions a plain street leaves
    unobserved.
    beam_calibration: per-beam elevation, azimuth and range offsets learned from the accepted
    registrations and applied to the filtered points (``slam.sensor.beam_calibration``).
    Source covariances know the rings of their support: a one-ring support borrows the other
    rings' points within ``registration.span_distance`` (``estimate_covariances``).
    ground: source features on the scan's ground plane constrain only along its normal
    (``slam.registration.ground_plane``; sensors of ``ground.min_beams`` or more): the rings'
    pattern moves with the sensor.
    scatter: the open-road mode (``slam.features.scatter``): also register the points LOAM's
    selection leaves out (vegetation, clutter) off the ground, the ground a plane on any
    sensor; ``mode`` auto switches it by the recent scans' ``along_road`` (1 below
    ``slam.features.scatter.ALONG_ROAD`` of ``horizontal_observability``), which every scan
    reports with ``open_road``.
    young_map_scans / young_map_correspondence: while the map holds fewer scans, a tracked
    registration pairs within the gate's bound off the prediction (at least that many m)
    instead of ``registration.max_correspondence`` (``_correspondence``; 0 scans = off).
    """

    sor: SorConfig = field(default_factory=SorConfig)
    features: FeatureConfig = field(default_factory=_improved_features)
    plausibility: PlausibilityConfig = field(default_factory=_improved_plausibility)
    registration: GicpConfig = field(default_factory=GicpConfig)
    map: LocalMapConfig = field(default_factory=LocalMapConfig)
    beam_calibration: BeamCalibrationConfig = field(default_factory=BeamCalibrationConfig)
    motion_prior: MotionPriorConfig = field(default_factory=_improved_motion_prior)
    ground: GroundPlaneConfig = field(default_factory=GroundPlaneConfig)
    scatter: ScatterConfig = field(default_factory=ScatterConfig)
    edge_voxel: float = 0.2
    plane_voxel: float = 0.4
    covariance_source: str = "features"
    covariance_voxel: float = 0.25
    map_covariance: str = "map"
    map_refresh: str = "on_use"
    map_refresh_thread: bool = True
    filter_ahead: bool = True
    max_registration_points: int = 8000
    coarse_points: int = 2000
    max_scan_points: int = 140000
    min_ring_columns: int = 1024
    young_map_scans: int = 10
    young_map_correspondence: float = 0.3

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive(self, "frontend", ("edge_voxel", "plane_voxel", "covariance_voxel"))
        self.strategies()  # the choices are checked here, at load
        if self.young_map_scans < 0 or self.young_map_correspondence <= 0:
            raise ConfigError("young_map_scans must be >= 0 and young_map_correspondence > 0 m")
        if self.max_registration_points < 0 or self.coarse_points < 0:
            raise ConfigError("max_registration_points and coarse_points must be >= 0 (0 = no cap)")
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
    points registered (None: all); n_features: the points before it are edges and planes,
    the rest the open-road mode's scatter points (None: all are features)."""

    points: np.ndarray
    covs: np.ndarray
    rows: np.ndarray | None = None
    registered: np.ndarray | None = None
    rings: np.ndarray | None = None  # the beam of each point
    n_features: int | None = None
    # the open-road mode's ground plane (n, d: n.x + d = 0) and whether the mode was on
    plane: tuple[np.ndarray, float] | None = None
    open_road: bool = False

    def scatter(self) -> np.ndarray:
        """The open-road mode's scatter points (M, 3, sensor frame; M may be 0)."""
        return self.points[len(self.points) if self.n_features is None else self.n_features :]

    def registered_rings(self) -> np.ndarray | None:
        """The beams of the registered points."""
        if self.rings is None or self.registered is None:
            return self.rings
        return self.rings[self.registered]

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
        self._calibration = BeamCalibration(self.cfg.beam_calibration)
        self._open_road = OpenRoadGate(self.cfg.scatter)
        sc = self.cfg.scatter
        self._sighting = SecondSighting(sc.confirm_distance, sc.confirm_height)
        self._inserted_scans = 0  # scans the map holds (a young map pairs ring samples)

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
            est.result = self._align(src, covs, T_pred, wide, self._motion_prior(T_pred))
            est.pose = est.result.T_target_source
            est.evidence = self._scatter_evidence(est.pending, est.pose)
        timings["registration_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def _prepare(self, scan: Scan, T_pred: np.ndarray, timings: dict) -> Estimate:
        """SOR, features and their covariances (``est.pending``): everything before the
        registration, none of it reading the map."""
        flt = self._filtered.moved_to(scan.xyz)  # the filter's decisions, deskewed points
        counts: dict = {"n_after_sor": int(len(flt.xyz))}
        if flt.stride is not None:
            counts.update(column_stride=flt.stride, n_after_stride=int(len(flt.raw)))

        t = time.perf_counter()
        rings, fc = flt.rings, self.cfg.features
        if rings is None:  # a driver without a ring field: inferred once for both users
            rings = ring_from_elevation(flt.xyz, fc.n_beams, fc.fov_deg)
        rings = np.asarray(rings)
        flt = replace(flt, xyz=self._calibration.correct(flt.xyz, rings))
        est = Estimate(T_pred, filtered=flt.xyz, counts=counts)
        e_idx, p_idx, candidates = self._feature_indices(flt, rings)
        counts.update(n_edges=int(len(e_idx)), n_planes=int(len(p_idx)))
        timings["features_ms"] = (time.perf_counter() - t) * 1e3
        if len(e_idx) + len(p_idx) < 10:
            est.skipped = f"too few features ({len(e_idx) + len(p_idx)})"
            return est

        t = time.perf_counter()
        gc, gate = self.cfg.ground, self._open_road
        plane = fit_ground(flt.xyz, gc) if gc.enabled else None
        first, open_road = gate.unjudged, gate.on
        build = (flt.xyz, rings, e_idx, p_idx, candidates, plane)
        est.pending = self._open_road_cloud(*build, open_road)
        seen = self._observability(est.pending, plane)
        gate.update(seen < ALONG_ROAD)
        starting = self._starting()
        if (first and gate.on != open_road) or (starting and not open_road):
            # the first scan of a run is judged by itself; a start by what shows the motion
            open_road = gate.on or starting
            est.pending = self._open_road_cloud(*build, open_road)
        counts.update(
            horizontal_observability=seen,
            along_road=int(seen < ALONG_ROAD),
            open_road=int(open_road),
            scatter_points=int(len(est.pending.scatter())),
            n_registered=int(len(est.pending.registration_source()[0])),
        )
        timings["covariance_ms"] = (time.perf_counter() - t) * 1e3
        return est

    def _starting(self) -> bool:
        """Whether this scan is built in the open-road mode because the motion is not known
        yet (``scatter.at_start``: the first scan and the first-motion search)."""
        sc = self.cfg.scatter
        return sc.at_start and sc.mode == "auto" and self.gate.n_trusted < 2

    def _observability(self, fc: FeatureCloud, plane: tuple[np.ndarray, float] | None) -> float:
        """``horizontal_observability`` of the registered features (not the scatter points)
        of ``fc`` off the ground ``plane``: flattened or not, the ground observes no
        horizontal motion, so every sensor is judged alike. At most ~500 covariances (an
        even subsample, ~1 ms): a statistic of the scan."""
        src, covs = fc.registration_source()
        reg = np.arange(len(fc.points)) if fc.registered is None else fc.registered
        keep = reg < len(fc.points) - len(fc.scatter())
        if plane is not None:
            keep &= ~on_ground(src, plane, self.cfg.ground.band)
        rows = np.flatnonzero(keep)
        return horizontal_observability(covs[rows[:: max(1, len(rows) // 500)]])

    def _open_road_cloud(
        self,
        xyz: np.ndarray,
        rings: np.ndarray,
        e_idx: np.ndarray,
        p_idx: np.ndarray,
        candidates: np.ndarray,
        plane: tuple[np.ndarray, float] | None,
        open_road: bool,
    ) -> FeatureCloud:
        """``_feature_cloud`` of the features and, in the open-road mode, the scatter points
        after them with the ground a plane on any sensor."""
        extra = np.zeros(0, dtype=np.int64)
        if open_road:
            extra = scatter_points(xyz, candidates, plane, self.cfg.scatter)
        flatten = plane if open_road or enough_beams(rings, self.cfg.ground) else None
        fc = self._feature_cloud(xyz, rings, e_idx, np.concatenate([p_idx, extra]), flatten)
        fc.n_features = len(e_idx) + len(p_idx)
        fc.plane, fc.open_road = (plane if open_road else None), open_road
        return fc

    def _scan_state(self) -> object:
        return self._open_road.state()

    def _restore_scan_state(self, state: object) -> None:
        self._open_road.restore(state)

    def _scatter_evidence(self, fc: FeatureCloud, T: np.ndarray) -> tuple[int, float] | None:
        """(pairs, RMSE m) of the open-road mode's scatter points at pose ``T`` against the
        map (nearest point within ``max_correspondence``): the start search judges a start
        by them, as the features' ring samples fit the pose at rest as well as the moving
        one (docs/robustness.md, "16 beams on a motorway"). None outside the mode."""
        pts = fc.scatter()
        if not len(pts):
            return None
        d, _ = self._map.query(
            transform(T, pts), distance_upper_bound=self.cfg.registration.max_correspondence
        )
        d = d[np.isfinite(d)]
        return int(len(d)), float(np.sqrt(np.mean(d**2))) if len(d) else np.inf

    def look_ahead(self, scan: Scan) -> None:
        self._scan_filter.ahead(scan)

    def _before_deskew(self, scan: Scan, work: Scan, timings: dict) -> None:
        self._filtered, waited = self._scan_filter.get(scan, work)
        timings.update(self._filtered.timings)
        timings["filter_wait_ms"] = waited * 1e3

    def _feature_indices(
        self, flt: Filtered, rings: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Edge and plane indices into ``flt.xyz``: LOAM features voxel-thinned in place, then
        the curvature correction (paper 000, kappa = tr/||.||_F) on the features kept; and
        the (N,) mask of every edge or plane candidate before thinning."""
        cfg, fc, xyz = self.cfg, self.cfg.features, flt.xyz
        feats = extract_features(xyz, rings, self._features_no_kappa, top_picks=False)
        candidates = np.zeros(len(xyz), dtype=bool)
        candidates[feats.edge_idx] = True
        candidates[feats.plane_idx] = True
        e_idx = feats.edge_idx[voxel_thin(xyz, cfg.edge_voxel, feats.edge_idx)]
        p_idx = feats.plane_idx[voxel_thin(xyz, cfg.plane_voxel, feats.plane_idx)]
        if not fc.use_covariance_curvature or len(e_idx) + len(p_idx) == 0:
            return e_idx, p_idx, candidates
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
        return e_idx, p_idx, candidates

    def _feature_cloud(
        self,
        xyz: np.ndarray,
        rings: np.ndarray,
        e_idx: np.ndarray,
        p_idx: np.ndarray,
        plane: tuple[np.ndarray, float] | None,
    ) -> FeatureCloud:
        """The features with their covariances (eq. (1), ring-aware supports) and, above
        ``max_registration_points``, the density-aware subset that is registered; with map
        covariances from the map only the registered points need theirs. plane: the ground
        the features are flattened on (``flatten_ground``), or None."""
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
            rc.regularisation,
            rc.covariance_mode,
            query=src if rows is None else src[rows],
            plane_epsilon=rc.plane_epsilon,
            line_ratio=rc.line_ratio,
            labels=rings[ref_idx],
            span_distance=rc.span_distance,
            threads=rc.threads,
        )
        q = src if rows is None else src[rows]
        if plane is not None:
            flatten_ground(q, covs, plane, cfg.ground)
        covs = add_beam_angle_noise(q, covs, np.radians(rc.beam_angle_noise))
        return FeatureCloud(src, covs, rows, reg, rings[src_idx])

    def _motion_prior(self, T_pred: np.ndarray) -> PosePrior | None:
        """The tracked prediction as a prior of the registration (``motion_prior``), or None."""
        if not self.cfg.motion_prior.enabled or self.tracked_horizon is None:
            return None
        return self.cfg.motion_prior.prior(T_pred, self.tracked_horizon)

    def _align(
        self,
        src: np.ndarray,
        covs: np.ndarray,
        T_pred: np.ndarray,
        wide: bool,
        prior: PosePrior | None = None,
    ) -> RegistrationResult:
        """GICP against the map (its voxel hash answers the neighbour queries) from
        ``T_pred``; ``wide``: a coarse pass with a wider search first; ``prior``: on the pose."""
        rc = self._correspondence()
        tree = self._fresh if self._refresh is MapRefresh.ON_USE else self._map
        target = GicpTarget(self._map.points, self._map.covs, tree=tree)
        T0 = T_pred
        if wide:  # tracking lost: coarse pass from the prediction with a wider search
            d = rc.max_correspondence * self.cfg.recovery_correspondence_factor
            coarse = replace(rc, max_correspondence=d)
            step = 1
            if self.cfg.coarse_points and len(src) > self.cfg.coarse_points:
                step = -(-len(src) // self.cfg.coarse_points)
            T0 = gicp_align(
                src[::step], target, T_pred, coarse, source_covs=covs[::step]
            ).T_target_source
        return gicp_align(src, target, T0, rc, source_covs=covs, prior=prior)

    def _correspondence(self) -> GicpConfig:
        """The GICP settings, with the pairing distance cut to what the tracked prediction
        may be off (the gate's bound over the frame, at least ``young_map_correspondence``
        m) while the map holds fewer than ``young_map_scans`` scans: there its surfaces are
        a few scans' ring samples metres apart, and a wide pairing distance pairs more of
        them the nearer the scan slides back to where the rings coincide, at rest. Searches
        (no tracked velocity) keep the whole distance."""
        rc, cfg = self.cfg.registration, self.cfg
        if self._inserted_scans >= cfg.young_map_scans or self.tracked_horizon is None:
            return rc
        bound = prediction_bound(cfg.plausibility, self.tracked_horizon)
        return replace(
            rc,
            max_correspondence=min(rc.max_correspondence, max(bound, cfg.young_map_correspondence)),
        )

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
        if self.cfg.beam_calibration.enabled:
            self._calibrate(fc, T)
        world = fc.points @ R.T + T[:3, 3]
        rows = self._confirmed(fc, world)
        if fc.open_road:  # every scan of the mode, so the run's mean is the mode's share
            est.counts["unconfirmed"] = 0 if rows is None else int(len(world) - len(rows))
        if rows is not None:
            world, rotated = world[rows], rotated[rows]
        n_new = self._map.add(world, rotated, T[:3, 3])
        self._inserted_scans += 1
        if not (from_map and n_new):
            return
        if len(self._map) < rc.k_covariance:  # too few points for eq. (1): the source's
            acc = self._map.last_accepted
            covs = fc.all_covs(cfg.plane_voxel)
            covs = (covs if rows is None else covs[rows])[acc]
            self._map.covs[len(self._map) - n_new :] = np.einsum("ij,njk,lk->nil", R, covs, R)
        else:
            self._map_job.submit(lambda: self._timed_refresh(n_new))

    def _confirmed(self, fc: FeatureCloud, world: np.ndarray) -> np.ndarray | None:
        """In the open-road mode, the rows of ``world`` (the scan's points in the odometry
        frame) that the previous inserted scan confirms, the ground always
        (``SecondSighting``); None: every row (the mode off, or all confirmed)."""
        if not (fc.open_road and self.cfg.scatter.confirm_distance > 0):
            self._sighting.reset()
            return None
        ground = np.zeros(len(world), dtype=bool)
        if fc.plane is not None:
            ground = on_ground(fc.points, fc.plane, self.cfg.ground.band)
        keep = self._sighting.keep(world, ground)
        return None if keep.all() else np.flatnonzero(keep)

    def _calibrate(self, fc: FeatureCloud, T: np.ndarray) -> None:
        """Measure the beams' offsets on the accepted registration at ``T``: its registered
        points paired with the map as GICP pairs them (one more association at ``T``)."""
        rings = fc.registered_rings()
        if rings is None or len(self._map) < 10:
            return
        rc = self.cfg.registration
        src, covs = fc.registration_source()
        tree = self._fresh if self._refresh is MapRefresh.ON_USE else self._map
        d, j = tree.query(transform(T, src), k=1, distance_upper_bound=rc.max_correspondence)
        ok = np.isfinite(d)
        j = np.where(ok, j, len(self._map.points))
        p, q, W, _, _, _ = kernels.gicp_terms(T, src, covs, self._map.points, self._map.covs, j)
        w = robust_weights(T, p, q, W, rc.robust_scale) if rc.robust_scale else None
        self._calibration.update(p, rings[ok], T, q, W, w)

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
            rc.regularisation,
            rc.covariance_mode,
            query=pts[rows],
            plane_epsilon=rc.plane_epsilon,
            line_ratio=rc.line_ratio,
            threads=rc.threads,
            neighbours=neighbours,
        )
