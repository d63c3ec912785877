"""Geometric verification of a loop candidate: global 2D start, GICP schedule, fine-scale judge.

The source (current keyframe's local cloud) is registered against the target (the
candidate's) from the guess, from the guess turned half a turn and from a bird's-eye-view
start (:mod:`slam.loop.bev`). From every start a coarse-to-fine GICP schedule runs, and each
stage's result is kept only if it raises the fine-scale score (share of structured source
points that meet a target surface): a coarse stage with long correspondences can slide a
correct start metres along a road, and such a result scores worse at the fine scale. When
the fine stage from the coarse result lands in a worse basin, it also runs from the start
itself and the better of the two is kept. The best-scoring result is judged:

- overlap: share of structured, steep source points with a target neighbour within a
  radius that grows with the point's range (the target's rings spread apart with range:
  ``inlier_distance`` near, ``tan(beam_gap) * range`` far) whose point-to-plane distance
  is within ``plane_tolerance`` (+ ``plane_range_ratio * range``, beam divergence);
- fitness: RMS point-to-plane distance (m) of those inliers, which unlike point-to-point
  distances does not depend on the two scans' sampling densities;
- the overlap required falls with the registered offset between the two sensors (scans
  taken a metre apart see nearly the same surfaces, far apart fewer);
- the registered yaw agrees with the guess.

The 6x6 information comes from the fine registration's Hessian through
:func:`slam.registration.information.information_from_hessian` (scaled by the residual
variance, eigenvalues clamped to the loop's sigma floors). small_gicp linearises
``T * Exp(delta)`` with ``delta = (rotation, translation)``, the same tangent ordering and
side as GTSAM's Pose3, so ``H`` is used as is (``tests/test_loop_plugin.py`` checks it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import small_gicp

from slam.loop.angles import wrap_angle, yaw_matrix, yaw_of
from slam.loop.bev import BevTarget, bev_target, bev_translation
from slam.registration.ambiguity import (
    MIN_JUDGED_POINTS,
    STEEP,
    alignment_score,
    ambiguous_axis,
    free_information,
    slide_shifts,
)
from slam.registration.ambiguity import Prepared as _Prepared
from slam.registration.ambiguity import prepare as _prepare
from slam.registration.information import InformationConfig, information_from_hessian

__all__ = ["VerifyParams", "VerifyResult", "verify", "wrap_angle", "yaw_matrix", "yaw_of"]

# lambda_min / (lambda_1 + lambda_2 + lambda_3) of a point's neighbourhood below which it lies on
# a surface or a line (a plane with 1-2 cm noise over a 0.5 m support: ~0.003; isotropic
# scatter such as a tree crown: up to 1/3)
MAX_SURFACE_VARIATION = 0.05
SHAPE_NEIGHBOURS = 10
COARSE_REGISTRATIONS = ("gicp", "vgicp")


@dataclass(frozen=True)
class VerifyParams:
    """How a loop candidate is registered and judged (``factors.loop_closure.verify``).

    neighbours: +-n keyframes merged into each local cloud (0: the keyframe alone).
    voxel / max_correspondence (m): the fine GICP stage; coarse_voxel /
    coarse_max_correspondence (m): the coarse stage (kept only if it improves the fine score).
    coarse_registration: "gicp" (KD-tree GICP on both clouds at coarse_voxel) or "vgicp"
    (the source against the fine target's Gaussian voxels of coarse_vgicp_resolution m:
    cheaper, but not the default, docs/loops.md).
    global_search (m, 0 = off): the bird's-eye-view start search, on a grid of bev_cell m
    over yaws of bev_yaw_offsets_deg, skipped when the guess already scores
    global_skip_overlap. try_flip: also start half a turn from the guess (Scan Context's yaw
    is ambiguous by 180 deg in streets and corridors). max_offset (m): a longer registered
    offset is no revisit. max_judged: source points the score uses (an even subsample).
    inlier_distance (m) near the sensor, tan(beam_gap_deg) x range far away: an inlier's
    neighbour radius; plane_tolerance (m) + plane_range_ratio x range: its point-to-plane
    distance. max_fitness (m): RMS point-to-plane distance of the inliers. Inlier share
    required: max(min_overlap, min_overlap_near - overlap_loss_per_m x offset in m), since
    scans taken close together see the same surfaces. yaw_tolerance_deg: max |yaw - guess|.
    min_sigma_trans (m) / min_sigma_rot_deg: sigma floor of the loop's information (a
    scan-to-scan loop is good to cm, not mm); max_sigma_ratio caps the weakest direction's
    sigma at that multiple; min_sigma_tilt_deg: floor of the roll / pitch sigma
    (:func:`tilt_floor`: revisits fix yaw far better than tilt; 0 off).
    ambiguity_*: the degeneracy test (:func:`slam.registration.ambiguity.ambiguous_axis`):
    slid ambiguity_min_shift..ambiguity_max_shift m (steps of ambiguity_step) along the
    weakest horizontal direction, if some slide keeps ambiguity_ratio of the overlap the
    axis is free: the loop's sigma along it becomes free_sigma m, or with free_sigma <= 0
    the loop is rejected (its position there is only the drifted start's); 0 ratio: off.
    """

    neighbours: int = 0
    voxel: float = 0.25
    max_correspondence: float = 1.0
    coarse_voxel: float = 0.5
    coarse_max_correspondence: float = 2.0
    coarse_registration: str = "gicp"
    coarse_vgicp_resolution: float = 1.0
    global_search: float = 20.0
    max_offset: float = 20.0
    global_skip_overlap: float = 0.8
    try_flip: bool = True
    bev_cell: float = 0.5
    bev_yaw_offsets_deg: tuple[float, ...] = (-6.0, -3.0, 0.0, 3.0, 6.0)
    max_iterations: int = 30
    inlier_distance: float = 0.3
    beam_gap_deg: float = 2.0
    plane_tolerance: float = 0.1
    plane_range_ratio: float = 0.002
    max_fitness: float = 0.1
    min_overlap: float = 0.4
    min_overlap_near: float = 0.65
    overlap_loss_per_m: float = 0.015
    yaw_tolerance_deg: float = 15.0
    min_sigma_trans: float = 0.05
    min_sigma_rot_deg: float = 0.5
    min_sigma_tilt_deg: float = 1.0
    max_sigma_ratio: float = 100.0
    max_judged: int = 3000
    num_threads: int = 1
    ambiguity_ratio: float = 0.8
    ambiguity_min_shift: float = 1.0
    ambiguity_max_shift: float = 8.0
    ambiguity_step: float = 0.5
    free_sigma: float = 20.0

    def __post_init__(self) -> None:
        for name in ("voxel", "inlier_distance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("min_sigma_trans", "min_sigma_rot_deg"):  # the information floors
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.max_sigma_ratio >= 1:
            raise ValueError(f"max_sigma_ratio must be >= 1, got {self.max_sigma_ratio}")
        if self.neighbours < 0:
            raise ValueError(f"neighbours must be >= 0, got {self.neighbours}")
        if not 0.0 <= self.min_overlap <= 1.0:
            raise ValueError(f"min_overlap must be in [0, 1], got {self.min_overlap}")
        if self.coarse_registration not in COARSE_REGISTRATIONS:
            raise ValueError(
                f"unknown coarse_registration '{self.coarse_registration}'; valid: "
                f"{', '.join(COARSE_REGISTRATIONS)}"
            )


@dataclass
class VerifyResult:
    """Outcome: T_target_source after GICP, fitness (m), overlap (0-1), yaw (deg) of the
    result, info (6x6, rotation first), accepted and the reason when rejected; start: which
    start won ("guess" or "bev"), stages: names of the GICP stages kept."""

    accepted: bool
    T_target_source: np.ndarray
    fitness: float
    overlap: float
    yaw_deg: float
    info: np.ndarray
    reason: str = ""
    start: str = "guess"
    stages: list[str] = field(default_factory=list)
    free_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    ambiguity: float = 0.0


def scaled_information(
    H: np.ndarray, min_sigma_trans: float, min_sigma_rot: float, max_sigma_ratio: float
) -> np.ndarray:
    """A plausible 6x6 information (rotation first) from a registration Hessian.

    Raw GICP Hessians are 1e6-1e9 (thousands of points, mm-thin covariances) and claim
    sub-millimetre sigmas: the best-determined direction gets exactly the floor sigma
    (min_sigma_rot rad, min_sigma_trans m), the Hessian's shape is kept, and weak
    (degenerate) directions are lifted to at most max_sigma_ratio times the floor. This is
    :func:`information_from_hessian` with the residual variance chosen so the best direction
    sits on the floor.
    """
    floor = np.array([min_sigma_rot] * 3 + [min_sigma_trans] * 3)
    Hs = 0.5 * (np.asarray(H, dtype=np.float64) + np.asarray(H, dtype=np.float64).T)
    W = Hs * floor[:, None] * floor[None, :]
    top = float(np.linalg.eigvalsh(W).max()) if np.all(np.isfinite(W)) else 0.0
    cfg = InformationConfig(
        min_sigma_translation=min_sigma_trans,
        min_sigma_rotation_deg=float(np.degrees(min_sigma_rot)),
        max_sigma_translation=min_sigma_trans * max_sigma_ratio,
        max_sigma_rotation_deg=float(np.degrees(min_sigma_rot)) * max_sigma_ratio,
    )
    if top <= 0.0:
        return information_from_hessian(np.zeros((6, 6)), 1.0, cfg).info
    return information_from_hessian(Hs, top, cfg).info


# ----------------------------------------------------------------------------- fine judge


def _shape_covariances(prepared: _Prepared, query_idx: np.ndarray, k: int) -> np.ndarray:
    """(M, 3, 3) covariance (m^2) of the k nearest points of each queried point, searched in
    the prepared cloud's own KD-tree (as slam.features.curvature.local_covariances, without
    building another tree)."""
    pts = prepared.points
    k = min(k, len(pts))
    idx, _ = prepared.tree.batch_knn_search(pts[query_idx], k, num_threads=1)
    centred = pts[np.asarray(idx, dtype=np.int64)]
    centred -= centred.mean(axis=1, keepdims=True)
    return np.einsum("mki,mkj->mij", centred, centred) / max(k - 1, 1)


def judged_points(source: _Prepared, R: np.ndarray, max_points: int = 3000) -> np.ndarray:
    """The source points a verification is judged on (:func:`judged_indices`)."""
    return source.points[judged_indices(source, R, max_points)]


def judged_indices(source: _Prepared, R: np.ndarray, max_points: int = 3000) -> np.ndarray:
    """Indices of the source points a verification is judged on.

    Steep (|normal_z| < 0.7 after rotation R: walls, poles, trunks, facades) because ground
    and ceiling overlap in almost any two scans and would make unrelated places look alike;
    structured (surface variation lambda_min / trace < MAX_SURFACE_VARIATION: a plane or a
    line) because foliage and mixed pixels scatter in depth, so even a perfect alignment of
    a tree crown leaves ~0.15-0.2 m between nearest neighbours. Falls back to all steep (or
    all) points when fewer than MIN_JUDGED_POINTS qualify. At most ``max_points`` steep points
    are examined (an even subsample: the score is a share, known to ~1 % from 3000 points).
    """
    pts = source.points
    steep_idx = np.flatnonzero(np.abs(source.normals @ R.T[:, 2]) < STEEP)
    if len(steep_idx) < MIN_JUDGED_POINTS:
        return np.arange(len(pts))
    if len(steep_idx) > max_points:
        steep_idx = steep_idx[np.linspace(0, len(steep_idx) - 1, max_points).astype(np.intp)]
    # shape of the steep points only (neighbours among all points), from raw covariances:
    # small_gicp's are regularised to planes and carry no shape
    cov = _shape_covariances(source, steep_idx, SHAPE_NEIGHBOURS)
    ev = np.linalg.eigvalsh(cov)  # ascending
    structured = ev[:, 0] < MAX_SURFACE_VARIATION * np.maximum(ev.sum(axis=1), 1e-12)
    if structured.sum() >= MIN_JUDGED_POINTS:
        return steep_idx[structured]
    return steep_idx


def tilt_floor(info: np.ndarray, min_sigma_tilt: float) -> np.ndarray:
    """``info`` (6x6, rotation first) with the marginal sigmas of roll and pitch (rotation
    about the sensor's x and y, rad) lifted to at least ``min_sigma_tilt``: the covariance
    is scaled on those axes (C' = D C D), so correlations are kept and nothing else changes.

    Why: two scans of a revisit see the same ground and walls, which fix yaw far better than
    tilt, and the tilt errors repeat along a street, so many loops claiming a tight tilt
    bend the trajectory in z.
    """
    if min_sigma_tilt <= 0:
        return info
    C = np.linalg.inv(0.5 * (info + info.T))
    d = np.ones(6)
    for i in (0, 1):
        sig = float(np.sqrt(max(C[i, i], 0.0)))
        d[i] = max(1.0, min_sigma_tilt / sig) if sig > 0 else 1.0
    C = C * d[:, None] * d[None, :]
    out = np.linalg.inv(C)
    return 0.5 * (out + out.T)


def required_overlap(offset: float, p: VerifyParams) -> float:
    """Inlier share a registration with this offset (m) between the sensors must reach."""
    return max(p.min_overlap, p.min_overlap_near - p.overlap_loss_per_m * offset)


def _align(t: _Prepared, s: _Prepared, T: np.ndarray, corr: float, p: VerifyParams):
    return small_gicp.align(
        t.cloud, s.cloud, t.tree, init_T_target_source=T, registration_type="GICP",
        max_correspondence_distance=corr, max_iterations=p.max_iterations,
        num_threads=p.num_threads,
    )  # fmt: skip


@dataclass
class _VoxelTarget:
    """The coarse target for VGICP: a Gaussian voxel map and the coarse points (BEV search)."""

    voxels: small_gicp.GaussianVoxelMap
    points: np.ndarray


def _coarse_voxel_map(fine: _Prepared, points: np.ndarray, p: VerifyParams) -> _VoxelTarget:
    """The fine target cloud (its covariances) in voxels of coarse_vgicp_resolution m, and the
    target thinned to coarse_voxel m (the bird's-eye-view image's points)."""
    voxels = small_gicp.GaussianVoxelMap(p.coarse_vgicp_resolution)
    voxels.insert(fine.cloud)
    thin = np.asarray(small_gicp.voxelgrid_sampling(points, p.coarse_voxel).points())[:, :3]
    return _VoxelTarget(voxels, thin)


def _align_vgicp(t: _VoxelTarget, s: _Prepared, T: np.ndarray, corr: float, p: VerifyParams):
    return small_gicp.align(
        t.voxels, s.cloud, init_T_target_source=T, max_correspondence_distance=corr,
        max_iterations=p.max_iterations, num_threads=p.num_threads,
    )  # fmt: skip


def _half_turn() -> np.ndarray:
    """4x4 rotation by 180 deg about the sensor's z axis."""
    return np.diag([-1.0, -1.0, 1.0, 1.0])


def _rejected(T: np.ndarray, reason: str) -> VerifyResult:
    return VerifyResult(
        False, np.asarray(T, float), np.inf, 0.0, np.degrees(yaw_of(T)), np.zeros((6, 6)), reason
    )


@dataclass
class _Pair:
    """The two clouds of one verification, prepared at the fine (and coarse) voxel, the
    judged source points, and the clouds of the bird's-eye-view search (``bt``: its target
    spectrum, made on first use)."""

    ft: _Prepared
    fs: _Prepared
    ct: _Prepared | _VoxelTarget | None
    cs: _Prepared | None
    judged: np.ndarray
    judged_normals: np.ndarray
    bev_tgt: np.ndarray | None
    bev_src: np.ndarray | None
    bt: BevTarget | None = None

    @property
    def coarse(self) -> bool:
        return self.cs is not None


def _prepare_pair(target: np.ndarray, source: np.ndarray, T0: np.ndarray, p: VerifyParams) -> _Pair:
    tgt = np.ascontiguousarray(np.asarray(target, dtype=np.float64)[:, :3])
    src = np.ascontiguousarray(np.asarray(source, dtype=np.float64)[:, :3])
    ft, fs = _prepare(tgt, p.voxel, p.num_threads), _prepare(src, p.voxel, p.num_threads)
    ct = cs = None
    if p.coarse_voxel > p.voxel and p.coarse_registration == "vgicp":
        # the target side is a voxel map of the fine cloud: no KD-tree, no covariances
        cs = _prepare(src, p.coarse_voxel, p.num_threads)
        ct = _coarse_voxel_map(ft, tgt, p)
    elif p.coarse_voxel > p.voxel:
        ct, cs = (_prepare(tgt, p.coarse_voxel, p.num_threads),
                  _prepare(src, p.coarse_voxel, p.num_threads))  # fmt: skip
    judged_idx = judged_indices(fs, T0[:3, :3], p.max_judged)
    bev_tgt = bev_src = None
    if p.global_search > 0.0:
        bev_tgt, bev_src = (ct.points, cs.points) if cs is not None else (tgt, src)
    return _Pair(ft, fs, ct, cs, fs.points[judged_idx], fs.normals[judged_idx], bev_tgt, bev_src)


def _bev_start(pair: _Pair, yaw: float, p: VerifyParams) -> np.ndarray:
    if pair.bt is None:
        pair.bt = bev_target(pair.bev_tgt, p.global_search, p.bev_cell)
    start, _ = bev_translation(
        pair.bev_tgt, pair.bev_src, yaw, p.global_search, p.bev_cell, p.bev_yaw_offsets_deg,
        pair.bt,
    )  # fmt: skip
    return start


def _best_start(pair: _Pair, T0: np.ndarray, p: VerifyParams) -> tuple:
    """(name, T, score, stages kept, start) of the best start after its coarse stage.

    "flip": the guess turned by half a turn: Scan Context's column shift is ambiguous by
    180 deg in street canyons and corridors (their descriptor is nearly symmetric under a
    half turn), so a street driven back the other way often gets yaw ~0 instead of ~180."""
    best = None
    for name in ("guess", "flip", "bev"):
        if name == "flip":
            if not p.try_flip:  # always tried: a wrong half turn can score 0.8 in a street
                continue
            start = T0 @ _half_turn()
            if p.global_search > 0.0:  # the other lane is metres aside: search it at once
                start = _bev_start(pair, yaw_of(start), p)
        elif name == "bev":
            if p.global_search <= 0.0 or best[2][0] >= p.global_skip_overlap:
                break  # off, or the guess already explains the scan
            start = _bev_start(pair, yaw_of(T0), p)
        else:
            start = T0
        T = start
        score = alignment_score(pair.judged, pair.ft, T, p)
        kept = []
        if pair.coarse:
            align = _align_vgicp if isinstance(pair.ct, _VoxelTarget) else _align
            c = align(pair.ct, pair.cs, T, p.coarse_max_correspondence, p)
            c_score = alignment_score(pair.judged, pair.ft, c.T_target_source, p)
            if c_score[0] > score[0]:
                T, score = np.array(c.T_target_source), c_score
                kept.append("coarse")
        if best is None or score[0] > best[2][0]:
            best = (name, T, score, kept, start)
    return best


def _fine_stage(pair: _Pair, T: np.ndarray, start: np.ndarray, score, kept, p: VerifyParams):
    """The accurate stage from the best start; when the coarse result leads it into a worse
    basin (the score drops), it also runs from the start itself. (result, T, score, kept)."""
    fines = [_align(pair.ft, pair.fs, T, p.max_correspondence, p)]
    scores = [alignment_score(pair.judged, pair.ft, fines[0].T_target_source, p)]
    if kept and scores[0][0] < score[0]:
        fines.append(_align(pair.ft, pair.fs, start, p.max_correspondence, p))
        scores.append(alignment_score(pair.judged, pair.ft, fines[1].T_target_source, p))
        if scores[1][0] > scores[0][0]:
            kept = []
    k = int(np.argmax([sc[0] for sc in scores]))
    fine = fines[k]
    if fine.converged:
        T, score = np.array(fine.T_target_source), scores[k]
        kept = [*kept, "fine"]
    return fine, T, score, kept


def _information(pair: _Pair, fine, T: np.ndarray, p: VerifyParams):
    """(6x6 information, free axes (k, 3), ambiguity) of the fine registration."""
    info = scaled_information(
        np.asarray(fine.H), p.min_sigma_trans, np.radians(p.min_sigma_rot_deg), p.max_sigma_ratio
    )
    info = tilt_floor(info, np.radians(p.min_sigma_tilt_deg))
    free, ambiguity = np.zeros((0, 3)), 0.0
    if fine.converged and p.ambiguity_ratio > 0:
        shifts = slide_shifts(p.ambiguity_min_shift, p.ambiguity_max_shift, p.ambiguity_step)
        free, ambiguity = ambiguous_axis(
            pair.judged, pair.judged_normals, pair.ft, T, np.asarray(fine.H), p,
            p.ambiguity_ratio, shifts,
        )  # fmt: skip
        if len(free) and p.free_sigma > 0:  # the factor's tangent is the source frame
            info = free_information(info, free @ T[:3, :3], p.free_sigma)
    return info, free, ambiguity


def _rejection(T: np.ndarray, score, guess_yaw: float, converged: bool, free, ambiguity: float,
               p: VerifyParams) -> str:  # fmt: skip
    """Why the registered T fails the judge (empty string when it passes)."""
    overlap, fitness = score
    offset = float(np.linalg.norm(T[:3, 3]))
    yaw = yaw_of(T)
    if not converged:
        return "gicp did not converge"
    if np.linalg.norm(T[:3, 3]) > p.max_offset:
        return f"offset {np.linalg.norm(T[:3, 3]):.1f} m > {p.max_offset:.1f} m"
    if overlap < required_overlap(offset, p):
        return f"overlap {overlap:.2f} < {required_overlap(offset, p):.2f}"
    if fitness > p.max_fitness:
        return f"fitness {fitness:.3f} m > {p.max_fitness:.3f} m"
    if abs(np.degrees(wrap_angle(yaw - guess_yaw))) > p.yaw_tolerance_deg:
        return f"yaw {np.degrees(yaw):.1f} deg disagrees with guess {np.degrees(guess_yaw):.1f} deg"
    if len(free) and p.free_sigma <= 0:
        return f"not unique along its weakest horizontal axis (ambiguity {ambiguity:.2f})"
    return ""


def verify(
    target: np.ndarray,
    source: np.ndarray,
    init_T_target_source: np.ndarray,
    params: VerifyParams = VerifyParams(),
) -> VerifyResult:
    """Register ``source`` (N, 3) onto ``target`` (M, 3) from the initial guess and judge it."""
    p = params
    T0 = np.asarray(init_T_target_source, dtype=np.float64)
    if len(target) < 10 or len(source) < 10:
        return _rejected(T0, "too few points")
    pair = _prepare_pair(target, source, T0, p)
    name, T, score, kept, start = _best_start(pair, T0, p)
    guess_yaw = yaw_of(start) if name == "flip" else yaw_of(T0)
    if score[0] < 0.5 * p.min_overlap:  # hopeless: a fine stage cannot double the overlap
        return VerifyResult(
            False, T, score[1], score[0], np.degrees(yaw_of(T)), np.zeros((6, 6)),
            f"overlap {score[0]:.2f} < {p.min_overlap:.2f} (coarse)", name, kept,
        )  # fmt: skip
    fine, T, score, kept = _fine_stage(pair, T, start, score, kept, p)
    info, free, ambiguity = _information(pair, fine, T, p)
    converged = "fine" in kept and fine.converged
    reason = _rejection(T, score, guess_yaw, converged, free, ambiguity, p)
    overlap, fitness = score
    return VerifyResult(
        not reason, T, fitness, overlap, float(np.degrees(yaw_of(T))), info, reason, name,
        kept, free, ambiguity,
    )  # fmt: skip
