"""Geometric verification of a loop candidate by GICP (small_gicp), coarse then fine.

The source (current keyframe's local cloud) is registered against the target (the
candidate's) from the descriptor's yaw guess. A candidate passes only if the fine
registration converged, the RMSE of inlier distances (``fitness``) is small, the share
of source points with a target neighbour (``overlap``) is large, and the registered yaw
agrees with the guess. The 6x6 information comes from the registration's Hessian.

small_gicp linearises ``T * Exp(delta)`` with ``delta = (rotation, translation)``
(its Jacobian is ``[R skew(p), -R]``), the same tangent ordering and side as GTSAM's
Pose3, so ``H`` is used as is (``tests/test_loop_plugin.py`` checks the ordering).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import small_gicp

from slam.features.curvature import local_covariances

# lambda_min / (lambda_1 + lambda_2 + lambda_3) of a point's neighbourhood below which it lies on
# a surface or a line (a plane with 1-2 cm noise over a 0.5 m support: ~0.003; isotropic
# scatter such as a tree crown: up to 1/3)
MAX_SURFACE_VARIATION = 0.05
SHAPE_NEIGHBOURS = 10


@dataclass(frozen=True)
class VerifyParams:
    """voxel: fine downsampling (m); coarse stage uses coarse_voxel and coarse_max_corr.
    inlier_distance (m): a source point with a target neighbour closer than this overlaps.
    max_fitness: max RMSE (m) of inlier distances. min_overlap: min inlier share (0-1).
    yaw_tolerance_deg: max |registered yaw - guess yaw|. min_sigma_*: the best direction's
    sigma after scaling the Hessian; max_sigma_ratio caps the weakest direction's sigma."""

    voxel: float = 0.25
    max_correspondence: float = 1.0
    coarse_voxel: float = 1.0
    coarse_max_correspondence: float = 4.0
    max_iterations: int = 30
    inlier_distance: float = 0.3
    max_fitness: float = 0.15
    min_overlap: float = 0.6
    yaw_tolerance_deg: float = 15.0
    min_sigma_trans: float = 0.01
    min_sigma_rot_deg: float = 0.1
    max_sigma_ratio: float = 100.0
    num_threads: int = 1


@dataclass
class VerifyResult:
    """Outcome: T_target_source after GICP, fitness (m), overlap (0-1), yaw (deg) of the
    result, info (6x6, rotation first), accepted and the reason when rejected."""

    accepted: bool
    T_target_source: np.ndarray
    fitness: float
    overlap: float
    yaw_deg: float
    info: np.ndarray
    reason: str = ""


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

    Raw GICP Hessians are 1e6-1e9 (thousands of points, mm-thin covariances). Whiten by
    the floor sigmas, scale so the best-determined direction has exactly the floor sigma
    (min_sigma_rot rad, min_sigma_trans m), keep the Hessian's shape, and lift the
    weak (degenerate) directions to at most max_sigma_ratio times the floor.
    """
    floor = np.array([min_sigma_rot] * 3 + [min_sigma_trans] * 3)
    Hs = 0.5 * (H + H.T)
    W = Hs * floor[:, None] * floor[None, :]
    if not np.all(np.isfinite(W)):
        W = np.zeros((6, 6))
    w, V = np.linalg.eigh(W)
    top = w.max()
    w = w / top if top > 0 else np.zeros(6)
    w = np.clip(w, 1.0 / max_sigma_ratio**2, 1.0)
    Wn = (V * w) @ V.T
    return Wn / floor[:, None] / floor[None, :]


def _points(cloud: small_gicp.PointCloud) -> np.ndarray:
    return np.asarray(cloud.points())[:, :3]


def _fit_and_overlap(
    source: small_gicp.PointCloud,
    target_tree: small_gicp.KdTree,
    T: np.ndarray,
    inlier_distance: float,
    num_threads: int,
) -> tuple[float, float]:
    """RMSE (m) of inlier nearest-neighbour distances and inlier share of the source points.

    Only points on steep, structured surfaces are counted when there are enough of them:
    steep (|normal_z| < 0.7: walls, poles, trunks, facades) because ground and ceiling
    overlap in almost any two indoor scans and would make unrelated places look alike;
    structured (surface variation lambda_min / trace < MAX_SURFACE_VARIATION: a plane or a
    line) because foliage and mixed pixels scatter in depth, so even a perfect alignment of
    a tree crown leaves ~0.15-0.2 m between nearest neighbours and would fail the fitness
    test in any vegetated place.
    """
    pts = _points(source)
    steep = np.abs(np.asarray(source.normals())[:, :3] @ T[:3, :3].T[:, 2]) < 0.7
    steep_idx = np.flatnonzero(steep)
    if len(steep_idx) >= 50:
        # shape of the steep points only (neighbours among all points), from raw covariances:
        # small_gicp's are regularised to planes and carry no shape
        cov = local_covariances(pts, SHAPE_NEIGHBOURS, query_idx=steep_idx)
        ev = np.linalg.eigvalsh(cov)  # ascending
        structured = ev[:, 0] < MAX_SURFACE_VARIATION * np.maximum(ev.sum(axis=1), 1e-12)
        pts = pts[steep_idx[structured]] if structured.sum() >= 50 else pts[steep_idx]
    moved = pts @ T[:3, :3].T + T[:3, 3]
    _, sq = target_tree.batch_nearest_neighbor_search(moved, num_threads=num_threads)
    sq = np.asarray(sq, dtype=np.float64).reshape(-1)
    inl = sq < inlier_distance**2
    overlap = float(inl.mean()) if len(sq) else 0.0
    fitness = float(np.sqrt(np.mean(sq[inl]))) if inl.any() else float("inf")
    return fitness, overlap


def verify(
    target: np.ndarray,
    source: np.ndarray,
    init_T_target_source: np.ndarray,
    params: VerifyParams = VerifyParams(),
) -> VerifyResult:
    """Register ``source`` (N, 3) onto ``target`` (M, 3) from the initial guess and judge it."""
    p = params
    guess_yaw = yaw_of(init_T_target_source)
    if len(target) < 10 or len(source) < 10:
        return VerifyResult(
            False, np.asarray(init_T_target_source, float), np.inf, 0.0,
            np.degrees(guess_yaw), np.zeros((6, 6)), "too few points",
        )  # fmt: skip
    tgt = np.ascontiguousarray(target, dtype=np.float64)
    src = np.ascontiguousarray(source, dtype=np.float64)
    T = np.asarray(init_T_target_source, dtype=np.float64)
    if p.coarse_voxel > p.voxel:
        ct, ct_tree = small_gicp.preprocess_points(tgt, p.coarse_voxel, num_threads=p.num_threads)
        cs, _ = small_gicp.preprocess_points(src, p.coarse_voxel, num_threads=p.num_threads)
        coarse = small_gicp.align(
            ct, cs, ct_tree, init_T_target_source=T, registration_type="GICP",
            max_correspondence_distance=p.coarse_max_correspondence,
            max_iterations=p.max_iterations, num_threads=p.num_threads,
        )  # fmt: skip
        T = coarse.T_target_source
    ft, ft_tree = small_gicp.preprocess_points(tgt, p.voxel, num_threads=p.num_threads)
    fs, _ = small_gicp.preprocess_points(src, p.voxel, num_threads=p.num_threads)
    fine = small_gicp.align(
        ft, fs, ft_tree, init_T_target_source=T, registration_type="GICP",
        max_correspondence_distance=p.max_correspondence,
        max_iterations=p.max_iterations, num_threads=p.num_threads,
    )  # fmt: skip
    T = np.array(fine.T_target_source)
    fitness, overlap = _fit_and_overlap(fs, ft_tree, T, p.inlier_distance, p.num_threads)
    yaw = yaw_of(T)
    info = scaled_information(
        np.asarray(fine.H), p.min_sigma_trans, np.radians(p.min_sigma_rot_deg), p.max_sigma_ratio
    )
    reason = ""
    if not fine.converged:
        reason = "gicp did not converge"
    elif overlap < p.min_overlap:
        reason = f"overlap {overlap:.2f} < {p.min_overlap:.2f}"
    elif fitness > p.max_fitness:
        reason = f"fitness {fitness:.3f} m > {p.max_fitness:.3f} m"
    elif abs(np.degrees(wrap_angle(yaw - guess_yaw))) > p.yaw_tolerance_deg:
        reason = (
            f"yaw {np.degrees(yaw):.1f} deg disagrees with guess {np.degrees(guess_yaw):.1f} deg"
        )
    return VerifyResult(not reason, T, fitness, overlap, float(np.degrees(yaw)), info, reason)
