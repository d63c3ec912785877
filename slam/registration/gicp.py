"""Generalized-ICP scan-to-map registration (improved FLOAM, paper 000, section 2.2).

Per-point covariances from the k nearest neighbours plus lambda*I (eq. (1), lambda = 1e-6),
a Mahalanobis cost with the joint covariance C_ij = R Sigma_p R^T + Sigma_q (eqs. (2)-(3)),
minimised over SE(3) by Gauss-Newton with Levenberg-Marquardt damping (eq. (4)); the
information matrices C_ij^-1 are re-evaluated with the current rotation every iteration
(eq. (5)). Convergence follows PCL's TransformationEpsilon / FitnessEpsilon (1e-6).

This module also holds what the registration modules share: the result type, the typed
error and the weighted Gauss-Newton solver over SE(3) (``solve_weighted``), which the
point-to-edge / point-to-plane matcher of ``feature_icp`` reuses with its own weights.
Tangent ordering everywhere is GTSAM's: rotation first, perturbation on the right
(``T <- T exp(xi)``), so Hessians live in the source (sensor) frame.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import small_gicp
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError, SlamError
from slam.registration import kernels

log = logging.getLogger(__name__)

COVARIANCE_MODES = ("raw", "plane", "shape")
STOP_REASONS = ("step", "fitness", "stalled", "max_iterations")
CONVERGED_REASONS = ("step", "fitness")


class RegistrationError(SlamError):
    """Registration could not run (too few points or correspondences)."""


@dataclass
class GicpConfig:
    """GICP settings (paper 000, section 2.2).

    k_covariance: neighbours per covariance (eq. (1)); lambda_reg: the lambda*I term (m^2).
    covariance_mode: "raw" = eq. (1) as written; "plane" = Segal et al.'s regularisation
    (eigenvalues replaced by (plane_epsilon, 1, 1)); "shape" = regularise by what the
    neighbourhood supports (see ``estimate_covariances``): a surface spanning several scan
    lines -> plane (plane_epsilon, 1, 1), a line spanning several scan lines (pole, corner)
    -> line (plane_epsilon, plane_epsilon, 1), a support sampled by one scan line only (a
    ring on open ground) or degenerate -> isotropic (1, 1, 1), i.e. no direction is
    trusted. line_ratio: lambda_2 / lambda_1 below which a support is a line.
    span_distance (m): a source support whose k neighbours all lie on one scan line borrows
    the nearest points of the other scan lines within this distance, so that eq. (1) sees the
    surface across the lines (taken as planar over the gap; 16-beam ground rings near a car
    are 1-2.5 m apart); 0 = off (such a support is then isotropic at its extent, see
    ``estimate_covariances``). max_correspondence:
    rejection distance (m). transformation_epsilon: squared step size (m^2 and rad^2) below
    which the solver stops; fitness_epsilon: relative change of the cost below which it stops.
    predict_convergence: also stop when the steps contract so fast that all the steps still to
    come (the geometric tail of the last two) sum to less than the transformation epsilon,
    without the association that would only confirm it (see ``solve_weighted``; improved
    FLOAM 64/128-beam scan-to-map: 2.84 -> 2.06 associations per frame on the OS-128 urban
    drive, APE over 100 frames 4.89 -> 4.74 cm HDL-64, 4.11 -> 4.06 OS-128; corridor 300
    1.21 -> 1.18 cm, park 300 2.27 -> 2.27).
    outlier_ratio: a pair whose squared Mahalanobis distance is above this many times the
    median of the iteration's pairs is left out of the step (``mahalanobis_inliers``: a pair
    of two different surfaces, e.g. a car roof first seen against the body below it, weighs
    as much as thousands of good pairs); the fitness (RMSE) still counts every pair within
    max_correspondence. 0 = off (default: on the real HDL-32E pair the gate moved the
    kernel-equivalence test's rotation to 0.26 deg, past its 0.2 deg bound). 1000 against 0,
    improved_floam, urban
    HDL-64E first 100 frames APE 3.71 -> 2.14 cm, worst step 14.6 -> 2.1 cm, 1 -> 0 frames
    lost; OS-128 3.81 -> 3.76 cm; VLP-16 5.17 -> 5.15 cm; corridor / plaza 300 scans 1.20 ->
    1.16 / 0.84 -> 0.83 cm. 100 did a little better on most (2.11 cm, 1.2 cm; 3.62; 1.14 /
    0.82; the street scene's departure worst step 20 -> 1.2 cm) but from a start 0.49 m off
    (the real HDL-32E pair, scan to scan from the identity) it left out the pairs that carry
    the correction and stopped 43 cm off (1000: 0.37 cm, 0 : 1.4 cm).
    """

    k_covariance: int = 10
    lambda_reg: float = 1e-6
    covariance_mode: str = "raw"
    plane_epsilon: float = 1e-3
    line_ratio: float = 0.05
    span_distance: float = 2.0
    max_correspondence: float = 1.0
    max_iterations: int = 30
    transformation_epsilon: float = 1e-6
    fitness_epsilon: float = 1e-6
    predict_convergence: bool = True
    threads: int = 2
    outlier_ratio: float = 0.0

    def __post_init__(self) -> None:
        if self.covariance_mode not in COVARIANCE_MODES:
            raise ConfigError(
                f"unknown covariance_mode '{self.covariance_mode}'; valid: "
                + ", ".join(COVARIANCE_MODES)
            )
        if self.k_covariance < 3:
            raise ConfigError(f"k_covariance must be >= 3, got {self.k_covariance}")
        if self.span_distance < 0:
            raise ConfigError(f"span_distance must be >= 0 m, got {self.span_distance}")
        if self.max_correspondence <= 0 or self.max_iterations < 1:
            raise ConfigError("max_correspondence must be > 0 and max_iterations >= 1")
        if self.outlier_ratio < 0 or 0 < self.outlier_ratio <= 1:
            raise ConfigError(
                f"outlier_ratio must be 0 (off) or > 1 (x the median), got {self.outlier_ratio}"
            )


@dataclass
class RegistrationResult:
    """Outcome of a registration.

    T_target_source: 4x4. H: 6x6 Gauss-Newton Hessian of the cost at the solution (rotation
    first, source-frame tangent), b: gradient. cost: final weighted cost (sum of squared
    Mahalanobis / point-to-feature distances); fitness: mean squared Euclidean distance of
    inlier correspondences (m^2, PCL's fitness score); rmse = sqrt(fitness). dof: number of
    scalar residuals minus 6 (for the residual variance cost / dof).

    stop_reason: why the solver stopped, one of ``STOP_REASONS``: "step" (update below
    transformation_epsilon), "fitness" (relative cost change below fitness_epsilon),
    "stalled" (no damped step lowered the cost although the Gauss-Newton step was not yet
    small: a saddle, a bad association or numerical trouble) or "max_iterations".
    converged is True only for "step" and "fitness".
    """

    T_target_source: np.ndarray
    H: np.ndarray
    b: np.ndarray
    cost: float
    fitness: float
    rmse: float
    num_inliers: int
    num_source: int
    iterations: int
    converged: bool
    dof: int = 0
    stop_reason: str = "step"

    @property
    def inlier_ratio(self) -> float:
        """Share of source points that found a correspondence (0-1)."""
        return self.num_inliers / max(self.num_source, 1)


# --------------------------------------------------------------------------- SE(3) helpers


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 exp of a twist xi = (omega, v), rotation first (GTSAM Pose3.Expmap ordering)."""
    omega, v = np.asarray(xi[:3], float), np.asarray(xi[3:], float)
    theta = float(np.linalg.norm(omega))
    K = skew(omega)
    if theta < 1e-9:
        V = np.eye(3) + 0.5 * K
    else:
        V = (
            np.eye(3)
            + (1 - np.cos(theta)) / theta**2 * K
            + (theta - np.sin(theta)) / theta**3 * (K @ K)
        )
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(omega).as_matrix()
    T[:3, 3] = V @ v
    return T


def transform(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Apply a 4x4 pose to (N, 3) points."""
    return xyz @ T[:3, :3].T + T[:3, 3]


def _check_points(xyz: np.ndarray, name: str) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise RegistrationError(f"{name} must be an (N, 3) array, got shape {xyz.shape}")
    return xyz


# --------------------------------------------------------------------------- covariances

SERIAL_QUERIES = 20000  # below this many queries cKDTree runs on one thread: starting its
# worker threads cost more than they saved (700 queries: 1.2 ms on one, 2.2 ms on two)


def _workers(n_queries: int, threads: int) -> int:
    """cKDTree ``workers`` for a batch of ``n_queries``: ``threads`` for large batches only."""
    return threads if n_queries >= SERIAL_QUERIES else 1


class KnnTree:
    """Exact k-NN over fixed points with ``cKDTree.query``'s interface and results (k
    nearest, ascending; beyond ``distance_upper_bound`` or missing: inf and ``len(points)``),
    answered by small_gicp's KdTree: the same neighbours as a cKDTree at about half the cost
    (11.7k voxel-thinned 64-beam features, k = 10: 1.6 + 7.7 ms CPU against 2.1 + 14.3)."""

    def __init__(self, points: np.ndarray):
        self.n = len(points)
        self._tree = small_gicp.KdTree(np.ascontiguousarray(points, dtype=np.float64), 1)

    def query(
        self, x: np.ndarray, k: int = 1, distance_upper_bound: float = np.inf, workers: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        k_found = min(int(k), self.n)
        if len(x) == 0 or k_found == 0:
            d, j = np.full((len(x), k), np.inf), np.full((len(x), k), self.n, dtype=np.int64)
        else:
            j, sq = self._tree.batch_knn_search(x, k_found, num_threads=max(int(workers), 1))
            j, d = j.astype(np.int64), np.sqrt(sq)
            far = ~(d < distance_upper_bound)  # cKDTree: neighbours closer than the bound
            d[far], j[far] = np.inf, self.n
            if k_found < k:
                d = np.pad(d, ((0, 0), (0, k - k_found)), constant_values=np.inf)
                j = np.pad(j, ((0, 0), (0, k - k_found)), constant_values=self.n)
        return (d[:, 0], j[:, 0]) if k == 1 else (d, j)


def _covariances_of(nb: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n, 3, 3) eq. (1) of neighbour sets nb (n, K, 3) with 0/1 weights w (n, K)."""
    cnt = w.sum(axis=1)
    centred = nb - (np.einsum("nk,nki->ni", w, nb) / cnt[:, None])[:, None, :]
    return np.einsum("nk,nki,nkj->nij", w, centred, centred) / (cnt - 1)[:, None, None]


def _wide_neighbours(
    tree: cKDTree | KnnTree,
    x: np.ndarray,
    k_wide: int,
    own: np.ndarray,
    labels: np.ndarray,
    m: int,
    span_distance: float,
    threads: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(d, j) (n, k_wide) as ``tree.query(x, k_wide, span_distance)`` gives them where it
    matters to ``_span_scan_lines``: the k_wide / 2 nearest first; only the rows whose m
    nearest points of other lines than ``own`` are not all among them (and whose half set
    does not exhaust ``span_distance``) are queried again with k_wide. The others' missing
    columns are "beyond the bound" (inf, ``len(labels)``): none of them would be taken,
    they weigh 0 in eq. (1), and the exhaustion test of the full set holds for these rows
    as well (same covariances to the bit, about half the k-NN work on 16-beam features)."""
    n = len(labels)
    k_half = min(max(k_wide // 2, 1), k_wide)
    d, j = tree.query(
        x, k=k_half, distance_upper_bound=span_distance, workers=_workers(len(x), threads)
    )
    d, j = d.reshape(len(x), k_half), j.reshape(len(x), k_half)
    if k_half == k_wide:
        return d, j
    found = np.isfinite(d)
    other = found & (labels[np.where(found, j, 0)] != own[:, None])
    settled = (other.sum(axis=1) >= m) | ~found[:, -1]
    d = np.pad(d, ((0, 0), (0, k_wide - k_half)), constant_values=np.inf)
    j = np.pad(j, ((0, 0), (0, k_wide - k_half)), constant_values=n)
    redo = np.flatnonzero(~settled)
    if len(redo):
        dr, jr = tree.query(
            x[redo],
            k=k_wide,
            distance_upper_bound=span_distance,
            workers=_workers(len(redo), threads),
        )
        d[redo], j[redo] = dr.reshape(len(redo), k_wide), jr.reshape(len(redo), k_wide)
    return d, j


def _span_scan_lines(
    xyz: np.ndarray,
    query: np.ndarray,
    idx: np.ndarray,
    rows: np.ndarray,
    labels: np.ndarray,
    tree: cKDTree | KnnTree,
    span_distance: float,
    threads: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (1) on one-line supports extended across scan lines.

    For each query in ``rows`` (its k neighbours ``idx`` all on one scan line) the
    m = max(k // 2, 3) nearest reference points of *other* lines within ``span_distance``
    join its support. Returns (the rows that found at least 2 such points, their (n, 3, 3)
    covariances in m^2, without lambda). The m are looked for among the 4k nearest
    neighbours (one query on ``tree``); rows where that set may miss some (fewer than m
    found and the set does not exhaust ``span_distance``) query a KD-tree of the other
    lines' points, one per scan line (<= the number of beams); no per-point loop.
    """
    k = idx.shape[1]
    m = max(k // 2, 3)
    k_wide = min(4 * k, len(xyz))
    own = labels[idx[rows, 0]]
    d, j = _wide_neighbours(tree, query[rows], k_wide, own, labels, m, span_distance, threads)
    found = np.isfinite(d)
    j = np.where(found, j, 0)
    other = found & (labels[j] != labels[idx[rows, :1]])
    take = other & (np.cumsum(other, axis=1) <= m)  # the m nearest points of other lines
    n_take = take.sum(axis=1)
    exact = (n_take >= m) | ~found[:, -1]
    fast = exact & (n_take >= 2)
    done = [rows[fast]]
    covs = [
        _covariances_of(
            np.concatenate([xyz[idx[rows[fast]]], xyz[j[fast]]], axis=1),
            np.concatenate([np.ones((int(fast.sum()), k)), take[fast]], axis=1),
        )
    ]
    slow = rows[~exact]
    own = labels[idx[slow, 0]]
    for line in np.unique(own):
        sel = slow[own == line]
        cand = np.flatnonzero(labels != line)
        if len(cand) < 2:
            continue
        ds, js = cKDTree(xyz[cand]).query(
            query[sel],
            k=min(m, len(cand)),
            distance_upper_bound=span_distance,
            workers=_workers(len(sel), threads),
        )
        ok = np.isfinite(ds.reshape(len(sel), -1))
        js = js.reshape(len(sel), -1)
        enough = ok.sum(axis=1) >= 2
        sel, ok, js = sel[enough], ok[enough], js[enough]
        done.append(sel)
        covs.append(
            _covariances_of(
                np.concatenate([xyz[idx[sel]], xyz[cand[np.where(ok, js, 0)]]], axis=1),
                np.concatenate([np.ones((len(sel), k)), ok], axis=1),
            )
        )
    return np.concatenate(done), np.concatenate(covs)


def estimate_covariances(
    xyz: np.ndarray,
    k: int = 10,
    lambda_reg: float = 1e-6,
    mode: str = "raw",
    *,
    query: np.ndarray | None = None,
    tree: cKDTree | None = None,
    plane_epsilon: float = 1e-3,
    line_ratio: float = 0.05,
    labels: np.ndarray | None = None,
    span_distance: float = 0.0,
    threads: int = 2,
    reference: bool = False,
    neighbours: np.ndarray | None = None,
) -> np.ndarray:
    """(M, 3, 3) covariances (m^2) of the k nearest neighbours in ``xyz`` of each query point.

    Eq. (1): Sigma = 1/(k-1) sum (p_t - mean)(p_t - mean)^T + lambda I. ``query`` defaults to
    ``xyz`` itself (so the point is its own first neighbour). mode "plane" replaces the
    eigenvalues by (eps, 1, 1) (Segal et al., GICP; small_gicp's default), so every point
    weighs alike and acts as a plane; the result is then dimensionless.

    ``labels`` (the scan line / ring of each reference point), when given, mark supports whose
    neighbours all lie on one scan line: one line cannot tell a surface's normal. In mode
    "raw" such a support is extended by the max(k // 2, 3) nearest points of the other scan
    lines within ``span_distance`` (m) and eq. (1) runs on the union (the surface seen across
    the lines); where fewer than 2 such points exist (or ``span_distance`` is 0) its
    covariance is isotropic at the support's extent (largest eigenvalue). That isotropic
    fallback alone left ~90 % of 16-beam ground supports nearly point-to-point and weak
    (< 20 % of the pitch information), and point-to-point on ring-sampled facades pulls the
    scan vertically toward the map's ring pattern, which moves with the speed: a steady pitch
    bias at car speed (simulated urban drive at 10-15 m/s: -0.1 to -0.4 deg per frame against
    a ground-truth map, +9.7 m of height after 134 m).

    mode "shape" regularises by the shape the support really has (dimensionless as well):
    with eigenvalues l1 >= l2 >= l3, a support with l2 >= line_ratio * l1 is a surface ->
    (eps, 1, 1) with the normal of the smallest eigenvalue; a line (l2 < line_ratio * l1) ->
    (eps, eps, 1) along the largest; a support whose neighbours all carry the same ``labels``
    value (the scan line / ring of each reference point) -> isotropic (1, 1, 1). One scan
    line samples a surface only along the line: on open ground a 16-beam ring is a thin arc
    whose "normal" points at the neighbouring rings, and since the ring pattern moves with
    the sensor, trusting it pulls every registration toward zero motion.

    ``tree``: a cKDTree of ``xyz`` or anything with its ``query`` (the local map). reference:
    eq. (1) by numpy einsum instead of the compiled kernel (same numbers). neighbours:
    the (M, k) indices into ``xyz`` of each query's k nearest points when the caller has
    them already (the same query is then not repeated).
    """
    xyz = _check_points(xyz, "points")
    query = xyz if query is None else _check_points(query, "query points")
    if len(xyz) < 3:
        raise RegistrationError(f"need at least 3 points for covariances, got {len(xyz)}")
    k_eff = min(k, len(xyz))
    if neighbours is not None:
        idx = np.asarray(neighbours, dtype=np.int64)
        if idx.shape != (len(query), k_eff):
            raise RegistrationError(f"neighbours must be ({len(query)}, {k_eff}), got {idx.shape}")
    else:
        tree = KnnTree(xyz) if tree is None else tree
        _, idx = tree.query(query, k=k_eff, workers=_workers(len(query), threads))
    if reference:
        nb = xyz[idx.reshape(len(query), k_eff)]
        centred = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred) / (k_eff - 1)
    else:
        cov = kernels.neighbour_covariances(xyz, idx.reshape(len(query), k_eff))
    single = None
    if labels is not None:  # supports sampled by one scan line only
        lab = np.asarray(labels)[idx.reshape(len(query), k_eff)]
        single = np.all(lab == lab[:, :1], axis=1)
    if mode == "raw" and single is not None and single.any():
        if span_distance > 0:  # the surface across the scan lines, where they are close
            spanned, spanned_cov = _span_scan_lines(
                xyz,
                query,
                idx.reshape(len(query), k_eff),
                np.flatnonzero(single),
                np.asarray(labels),
                KnnTree(xyz) if tree is None else tree,
                span_distance,
                threads,
            )
            cov[spanned] = spanned_cov
            single = single.copy()
            single[spanned] = False
        # isotropic at the support's extent: "somewhere along this scan line", no direction
        cov[single] = np.eye(3) * np.linalg.eigvalsh(cov[single])[:, 2, None, None]
    if mode == "plane":
        w, v = np.linalg.eigh(cov)
        lam = np.array([plane_epsilon, 1.0, 1.0])
        cov = np.einsum("nij,j,nkj->nik", v, lam, v)
    elif mode == "shape":
        w, v = np.linalg.eigh(cov)  # ascending: w[:, 2] is the largest
        line = w[:, 1] < line_ratio * w[:, 2]
        lam = np.where(
            line[:, None], [plane_epsilon, plane_epsilon, 1.0], [plane_epsilon, 1.0, 1.0]
        )
        flat = w[:, 2] <= 0
        if single is not None:
            flat |= single
        lam[flat] = 1.0
        cov = np.einsum("nij,nj,nkj->nik", v, lam, v)
    elif mode != "raw":
        raise ConfigError(f"unknown covariance mode '{mode}'; valid: {', '.join(COVARIANCE_MODES)}")
    cov[:, [0, 1, 2], [0, 1, 2]] += lambda_reg
    return cov


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
            cfg.lambda_reg,
            cfg.covariance_mode,
            tree=tree,
            plane_epsilon=cfg.plane_epsilon,
            line_ratio=cfg.line_ratio,
            threads=cfg.threads,
        )
        return cls(xyz, covs, tree)

    def __len__(self) -> int:
        return len(self.points)


# --------------------------------------------------------------------------- the solver

# associate(T) -> (p source points (N, 3), q target points (N, 3), W (N, 3, 3) information in
# the target frame, robust weights (N,) or None, squared Euclidean distances (N,)), optionally
# followed by (H, b, cost) at T when the association computed them already (fused kernel)
Associate = Callable[[np.ndarray], tuple]


def _linearise(T, p, q, W, w):
    """Hessian, gradient and cost of sum w e^T W e, e = R p + t - q, right perturbation."""
    R = T[:3, :3]
    e = p @ R.T + T[:3, 3] - q
    # d e / d xi = R [-[p]x, I]  (3x6, rotation first)
    Jb = np.concatenate([-skew(p), np.broadcast_to(np.eye(3), (len(p), 3, 3))], axis=2)
    J = np.einsum("ij,njk->nik", R, Jb)
    We = np.einsum("nij,nj->ni", W, e)
    WJ = np.einsum("nij,njk->nik", W, J)
    if w is not None:
        We = We * w[:, None]
        WJ = WJ * w[:, None, None]
    H = J.reshape(-1, 6).T @ WJ.reshape(-1, 6)
    b = J.reshape(-1, 6).T @ We.reshape(-1)
    cost = float(np.einsum("ni,ni->", e, We))
    return H, b, cost


def _cost(T, p, q, W, w) -> float:
    e = p @ T[:3, :3].T + T[:3, 3] - q
    We = np.einsum("nij,nj->ni", W, e)
    if w is not None:
        We = We * w[:, None]
    return float(np.einsum("ni,ni->", e, We))


def solve_weighted(
    init_T: np.ndarray,
    associate: Associate,
    num_source: int,
    *,
    max_iterations: int,
    transformation_epsilon: float,
    fitness_epsilon: float,
    residual_dims: int = 3,
    min_inliers: int = 6,
    reference: bool = False,
    predict_convergence: bool = False,
) -> RegistrationResult:
    """Gauss-Newton / Levenberg-Marquardt on SE(3) with re-association every iteration.

    Each iteration: associate at T, build H = sum J^T W J and b = sum J^T W e, solve
    (H + mu diag H) xi = -b, accept the step when the cost with these correspondences drops
    (else raise mu and retry). Stops when the step is below ``transformation_epsilon``
    (squared metres and squared radians) or the cost changes by less than ``fitness_epsilon``
    relative. ``residual_dims`` counts scalar residuals per correspondence (for dof).
    reference: build H, b and the cost with the numpy reference (``_linearise`` / ``_cost``)
    instead of the compiled kernels (``slam.registration.kernels``, same numbers).
    predict_convergence: stop ("step") as well when the last two accepted steps contract
    (ratio r < 1/2 of their sizes, rotation and translation each) and the tail still to come,
    |xi| r / (1 - r), is below the transformation epsilon in both: the solution is then
    within the epsilon of where the iteration converges, and the association and
    linearisation that would only measure the next, smaller step are saved (64-beam
    scan-to-map: 3.05 -> ~2.3 associations per frame). The Hessian returned is the one of
    the last association, as with the plain step test.
    """
    lin, cost_of = (_linearise, _cost) if reference else (kernels.linearise, kernels.cost)
    T = np.asarray(init_T, dtype=np.float64).copy()
    mu = 1e-6
    prev_cost = None
    reason = "max_iterations"
    H = np.zeros((6, 6))
    b = np.zeros(6)
    cost, n_in, sqd, iterations = 0.0, 0, np.zeros(0), 0

    def small(xi: np.ndarray) -> bool:
        return (
            float(xi[:3] @ xi[:3]) < transformation_epsilon
            and float(xi[3:] @ xi[3:]) < transformation_epsilon
        )

    def tail_small(xi: np.ndarray, prev: np.ndarray | None) -> bool:
        if prev is None:
            return False
        for part in (slice(0, 3), slice(3, 6)):
            now, before = float(np.linalg.norm(xi[part])), float(np.linalg.norm(prev[part]))
            if now == 0.0:
                continue
            r = now / before if before > 0 else 1.0
            if r >= 0.5 or (now * r / (1.0 - r)) ** 2 >= transformation_epsilon:
                return False
        return True

    prev_xi = None

    for it in range(1, max_iterations + 1):
        iterations = it
        terms = associate(T)
        p, q, W, w, sqd = terms[:5]
        n_in = len(p)
        if n_in < min_inliers:
            raise RegistrationError(
                f"only {n_in} correspondences within the distance limit (need {min_inliers});"
                " the initial guess is too far off or the clouds do not overlap"
            )
        H, b, cost = terms[5] if len(terms) > 5 and not reference else lin(T, p, q, W, w)
        if prev_cost is not None and abs(prev_cost - cost) <= fitness_epsilon * max(cost, 1e-12):
            reason = "fitness"
            break
        prev_cost = cost
        accepted = False
        first_step = None
        for _ in range(8):
            A = H + mu * np.diag(np.maximum(np.diag(H), 1e-12))
            try:
                xi = -np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            if first_step is None:
                first_step = xi
            T_new = T @ se3_exp(xi)
            if cost_of(T_new, p, q, W, w) <= cost:
                T = T_new
                mu = max(mu * 0.1, 1e-9)
                accepted = True
                break
            mu *= 10.0
        if not accepted:
            # no damped step lowers the cost: at the minimum when even the least damped step
            # was already below the epsilon (rounding), else stuck short of it
            reason = "step" if first_step is not None and small(first_step) else "stalled"
            break
        if small(xi) or (predict_convergence and tail_small(xi, prev_xi)):
            reason = "step"
            break
        prev_xi = xi
    fitness = float(sqd.mean()) if len(sqd) else float("inf")
    return RegistrationResult(
        T_target_source=T,
        H=H,
        b=b,
        cost=cost,
        fitness=fitness,
        rmse=float(np.sqrt(fitness)),
        num_inliers=n_in,
        num_source=num_source,
        iterations=iterations,
        converged=reason in CONVERGED_REASONS,
        dof=max(residual_dims * n_in - 6, 1),
        stop_reason=reason,
    )


# --------------------------------------------------------------------------- GICP


def mahalanobis_inliers(
    T: np.ndarray, p: np.ndarray, q: np.ndarray, W: np.ndarray, ratio: float
) -> np.ndarray | None:
    """Mask of the pairs whose squared Mahalanobis distance e^T W e (e = R p + t - q) is at
    most ``ratio`` times the median of all pairs; None when every pair passes.

    GICP's cost has no robust term: a plane pair claims the millimetre its covariance has
    along the normal, so a pair of two different surfaces within the distance limit (a car
    roof first seen from close by against the body 26 cm below it) weighs as much as
    thousands of good pairs. On the urban HDL-64E drive (frame 78) 117 of 6153 pairs above
    100 x the median carried 92 % of the cost at the true pose, three roof points 84 %: the
    solution slid 8.5 cm down in z. The test is relative to the median, so that it scales
    with how far the start is off (a gap recovery's first iterations) and with the sensor."""
    e = p @ T[:3, :3].T + T[:3, 3] - q
    d2 = np.einsum("ni,nij,nj->n", e, W, e)
    if not len(d2):
        return None
    keep = d2 <= ratio * float(np.median(d2))
    return None if keep.all() else keep


def gicp_align(
    source_xyz: np.ndarray,
    target: GicpTarget | np.ndarray,
    init_T: np.ndarray | None = None,
    cfg: GicpConfig | None = None,
    source_covs: np.ndarray | None = None,
    *,
    reference: bool = False,
) -> RegistrationResult:
    """Align ``source_xyz`` to ``target`` (a GicpTarget, e.g. the local map, or raw points).

    Minimises eq. (4), sum d^T (R Sigma_p R^T + Sigma_q)^-1 d over nearest-neighbour pairs
    closer than ``cfg.max_correspondence``. ``source_covs`` (N, 3, 3) default to eq. (1) on
    the source itself. Returns T_target_source and the Hessian at the solution.
    ``target.tree`` may be a cKDTree or anything with its ``query`` (the local map
    ``VoxelHashMap``). reference: the numpy solver throughout (the compiled kernels give the
    same transform; see tests/test_gicp.py).
    """
    cfg = cfg or GicpConfig()
    src = _check_points(source_xyz, "source points")
    if not isinstance(target, GicpTarget):
        target = GicpTarget.from_points(target, cfg)
    if len(src) < 6 or len(target) < 6:
        raise RegistrationError(
            f"GICP needs at least 6 source and target points, got {len(src)} and {len(target)}"
        )
    if source_covs is None:
        source_covs = estimate_covariances(
            src,
            cfg.k_covariance,
            cfg.lambda_reg,
            cfg.covariance_mode,
            plane_epsilon=cfg.plane_epsilon,
            line_ratio=cfg.line_ratio,
            threads=cfg.threads,
        )
    elif source_covs.shape != (len(src), 3, 3):
        raise RegistrationError(f"source_covs must be ({len(src)}, 3, 3), got {source_covs.shape}")
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
            return p, q, W, None, sqd
        # eqs. (3)-(5) and H, b, cost in one pass over the correspondences
        j = np.where(ok, j, len(target.points))  # the "no correspondence" index, as cKDTree's
        p, q, W, H, b, cost = kernels.gicp_terms(T, src, source_covs, target.points, target.covs, j)
        sqd = d[ok] ** 2
        if cfg.outlier_ratio:
            keep = mahalanobis_inliers(T, p, q, W, cfg.outlier_ratio)
            if keep is not None:  # the fitness stays that of every pair within the limit
                p, q, W = p[keep], q[keep], W[keep]
                H, b, cost = kernels.linearise(T, p, q, W, None)
        return p, q, W, None, sqd, (H, b, cost)

    init = np.eye(4) if init_T is None else np.asarray(init_T, dtype=np.float64)
    return solve_weighted(
        init,
        associate,
        len(src),
        max_iterations=cfg.max_iterations,
        transformation_epsilon=cfg.transformation_epsilon,
        fitness_epsilon=cfg.fitness_epsilon,
        reference=reference,
        predict_convergence=cfg.predict_convergence,
    )
