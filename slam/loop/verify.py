"""Geometric verification of a loop candidate: global 2D start, GICP schedule, fine-scale judge.

The source (current keyframe's local cloud) is registered against the target (the
candidate's). Scan Context gives only a yaw, and two passes of the same street may lie
10-20 m apart, so besides the given start a second start comes from a bird's-eye-view
correlation of the two clouds (:func:`bev_translation`: occupancy images of the non-ground
points, FFT cross-correlation over a few yaws around the guess). From every start a
coarse-to-fine GICP schedule runs (the fine stage's Hessian gives the information), and
each stage's result is kept only if it raises the fine-scale score (share of structured
source points that meet a target surface): a coarse stage with long correspondences can
slide a correct start metres along a road, and such a result scores worse at the fine scale
and is discarded; when the fine stage from the coarse result still lands in a worse basin
than the coarse result's score promised, it also runs from
the start itself and the better of the two is kept. The best-scoring result is judged:

- overlap: share of structured, steep source points with a target neighbour within a
  radius that grows with the point's range (the target's rings spread apart with range:
  ``inlier_distance`` near, ``tan(beam_gap) * range`` far) whose point-to-plane distance
  is within ``plane_tolerance`` (+ ``plane_range_ratio * range``, beam divergence);
- fitness: RMS point-to-plane distance (m) of those inliers, which unlike point-to-point
  distances does not depend on the two scans' sampling densities;
- the overlap required falls with the registered offset between the two sensors (scans
  taken a metre apart see nearly the same surfaces; 17 m apart, half of them);
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
import scipy.fft
import small_gicp

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

# lambda_min / (lambda_1 + lambda_2 + lambda_3) of a point's neighbourhood below which it lies on
# a surface or a line (a plane with 1-2 cm noise over a 0.5 m support: ~0.003; isotropic
# scatter such as a tree crown: up to 1/3)
MAX_SURFACE_VARIATION = 0.05
SHAPE_NEIGHBOURS = 10
COARSE_REGISTRATIONS = ("gicp", "vgicp")


@dataclass(frozen=True)
class VerifyParams:
    """voxel / max_correspondence (m): the fine GICP stage; coarse_voxel /
    coarse_max_correspondence (m): the coarse stage (kept only if it improves the fine score).
    coarse_registration: "gicp" (KD-tree GICP on both clouds thinned to coarse_voxel) or
    "vgicp" (small_gicp's voxelised GICP of the source thinned to coarse_voxel against the
    fine target's Gaussian voxels of coarse_vgicp_resolution m: no coarse target covariances
    or KD-tree; on 35 urban-drive candidates and 13 real pairs the same decisions at 0.65-0.8x
    the CPU, but in the simulated corridor it let a loop 4 deg off in roll through, so it is
    not the default).
    global_search (m): radius of the bird's-eye-view translation search (0 = off), on a grid
    of bev_cell (m), over yaws of bev_yaw_offsets_deg around the guess. max_offset (m): a
    registered offset longer than this is no revisit (the two scans would barely overlap).
    global_skip_overlap: the search is skipped when the guess already scores this overlap.
    try_flip: also start from the guess turned by 180 deg (Scan Context's yaw is ambiguous by
    half a turn in streets and corridors); the odometry-consistency gate judges the result.
    max_judged: the score uses at most this many source points (an even subsample).
    inlier_distance (m): neighbour radius near the sensor; beam_gap_deg: far away the radius
    is tan(beam_gap) x range (the coarsest common ring spacing, 16 beams over 30 deg: 2 deg).
    plane_tolerance (m) + plane_range_ratio x range: max point-to-plane distance of an inlier.
    max_fitness: max RMS point-to-plane distance (m) of inliers. min_overlap: min inlier share;
    two scans taken close together see the same surfaces, so the share required is
    max(min_overlap, min_overlap_near - overlap_loss_per_m x registered offset in m): a
    look-alike place that matches only half its structure at 0.3 m offset is no revisit
    (real same-place scans: 0.84 at 0.5-2 m, 0.53 at 17 m apart).
    yaw_tolerance_deg: max |registered yaw - guess yaw|. min_sigma_*: sigma floor of the
    loop's information; max_sigma_ratio caps the weakest direction's sigma at that multiple.
    min_sigma_tilt_deg: floor of the marginal roll / pitch sigma (:func:`tilt_floor`; 0 off).
    ambiguity_*: the degeneracy test of the result (:func:`ambiguous_axis`): the result is
    slid along its weakest horizontal direction by ambiguity_min_shift..ambiguity_max_shift m
    (steps of ambiguity_step m, both ways); if some slide keeps ambiguity_ratio of the
    result's overlap, the alignment is not unique along that axis (a plain or periodic
    corridor), and the loop's information along it is set to free_sigma m, or with
    free_sigma <= 0 the loop is rejected (its position along the axis is only the start's,
    the drifted estimate's: on building_loop_return 5 of the 20 such loops were 1.2-8.5 m
    off along it, the 287 others within 0.32 m) (0 ratio: off;
    slam.registration.ambiguity, shared with the front ends' odometry information)."""

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
    min_sigma_trans: float = 0.01
    min_sigma_rot_deg: float = 0.1
    min_sigma_tilt_deg: float = 0.0
    max_sigma_ratio: float = 100.0
    max_judged: int = 3000
    num_threads: int = 1
    ambiguity_ratio: float = 0.8
    ambiguity_min_shift: float = 1.0
    ambiguity_max_shift: float = 8.0
    ambiguity_step: float = 0.5
    free_sigma: float = 20.0


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


def yaw_of(T: np.ndarray) -> float:
    """Yaw (radians) of a 4x4 pose: rotation about z of its x axis."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def wrap_angle(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return float(np.pi - np.mod(np.pi - a, 2.0 * np.pi))


def yaw_matrix(yaw: float, translation: np.ndarray | None = None) -> np.ndarray:
    """4x4 rotation by ``yaw`` radians about z (plus an optional translation)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    if translation is not None:
        T[:3, 3] = translation
    return T


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


# ----------------------------------------------------------------------------- global start


def _bev_image(xy: np.ndarray, cell: float, half: int) -> np.ndarray:
    """Binary occupancy (2 half, 2 half) of points ``xy`` (N, 2) on a grid centred at 0."""
    ij = np.floor(xy / cell).astype(np.int64) + half
    ok = np.all((ij >= 0) & (ij < 2 * half), axis=1)
    img = np.zeros((2 * half, 2 * half), dtype=np.float64)
    img[ij[ok, 0], ij[ok, 1]] = 1.0
    return img


def _above_ground(points: np.ndarray) -> np.ndarray:
    """Points more than 0.5 m above the scan's ground level (its 5th height percentile):
    walls, poles, parked cars: what fixes a horizontal position (the ground does not)."""
    z = points[:, 2]
    return points[z > np.percentile(z, 5) + 0.5]


@dataclass(frozen=True)
class BevTarget:
    """The target's bird's-eye-view occupancy spectrum, computed once per verification and
    shared by every yaw and start searched against it. half: image half-size (cells);
    size: FFT size per axis (>= image size + search cells, so the circular correlation equals
    the linear one for every shift searched); reach: which FFT indices are shifts within the
    search radius."""

    spectrum: np.ndarray
    cell: float
    half: int
    size: int
    shifts: np.ndarray
    reach: np.ndarray


def bev_target(target: np.ndarray, search: float, cell: float = 0.5) -> BevTarget:
    """Prepare the target side of :func:`bev_translation` (above-ground points, ``cell`` m)."""
    half = int(np.ceil((search + 30.0) / cell))  # image covers +-(search + 30) m
    reach_cells = int(np.floor(search / cell))
    # zero padding of reach_cells suffices: corr[t] only needs x + t in [-reach, n + reach)
    size = int(scipy.fft.next_fast_len(2 * half + reach_cells + 1, real=True))
    img = _bev_image(_above_ground(target)[:, :2], cell, half)
    shifts = np.fft.fftfreq(size, 1.0 / size).astype(np.int64)  # index -> signed shift
    return BevTarget(
        scipy.fft.rfft2(img, s=(size, size)), cell, half, size, shifts,
        np.abs(shifts) <= reach_cells,
    )  # fmt: skip


def bev_translation(
    target: np.ndarray,
    source: np.ndarray,
    yaw: float,
    search: float,
    cell: float = 0.5,
    yaw_offsets_deg: tuple[float, ...] = (0.0,),
    prepared: BevTarget | None = None,
) -> tuple[np.ndarray, float]:
    """A 4x4 start T_target_source from a bird's-eye-view correlation, and its peak share.

    The above-ground points of both clouds become occupancy images (``cell`` m); for each
    yaw ``yaw + offset`` the rotated source image is cross-correlated with the target's by
    FFT and the best shift within ``search`` m is taken; the yaw and shift of the highest
    peak win (ties: the first offset, the first shift in FFT order; the correlation of two
    binary images is an integer count, rounded so ties do not hinge on FFT round-off).
    peak share: correlation peak / occupied source cells (0-1). ``prepared``: the target's
    :func:`bev_target` for the same search and cell (computed here when None).
    """
    bt = prepared if prepared is not None else bev_target(target, search, cell)
    src = _above_ground(source)
    n, half, cell = bt.size, bt.half, bt.cell
    outside = ~bt.reach
    best = (-1.0, 0.0, 0, 0, 1.0)
    for off in yaw_offsets_deg:
        y = yaw + np.radians(off)
        c, s = np.cos(y), np.sin(y)
        xy = src[:, :2] @ np.array([[c, s], [-s, c]])
        img = _bev_image(xy, cell, half)
        occupied = max(float(img.sum()), 1.0)
        # corr[t] = sum_x target[x + t] * source[x]
        spec = bt.spectrum * np.conj(scipy.fft.rfft2(img, s=(n, n)))
        corr = np.rint(scipy.fft.irfft2(spec, s=(n, n)))
        corr[outside, :] = -1.0
        corr[:, outside] = -1.0
        i, j = np.unravel_index(int(np.argmax(corr)), corr.shape)
        if corr[i, j] > best[0]:
            best = (float(corr[i, j]), y, int(bt.shifts[i]), int(bt.shifts[j]), occupied)
    peak, y, di, dj, occupied = best
    return yaw_matrix(y, np.array([di * cell, dj * cell, 0.0])), peak / occupied


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
    tilt; on the urban drive's opposite-lane loops the errors were roll / pitch 0.43 / 0.51
    deg std (max 1.6) against yaw 0.04, and they repeat along a street (the same geometry
    biases consecutive registrations alike), so 151 loops claiming 0.6 deg bent the
    trajectory in z (APE 0.41 m, of it z 0.40 m, xy 0.06 m).
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


def verify(
    target: np.ndarray,
    source: np.ndarray,
    init_T_target_source: np.ndarray,
    params: VerifyParams = VerifyParams(),
) -> VerifyResult:
    """Register ``source`` (N, 3) onto ``target`` (M, 3) from the initial guess and judge it."""
    p = params
    T0 = np.asarray(init_T_target_source, dtype=np.float64)
    guess_yaw = yaw_of(T0)
    if len(target) < 10 or len(source) < 10:
        return _rejected(T0, "too few points")
    tgt = np.ascontiguousarray(np.asarray(target, dtype=np.float64)[:, :3])
    src = np.ascontiguousarray(np.asarray(source, dtype=np.float64)[:, :3])
    ft, fs = _prepare(tgt, p.voxel, p.num_threads), _prepare(src, p.voxel, p.num_threads)
    coarse = p.coarse_voxel > p.voxel
    vgicp = coarse and p.coarse_registration == "vgicp"
    if vgicp:  # the target side is a voxel map of the fine cloud: no KD-tree, no covariances
        cs = _prepare(src, p.coarse_voxel, p.num_threads)
        ct = _coarse_voxel_map(ft, tgt, p)
    elif coarse:
        ct, cs = (_prepare(tgt, p.coarse_voxel, p.num_threads),
                  _prepare(src, p.coarse_voxel, p.num_threads))  # fmt: skip
    judged_idx = judged_indices(fs, T0[:3, :3], p.max_judged)
    judged, judged_normals = fs.points[judged_idx], fs.normals[judged_idx]
    bev_tgt = bev_src = bt = None
    if p.global_search > 0.0:
        bev_tgt, bev_src = (ct.points, cs.points) if coarse else (tgt, src)
    best = None
    # coarse stage per start, kept only if it improves the score. "flip": the guess turned by
    # half a turn: Scan Context's column shift is ambiguous by 180 deg in street canyons and
    # corridors (their descriptor is nearly symmetric under a half turn), so a street driven
    # back the other way often gets yaw ~0 instead of ~180; the registration decides
    for name in ("guess", "flip", "bev"):
        if name == "flip":
            if not p.try_flip:  # always tried: a wrong half turn can score 0.8 in a street
                continue
            start = T0 @ _half_turn()
            if p.global_search > 0.0:  # the other lane is metres aside: search it at once
                bt = bt or bev_target(bev_tgt, p.global_search, p.bev_cell)
                start, _ = bev_translation(
                    bev_tgt, bev_src, yaw_of(start), p.global_search, p.bev_cell,
                    p.bev_yaw_offsets_deg, bt,
                )  # fmt: skip
        elif name == "bev":
            if p.global_search <= 0.0 or best[2][0] >= p.global_skip_overlap:
                break  # off, or the guess already explains the scan
            bt = bt or bev_target(bev_tgt, p.global_search, p.bev_cell)
            start, _ = bev_translation(
                bev_tgt, bev_src, guess_yaw, p.global_search, p.bev_cell,
                p.bev_yaw_offsets_deg, bt,
            )  # fmt: skip
        else:
            start = T0
        T = start
        score = alignment_score(judged, ft, T, p)
        kept = []
        if coarse:
            c = (_align_vgicp if vgicp else _align)(ct, cs, T, p.coarse_max_correspondence, p)
            c_score = alignment_score(judged, ft, c.T_target_source, p)
            if c_score[0] > score[0]:
                T, score = np.array(c.T_target_source), c_score
                kept.append("coarse")
        if best is None or score[0] > best[2][0]:
            best = (name, T, score, kept, start)
    name, T, score, kept, start = best
    if name == "flip":
        guess_yaw = yaw_of(start)
    if score[0] < 0.5 * p.min_overlap:  # hopeless: a fine stage cannot double the overlap
        return VerifyResult(
            False, T, score[1], score[0], np.degrees(yaw_of(T)), np.zeros((6, 6)),
            f"overlap {score[0]:.2f} < {p.min_overlap:.2f} (coarse)", name, kept,
        )  # fmt: skip
    # the accurate stage, from the best start; when the coarse result leads the fine stage
    # into a worse basin (the score drops), the fine stage also runs from the start itself
    fines = [_align(ft, fs, T, p.max_correspondence, p)]
    scores = [alignment_score(judged, ft, fines[0].T_target_source, p)]
    if kept and scores[0][0] < score[0]:
        fines.append(_align(ft, fs, start, p.max_correspondence, p))
        scores.append(alignment_score(judged, ft, fines[1].T_target_source, p))
        if scores[1][0] > scores[0][0]:
            kept = []
    k = int(np.argmax([sc[0] for sc in scores]))
    fine = fines[k]
    if fine.converged:
        T, score = np.array(fine.T_target_source), scores[k]
        kept = [*kept, "fine"]
    overlap, fitness = score
    yaw = yaw_of(T)
    info = scaled_information(
        np.asarray(fine.H), p.min_sigma_trans, np.radians(p.min_sigma_rot_deg), p.max_sigma_ratio
    )
    info = tilt_floor(info, np.radians(p.min_sigma_tilt_deg))
    free, ambiguity = np.zeros((0, 3)), 0.0
    if fine.converged and p.ambiguity_ratio > 0:
        shifts = slide_shifts(p.ambiguity_min_shift, p.ambiguity_max_shift, p.ambiguity_step)
        free, ambiguity = ambiguous_axis(
            judged, judged_normals, ft, T, np.asarray(fine.H), p, p.ambiguity_ratio, shifts
        )
        if len(free) and p.free_sigma > 0:  # the factor's tangent is the source frame
            info = free_information(info, free @ T[:3, :3], p.free_sigma)
    reason = ""
    if "fine" not in kept or not fine.converged:
        reason = "gicp did not converge"
    elif np.linalg.norm(T[:3, 3]) > p.max_offset:
        reason = f"offset {np.linalg.norm(T[:3, 3]):.1f} m > {p.max_offset:.1f} m"
    elif overlap < required_overlap(float(np.linalg.norm(T[:3, 3])), p):
        reason = (
            f"overlap {overlap:.2f} < {required_overlap(float(np.linalg.norm(T[:3, 3])), p):.2f}"
        )
    elif fitness > p.max_fitness:
        reason = f"fitness {fitness:.3f} m > {p.max_fitness:.3f} m"
    elif abs(np.degrees(wrap_angle(yaw - guess_yaw))) > p.yaw_tolerance_deg:
        reason = (
            f"yaw {np.degrees(yaw):.1f} deg disagrees with guess {np.degrees(guess_yaw):.1f} deg"
        )
    elif len(free) and p.free_sigma <= 0:
        reason = f"not unique along its weakest horizontal axis (ambiguity {ambiguity:.2f})"
    return VerifyResult(
        not reason, T, fitness, overlap, float(np.degrees(yaw)), info, reason, name, kept,
        free, ambiguity,
    )  # fmt: skip
