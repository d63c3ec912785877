"""Generalized-ICP scan-to-map registration (improved FLOAM, paper 000, section 2.2).

Per-point covariances from the k nearest neighbours plus lambda*I (eq. (1), lambda = 1e-6;
``covariances``), a Mahalanobis cost with the joint covariance C_ij = R Sigma_p R^T + Sigma_q
(eqs. (2)-(3)), minimised over SE(3) by Gauss-Newton with Levenberg-Marquardt damping (eq. (4);
``solver``); the information matrices C_ij^-1 are re-evaluated with the current rotation every
iteration (eq. (5)). Convergence follows PCL's TransformationEpsilon / FitnessEpsilon (1e-6).

The names the registration modules share (result, error, SE(3) helpers, k-NN tree, solver)
live in their own modules and are re-exported here, so ``slam.registration.gicp`` keeps
serving every caller.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError
from slam.registration import kernels
from slam.registration.covariances import COVARIANCE_MODES, estimate_covariances
from slam.registration.neighbours import SERIAL_QUERIES, KnnTree
from slam.registration.neighbours import _workers as _workers
from slam.registration.pose_prior import PosePrior
from slam.registration.result import (
    CONVERGED_REASONS,
    STOP_REASONS,
    RegistrationError,
    RegistrationResult,
)
from slam.registration.result import _check_points as _check_points
from slam.registration.se3 import se3_exp, skew, transform
from slam.registration.solver import Associate, solve_weighted
from slam.registration.solver import _cost as _cost
from slam.registration.solver import _linearise as _linearise

__all__ = [
    "CONVERGED_REASONS",
    "COVARIANCE_MODES",
    "SERIAL_QUERIES",
    "STOP_REASONS",
    "Associate",
    "GicpConfig",
    "GicpTarget",
    "KnnTree",
    "RegistrationError",
    "RegistrationResult",
    "estimate_covariances",
    "gicp_align",
    "mahalanobis_inliers",
    "robust_weights",
    "se3_exp",
    "skew",
    "solve_weighted",
    "transform",
]


@dataclass
class GicpConfig:
    """GICP settings (paper 000, section 2.2); distances in m. Why the defaults are what they
    are: docs/paper000.md (GICP settings)."""

    k_covariance: int = 10  # neighbours per covariance, eq. (1)
    lambda_reg: float = 1e-6  # the lambda I of eq. (1), m^2
    # the sensor's range noise (m): eq. (1) also gets point_noise^2 I, so no pair claims a
    # surface thinner than the sensor measures it (docs/paper000.md, GICP settings); 0 = eq.
    # (1) as printed
    point_noise: float = 0.01
    # the beam's angular uncertainty (deg): a source point at range r gets (r sigma)^2 across
    # its ray (``add_beam_angle_noise``), so a far surface claims no more than the beam
    # resolves; 0.05 deg, about the spread of a Velodyne beam's footprint (docs/paper000.md,
    # GICP settings); 0 = off
    beam_angle_noise: float = 0.05
    # "raw": eq. (1) as written; "plane": eigenvalues (plane_epsilon, 1, 1) (Segal et al.);
    # "shape": plane, line or isotropic by what the support spans (``estimate_covariances``)
    covariance_mode: str = "raw"
    plane_epsilon: float = 1e-3  # the normal's eigenvalue of a regularised plane or line
    line_ratio: float = 0.05  # "shape": lambda_2 / lambda_1 below which a support is a line
    # a support on one scan line borrows the other lines' nearest points this near (0 = off)
    span_distance: float = 2.0
    max_correspondence: float = 1.0  # pairs farther apart are rejected
    max_iterations: int = 30
    transformation_epsilon: float = 1e-6  # squared step (m^2 and rad^2) that stops the solver
    fitness_epsilon: float = 1e-6  # relative cost change that stops the solver
    # also stop when the steps still to come (the geometric tail of the last two) are below
    # the transformation epsilon (``solve_weighted``)
    predict_convergence: bool = True
    threads: int = 2  # k-NN threads for batches of at least SERIAL_QUERIES points
    # pairs above this many times the median squared Mahalanobis distance are left out of
    # the step, not of the fitness (``mahalanobis_inliers``); 0 = off
    outlier_ratio: float = 0.0
    # Geman-McClure weights (c^2 / (c^2 + d^2))^2 on each pair's squared Mahalanobis distance
    # d^2, c^2 this many times the median d^2 (``robust_weights``): a moving car's pairs,
    # far off in metres times the information, stop steering the step; 0 = off
    robust_scale: float = 100.0

    @property
    def regularisation(self) -> float:
        """What eq. (1) adds to each covariance's diagonal (m^2): lambda + point_noise^2."""
        return self.lambda_reg + self.point_noise**2

    def __post_init__(self) -> None:
        if self.covariance_mode not in COVARIANCE_MODES:
            raise ConfigError(
                f"unknown covariance_mode '{self.covariance_mode}'; valid: "
                + ", ".join(COVARIANCE_MODES)
            )
        if self.k_covariance < 3:
            raise ConfigError(f"k_covariance must be >= 3, got {self.k_covariance}")
        if self.point_noise < 0:
            raise ConfigError(f"point_noise must be >= 0 m, got {self.point_noise}")
        if self.beam_angle_noise < 0:
            raise ConfigError(f"beam_angle_noise must be >= 0 deg, got {self.beam_angle_noise}")
        if self.span_distance < 0:
            raise ConfigError(f"span_distance must be >= 0 m, got {self.span_distance}")
        if self.max_correspondence <= 0 or self.max_iterations < 1:
            raise ConfigError("max_correspondence must be > 0 and max_iterations >= 1")
        if self.robust_scale < 0:
            raise ConfigError(f"robust_scale must be >= 0 (0 = off), got {self.robust_scale}")
        if self.outlier_ratio < 0 or 0 < self.outlier_ratio <= 1:
            raise ConfigError(
                f"outlier_ratio must be 0 (off) or > 1 (x the median), got {self.outlier_ratio}"
            )


class GicpTarget:
    """Target of a GICP registration: points (M, 3), covariances (M, 3, 3) and a KD-tree."""

    def __init__(self, points: np.ndarray, covs: np.ndarray, tree: cKDTree | None = None):
        self.points = _check_points(points, "target points")
        self.covs = np.asarray(covs, dtype=np.float64)
        if self.covs.shape != (len(self.points), 3, 3):
            raise RegistrationError(
                f"target covariances must be ({len(self.points)}, 3, 3), got {self.covs.shape}"
            )
        self.tree = cKDTree(self.points) if tree is None else tree

    @classmethod
    def from_points(cls, xyz: np.ndarray, cfg: GicpConfig | None = None) -> GicpTarget:
        """Target with covariances estimated from the target's own neighbourhoods (eq. (1))."""
        cfg = cfg or GicpConfig()
        xyz = _check_points(xyz, "target points")
        tree = cKDTree(xyz)
        covs = estimate_covariances(
            xyz,
            cfg.k_covariance,
            cfg.regularisation,
            cfg.covariance_mode,
            tree=tree,
            plane_epsilon=cfg.plane_epsilon,
            line_ratio=cfg.line_ratio,
            threads=cfg.threads,
        )
        return cls(xyz, covs, tree)

    def __len__(self) -> int:
        return len(self.points)


def _mahalanobis_sq(T: np.ndarray, p: np.ndarray, q: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(N,) squared Mahalanobis distances e^T W e of the pairs, e = R p + t - q."""
    e = p @ T[:3, :3].T + T[:3, 3] - q
    return np.einsum("ni,nij,nj->n", e, W, e)


def mahalanobis_inliers(
    T: np.ndarray, p: np.ndarray, q: np.ndarray, W: np.ndarray, ratio: float
) -> np.ndarray | None:
    """Mask of the pairs whose squared Mahalanobis distance e^T W e (e = R p + t - q) is at
    most ``ratio`` times the median of all pairs; None when every pair passes.

    GICP's cost has no robust term: a pair of two different surfaces within the distance
    limit claims the millimetre of its plane covariances and can outweigh thousands of good
    pairs (docs/robustness.md, "A car roof against GICP's cost"). Relative to the median, the
    test scales with how far the start is off and with the sensor."""
    d2 = _mahalanobis_sq(T, p, q, W)
    if not len(d2):
        return None
    keep = d2 <= ratio * float(np.median(d2))
    return None if keep.all() else keep


def robust_weights(
    T: np.ndarray, p: np.ndarray, q: np.ndarray, W: np.ndarray, scale: float
) -> np.ndarray | None:
    """Geman-McClure IRLS weights (c^2 / (c^2 + d^2))^2 of the pairs, d^2 = e^T W e and
    c^2 = ``scale`` x the median d^2 (scale-free: wide while the start is off, tight at the
    minimum); None when there are no pairs."""
    d2 = _mahalanobis_sq(T, p, q, W)
    if not len(d2):
        return None
    c2 = scale * max(float(np.median(d2)), 1e-12)
    return (c2 / (c2 + d2)) ** 2


def _source_covariances(
    src: np.ndarray, source_covs: np.ndarray | None, cfg: GicpConfig
) -> np.ndarray:
    """The source's (N, 3, 3) covariances: ``source_covs`` checked, or eq. (1) on the source."""
    if source_covs is None:
        return estimate_covariances(
            src,
            cfg.k_covariance,
            cfg.regularisation,
            cfg.covariance_mode,
            plane_epsilon=cfg.plane_epsilon,
            line_ratio=cfg.line_ratio,
            threads=cfg.threads,
        )
    if source_covs.shape != (len(src), 3, 3):
        raise RegistrationError(f"source_covs must be ({len(src)}, 3, 3), got {source_covs.shape}")
    return source_covs


def _gicp_association(
    src: np.ndarray,
    source_covs: np.ndarray,
    target: GicpTarget,
    cfg: GicpConfig,
    reference: bool,
) -> Associate:
    """``associate(T)`` for ``solve_weighted``: nearest target point within
    ``cfg.max_correspondence`` and the information W = (R Sigma_p R^T + Sigma_q)^-1 (eqs.
    (3), (5)); with the compiled kernel also H, b and the cost in the same pass. The
    ``mahalanobis_inliers`` gate (``cfg.outlier_ratio``) leaves pairs out of the step only."""
    max_d = cfg.max_correspondence

    def associate(T):
        moved = transform(T, src)
        d, j = target.tree.query(
            moved, k=1, distance_upper_bound=max_d, workers=_workers(len(moved), cfg.threads)
        )
        ok = np.isfinite(d)
        R = T[:3, :3]
        if reference:
            C = np.einsum("ij,njk,lk->nil", R, source_covs[ok], R) + target.covs[j[ok]]  # (3)
            p, q, W, sqd = src[ok], target.points[j[ok]], np.linalg.inv(C), d[ok] ** 2  # (5)
            keep = mahalanobis_inliers(T, p, q, W, cfg.outlier_ratio) if cfg.outlier_ratio else None
            if keep is not None:  # the fitness stays that of every pair within the limit
                p, q, W = p[keep], q[keep], W[keep]
            w = robust_weights(T, p, q, W, cfg.robust_scale) if cfg.robust_scale else None
            return p, q, W, w, sqd
        # eqs. (3)-(5) and H, b, cost in one pass over the correspondences
        j = np.where(ok, j, len(target.points))  # the "no correspondence" index, as cKDTree's
        p, q, W, H, b, cost = kernels.gicp_terms(T, src, source_covs, target.points, target.covs, j)
        sqd = d[ok] ** 2
        keep = mahalanobis_inliers(T, p, q, W, cfg.outlier_ratio) if cfg.outlier_ratio else None
        if keep is not None:  # the fitness stays that of every pair within the limit
            p, q, W = p[keep], q[keep], W[keep]
        w = robust_weights(T, p, q, W, cfg.robust_scale) if cfg.robust_scale else None
        if keep is not None or w is not None:  # the fused pass had unit weights on every pair
            H, b, cost = kernels.linearise(T, p, q, W, w)
        return p, q, W, w, sqd, (H, b, cost)

    return associate


def gicp_align(
    source_xyz: np.ndarray,
    target: GicpTarget | np.ndarray,
    init_T: np.ndarray | None = None,
    cfg: GicpConfig | None = None,
    source_covs: np.ndarray | None = None,
    *,
    reference: bool = False,
    prior: PosePrior | None = None,
) -> RegistrationResult:
    """Align ``source_xyz`` to ``target`` (a GicpTarget, e.g. the local map, or raw points).

    Minimises eq. (4), sum d^T (R Sigma_p R^T + Sigma_q)^-1 d over nearest-neighbour pairs
    closer than ``cfg.max_correspondence``. ``source_covs`` (N, 3, 3) default to eq. (1) on
    the source itself. Returns T_target_source and the Hessian at the solution.
    ``target.tree`` may be a cKDTree or anything with its ``query`` (the local map
    ``VoxelHashMap``). reference: the numpy solver throughout (the compiled kernels give the
    same transform; see tests/test_gicp.py). prior: a Gaussian prior on the pose
    (``PosePrior``, e.g. the tracked prediction; ``solve_weighted``).
    """
    cfg = cfg or GicpConfig()
    src = _check_points(source_xyz, "source points")
    if not isinstance(target, GicpTarget):
        target = GicpTarget.from_points(target, cfg)
    if len(src) < 6 or len(target) < 6:
        raise RegistrationError(
            f"GICP needs at least 6 source and target points, got {len(src)} and {len(target)}"
        )
    source_covs = _source_covariances(src, source_covs, cfg)
    init = np.eye(4) if init_T is None else np.asarray(init_T, dtype=np.float64)
    return solve_weighted(
        init,
        _gicp_association(src, source_covs, target, cfg, reference),
        len(src),
        max_iterations=cfg.max_iterations,
        transformation_epsilon=cfg.transformation_epsilon,
        fitness_epsilon=cfg.fitness_epsilon,
        reference=reference,
        predict_convergence=cfg.predict_convergence,
        prior=prior,
    )
