"""LeGO-LOAM's two-step Levenberg-Marquardt scan matching with the ground residual of
LeGO-LOAM-LPB (paper 001, section 3.3; Shan and Englot 2018, section III-D).

Step 1: ground points of the scan against the plane map (point-to-plane) estimate
[roll, pitch, tz] only. Step 2: edge points against the edge map (point-to-line) estimate
[yaw, tx, ty] only, starting from step 1. The split follows what each feature class
constrains for a ground vehicle: the ground fixes height and tilt, edges (poles, corners,
wall edges) fix the horizontal position and heading. The final 6-DoF refinement (LeGO's
scan-to-map "mapping" pass) joins edges, planes and, for LeGO-LOAM-LPB, the ground residual
E_ground: the distance of each ground point to the ground plane fitted from the previous
frame (n . (R p + t) + d, eq. of 3.3: E = E_edge + E_plane + E_ground).

The two restricted steps perturb the pose in a frame at the sensor position with the
odometry frame's axes (q' = exp(dtheta) (q - t) + t + dt), so that "roll, pitch, z" are the
tilt and height over the odometry frame's ground, whatever the sensor's heading. The final
step is ``gicp.solve_weighted`` (right perturbation, GTSAM ordering), whose Hessian the front
ends turn into the information of the motion. Residuals carry Huber weights (FLOAM: 0.1 m).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from slam.deskew import se3_log
from slam.errors import ConfigError
from slam.registration.feature_icp import (
    HORIZONTAL,
    FeatureTarget,
    horizontal_pairs,
)
from slam.registration.ground_plane import FixedNormals
from slam.registration.neighbours import _workers
from slam.registration.result import RegistrationError, RegistrationResult, _check_points
from slam.registration.se3 import se3_exp, skew, transform
from slam.registration.solver import solve_weighted

# tangent indices (rotation first, GTSAM order): step 1 = roll, pitch, z; step 2 = yaw, x, y
GROUND_DOF = (0, 1, 5)
EDGE_DOF = (2, 3, 4)


@dataclass
class TwoStepConfig:
    """Two-step matching settings (paper 001, section 3.3); m and rad where not said. Why the
    defaults: docs/paper001.md (Two-step settings)."""

    # LOAM's correspondence tests (as in ``feature_icp``); plane_threshold 0.05 m, not 0.2
    k_neighbors: int = 5
    max_neighbor_distance: float = 1.0
    edge_ratio: float = 3.0
    plane_threshold: float = 0.05
    # a plane's neighbours spread at least this far (sqrt of the middle eigenvalue): one scan
    # line (collinear points) is no plane
    plane_min_spread: float = 0.03
    huber_delta: float = 0.1  # robust kernel; 0 = off
    two_step: bool = True  # the two restricted steps before the 6-DoF refinement (ablation)
    step_iterations: int = 8  # LM iterations of each restricted step
    max_iterations: int = 20  # LM iterations of the 6-DoF refinement ...
    # ... per this sweep period (s), at most 5x: a slower sensor's step starts farther from
    # its solution (2 Hz keyframes 4-5 m apart need ~40-100); 0 = the cap as it is
    iteration_period: float = 0.1
    # weight of each E_ground residual relative to a point-to-plane one (0 = LeGO-LOAM)
    ground_weight: float = 0.0
    ground_huber: float = 0.1  # the ground residual's robust kernel
    # each residual class (edges, planes, ground) weighs (noise_floor / sigma)^2, sigma =
    # 1.4826 x its median residual (>= noise_floor), at every association; 0 = equal weights
    noise_floor: float = 0.02
    # edge / plane residuals above this many robust sigmas of their class weigh 0 at each
    # association: what moved since the map saw it (LeGO-LOAM removes no moving objects;
    # trucks passing a motorway start pulled it 0.9 m); 0 = Huber alone. Only for sensors
    # of ``outlier_min_beams`` or more: along the 16-beam building's plain corridors the
    # few terms that hold the pose along them were cut (S route 6.0 -> 12.7 m); LeGO's
    # front ends cut on any sensor in the open-road mode, whose scatter points hold the pose
    outlier_sigmas: float = 3.0
    outlier_min_beams: int = 24
    transformation_epsilon: float = 1e-6
    fitness_epsilon: float = 1e-6
    # with the ground as a plane (``ground_normal``) the 6-DoF refinement stops as converged
    # when its pose comes back within this many m (and rad) of one 2-4 iterations before,
    # having gone 2.5x as far in between: freed from the rings, a motorway's length is
    # weakly held and the pairs cycle along it (LeGO-LOAM-LPB: 1 cm for 20 iterations, and
    # the start's unconverged frames were rejected); 0 = off, LeGO-LOAM's (its motorway
    # start did not cycle; on without the plane its nuScenes keyframes went 138 -> 296 cm)
    cycle_tolerance: float = 0.0
    # with the open-road mode's scatter points (nearest-point pairs, which change from one
    # iteration to the next) the refinement's cycle tolerance is at least this (m, rad)
    scatter_cycle_tolerance: float = 0.002
    # LOAM's solution remapping: translation directions with less than this fraction of the
    # best direction's information keep the prediction; 0 = off
    degenerate_ratio: float = 0.0
    threads: int = 2

    def __post_init__(self) -> None:
        if self.k_neighbors < 3:
            raise ConfigError(f"two_step k_neighbors must be >= 3, got {self.k_neighbors}")
        if self.max_neighbor_distance <= 0 or self.edge_ratio < 1:
            raise ConfigError("two_step needs max_neighbor_distance > 0 and edge_ratio >= 1")
        if self.max_iterations < 1 or self.step_iterations < 0:
            raise ConfigError("two_step needs max_iterations >= 1 and step_iterations >= 0")
        if self.iteration_period < 0:
            raise ConfigError(
                f"two_step iteration_period must be >= 0 s, got {self.iteration_period}"
            )
        if self.ground_weight < 0:
            raise ConfigError(f"two_step ground_weight must be >= 0, got {self.ground_weight}")
        if self.scatter_cycle_tolerance < 0:
            raise ConfigError("two_step scatter_cycle_tolerance must be >= 0 (0 = off)")
        if self.outlier_sigmas < 0 or self.outlier_min_beams < 0:
            raise ConfigError("two_step outlier_sigmas and outlier_min_beams must be >= 0")
        if not 0.0 <= self.degenerate_ratio < 1.0:
            raise ConfigError("two_step degenerate_ratio must be in [0, 1)")


@dataclass
class Terms:
    """Linear-algebra form of a set of residuals e = R p + t - c, cost w e^T W e."""

    p: np.ndarray  # (n, 3) source points, sensor frame
    c: np.ndarray  # (n, 3) target points, odometry frame
    W: np.ndarray  # (n, 3, 3) projector (line normal space / plane normal)
    w: np.ndarray  # (n,) weights (robust x class weight)
    sqd: np.ndarray  # (n,) squared point-to-feature distances (m^2)

    @classmethod
    def empty(cls) -> Terms:
        return cls(
            np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0), np.zeros(0)
        )

    @classmethod
    def join(cls, parts: list[Terms]) -> Terms:
        parts = [t for t in parts if len(t.p)]
        if not parts:
            return cls.empty()
        return cls(
            *(np.concatenate([getattr(t, f) for t in parts]) for f in ("p", "c", "W", "w", "sqd"))
        )


def _scaled(t: Terms, floor: float, cut: float = 0.0) -> Terms:
    """Terms with their weights scaled by (floor / sigma)^2 of their robust residual scale
    sigma = 1.4826 x median residual (>= floor); ``cut`` > 0: residuals above cut x sigma
    weigh 0 (points on what moved since the map saw it)."""
    if (floor <= 0 and cut <= 0) or len(t.sqd) == 0:
        return t
    sigma = max(1.4826 * float(np.sqrt(np.median(t.sqd))), floor, 1e-3)
    if floor > 0:
        t.w = t.w * (floor / sigma) ** 2
    if cut > 0:
        t.w = np.where(t.sqd > (cut * sigma) ** 2, 0.0, t.w)
    return t


def _huber(r: np.ndarray, delta: float) -> np.ndarray:
    if delta <= 0:
        return np.ones_like(r)
    return np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-12))


class MapTarget(Protocol):
    """A map the matcher can search besides a FeatureTarget (e.g. an incremental map):
    ``neighbours(queries (n, 3), k, max_distance=inf)`` -> distances (n, k) m ascending and
    the neighbours' coordinates (n, k, 3), neighbours beyond ``max_distance`` (m) may be
    left out (inf); ``len()`` = live points."""

    def __len__(self) -> int: ...

    def neighbours(
        self, queries: np.ndarray, k: int, *, max_distance: float = np.inf
    ) -> tuple[np.ndarray, np.ndarray]: ...


Target = FeatureTarget | MapTarget


class NeighbourCache:
    """Analyses (centroid, eigen-decomposition) of the k-NN map neighbourhoods of one point
    set, kept between the matcher's iterations: a point whose neighbours (coordinates, in
    order) did not change since it was last analysed keeps its analysis instead of a new
    eigh (the same numbers; near the optimum most points keep their neighbours, and the
    dense scans' ~27k surface points are re-associated 10-30 times per frame)."""

    def __init__(self) -> None:
        self._sets: dict[int, tuple[np.ndarray, tuple[np.ndarray, ...]]] = {}

    def analyse(self, pts: np.ndarray, ok: np.ndarray, nb: np.ndarray):
        """(c, w, V, centred) of the neighbourhoods ``nb`` (n_ok, k, 3) of the rows ``ok``
        (N,) bool of the point set ``pts`` (N, 3)."""
        key = id(pts)
        held = self._sets.get(key)
        if held is None or held[0] is not pts:
            n, k = len(pts), nb.shape[1]
            held = (
                pts,
                (
                    np.full((n, k, 3), np.nan),
                    np.zeros((n, 3)),
                    np.zeros((n, 3)),
                    np.zeros((n, 3, 3)),
                    np.zeros((n, k, 3)),
                ),
            )
            self._sets[key] = held
        last, c_all, w_all, V_all, cen_all = held[1]
        rows = np.flatnonzero(ok)
        new = np.any(nb != last[rows], axis=(1, 2))
        if new.any():
            r, nbn = rows[new], nb[new]
            c, centred, w, V = _analysis(nbn)
            last[r], c_all[r], cen_all[r], w_all[r], V_all[r] = nbn, c, centred, w, V
        return c_all[rows], w_all[rows], V_all[rows], cen_all[rows]


def _analysis(nb: np.ndarray):
    """Centroids, centred points and eigen-decomposition (ascending) of neighbourhoods
    nb (n, k, 3)."""
    k = nb.shape[1]
    c = nb.mean(axis=1)
    centred = nb - c[:, None, :]
    w, V = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred) / k)
    return c, centred, w, V


def _knn(
    moved: np.ndarray,
    target: Target | None,
    cfg: TwoStepConfig,
    cache: NeighbourCache | None = None,
    pts: np.ndarray | None = None,
):
    k = cfg.k_neighbors
    if target is None or len(target) < k or len(moved) == 0:
        return None
    # neighbourhoods whose k-th point is beyond max_neighbor_distance are dropped, so the
    # search stops there (same answers for the rows kept; the voxel-hash map then needs no
    # KD-tree fallback); worker threads only for large batches (their start-up costs more)
    bound = cfg.max_neighbor_distance
    if isinstance(target, FeatureTarget):
        workers = _workers(len(moved), cfg.threads)
        d, j = target.tree.query(moved, k=k, distance_upper_bound=bound, workers=workers)
        ok = d[:, -1] < bound
        nb = target.points[j[ok]]
    else:
        d, nb = target.neighbours(moved, k, max_distance=bound)
        ok = d[:, -1] < bound
        nb = nb[ok]
    if cache is not None and pts is not None:
        c, w, V, centred = cache.analyse(pts, ok, nb)
    else:
        c, centred, w, V = _analysis(nb)
    return ok, c, w, V, centred


def edge_terms(
    T: np.ndarray,
    pts: np.ndarray,
    target: FeatureTarget | None,
    cfg: TwoStepConfig,
    cache: NeighbourCache | None = None,
) -> Terms:
    """Point-to-line residuals of edge points ``pts`` (sensor frame) at pose T; ``cache``
    keeps the neighbourhood analyses of ``pts`` between calls."""
    moved = transform(T, pts)
    nh = _knn(moved, target, cfg, cache, pts)
    if nh is None:
        return Terms.empty()
    ok, c, w, V, _ = nh
    line = w[:, 2] > cfg.edge_ratio * w[:, 1]
    v = V[line, :, 2]
    P = np.eye(3) - v[:, :, None] * v[:, None, :]
    e = np.einsum("nij,nj->ni", P, moved[ok][line] - c[line])
    r = np.linalg.norm(e, axis=1)
    return _scaled(
        Terms(pts[ok][line], c[line], P, _huber(r, cfg.huber_delta), r**2),
        cfg.noise_floor,
        cfg.outlier_sigmas,
    )


def plane_terms(
    T: np.ndarray,
    pts: np.ndarray,
    target: FeatureTarget | None,
    cfg: TwoStepConfig,
    cache: NeighbourCache | None = None,
    fixed: FixedNormals | None = None,
) -> Terms:
    """Point-to-plane residuals of plane points ``pts`` (sensor frame) at pose T; ``cache``
    keeps the neighbourhood analyses of ``pts`` between calls. ``fixed``: the rows whose
    plane normal is known (the scan's ground): which neighbourhoods are planes is LOAM's
    test as for any row (testing them against the known normal instead let terms flip in
    and out at the 5 cm threshold and the solver cycle), their residual is along it."""
    moved = transform(T, pts)
    nh = _knn(moved, target, cfg, cache, pts)
    if nh is None:
        return Terms.empty()
    ok, c, w, V, centred = nh
    n = V[:, :, 0]
    flat = np.max(np.abs(np.einsum("nki,ni->nk", centred, n)), axis=1) < cfg.plane_threshold
    flat &= w[:, 1] > cfg.plane_min_spread**2
    if fixed is not None:
        n = fixed.applied(n, ok, T[:3, :3])
    n = n[flat]
    r = np.abs(np.einsum("ni,ni->n", moved[ok][flat] - c[flat], n))
    t = Terms(
        pts[ok][flat], c[flat], n[:, :, None] * n[:, None, :], _huber(r, cfg.huber_delta), r**2
    )
    return _scaled(t, cfg.noise_floor, cfg.outlier_sigmas)


def scatter_terms(
    T: np.ndarray, pts: np.ndarray, target: FeatureTarget | None, cfg: TwoStepConfig
) -> Terms:
    """Point-to-point residuals of the open-road mode's scatter points ``pts`` (sensor
    frame; ``slam.odometry.open_road``) to their nearest map point within
    ``max_neighbor_distance`` at pose T, horizontal only (``feature_icp``'s scatter terms):
    W = diag(1, 1, 0) in the odometry frame, residual the horizontal distance. Their heights
    are the rings' (a beam meets a trunk at another height from every pose), not the pose's."""
    if target is None or not len(pts):
        return Terms.empty()
    ok, q, d = horizontal_pairs(transform(T, pts), target, cfg.max_neighbor_distance, cfg.threads)
    t = Terms(
        pts[ok], q, np.broadcast_to(HORIZONTAL, (len(q), 3, 3)), _huber(d, cfg.huber_delta), d**2
    )
    return _scaled(t, cfg.noise_floor, cfg.outlier_sigmas)


def ground_terms(
    T: np.ndarray, pts: np.ndarray, plane_odom: tuple[np.ndarray, float], cfg: TwoStepConfig
) -> Terms:
    """E_ground (3.3): distances n . (R p + t) + d of ground points ``pts`` to the plane
    (n, d) of the previous frame expressed in the odometry frame."""
    if cfg.ground_weight <= 0 or len(pts) == 0:
        return Terms.empty()
    n, d = np.asarray(plane_odom[0], dtype=np.float64), float(plane_odom[1])
    r = np.abs(transform(T, pts) @ n + d)
    m = len(pts)
    t = Terms(
        pts,
        np.broadcast_to(-d * n, (m, 3)).copy(),
        np.broadcast_to(np.outer(n, n), (m, 3, 3)).copy(),
        cfg.ground_weight * _huber(r, cfg.ground_huber),
        r**2,
    )
    return _scaled(t, cfg.noise_floor)


def plane_to_odom(
    normal: np.ndarray, d: float, T_odom_sensor: np.ndarray
) -> tuple[np.ndarray, float]:
    """A sensor-frame plane n.x + d = 0 expressed in the odometry frame."""
    n_w = T_odom_sensor[:3, :3] @ np.asarray(normal, dtype=np.float64)
    return n_w, float(d - n_w @ T_odom_sensor[:3, 3])


def weak_translation(H: np.ndarray, ratio: float) -> np.ndarray:
    """Unit translation directions (k, 3) whose information, rotation marginalised out of
    the 6x6 Hessian ``H`` (rotation first: S = H_tt - H_tr H_rr^-1 H_rt), is below ``ratio``
    times the best direction's; (0, 3) when none is."""
    H = 0.5 * (np.asarray(H, dtype=np.float64) + np.asarray(H, dtype=np.float64).T)
    try:
        S = H[3:, 3:] - H[3:, :3] @ np.linalg.solve(H[:3, :3], H[:3, 3:])
    except np.linalg.LinAlgError:
        S = H[3:, 3:]
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    if not np.all(np.isfinite(w)) or w[-1] <= 0:
        return np.zeros((0, 3))
    return V[:, w < ratio * w[-1]].T


def remapped(
    res: RegistrationResult, T_start: np.ndarray, ratio: float
) -> tuple[RegistrationResult, int]:
    """Zhang et al. 2016's solution remapping applied to the converged 6-DoF result: its
    motion from ``T_start`` along the weak translation directions of its Hessian
    (``weak_translation``) is undone (on a flat direction the cost does not change, so
    projecting the total step equals projecting each one). Returns the result and the
    number of directions left at the start."""
    U = weak_translation(res.H, ratio)
    if len(U) == 0:
        return res, 0
    rho, phi = se3_log(np.linalg.inv(T_start) @ res.T_target_source)
    rho = rho - U.T @ (U @ rho)  # right perturbation: the Hessian's own (body) frame
    return replace(res, T_target_source=T_start @ se3_exp(np.concatenate([phi, rho]))), len(U)


def solve_restricted(
    T0: np.ndarray,
    terms_at: Callable[[np.ndarray], Terms],
    dof: tuple[int, ...],
    iterations: int,
    epsilon: float = 1e-6,
) -> tuple[np.ndarray, int]:
    """Levenberg-Marquardt over the ``dof`` (tangent indices, rotation first) of a
    perturbation at the sensor position with odometry-frame axes; the other coordinates stay
    fixed. Re-associates every iteration. Returns (pose, correspondences of the last
    iteration). Fewer than 3 correspondences: the pose is returned unchanged."""
    T = np.asarray(T0, dtype=np.float64).copy()
    sel = np.asarray(dof)
    mu = 1e-4
    n_used = 0
    for _ in range(iterations):
        tm = terms_at(T)
        n_used = len(tm.p)
        if n_used < 3:
            break
        q = transform(T, tm.p)
        e = q - tm.c
        J = np.concatenate(
            [-skew(q - T[:3, 3]), np.broadcast_to(np.eye(3), (n_used, 3, 3))], axis=2
        )
        J = J[:, :, sel]
        WJ = np.einsum("nij,njk->nik", tm.W, J) * tm.w[:, None, None]
        H = np.einsum("nij,nik->jk", J, WJ)
        b = np.einsum("nij,ni->j", WJ, e)
        cost = float(np.einsum("ni,nij,nj,n->", e, tm.W, e, tm.w))
        step = None
        for _ in range(6):
            A = H + mu * np.diag(np.maximum(np.diag(H), 1e-9))
            try:
                dx = -np.linalg.solve(A, b)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            xi = np.zeros(6)
            xi[sel] = dx
            T_new = np.eye(4)
            T_new[:3, :3] = se3_exp(np.r_[xi[:3], 0.0, 0.0, 0.0])[:3, :3] @ T[:3, :3]
            T_new[:3, 3] = T[:3, 3] + xi[3:]
            e_new = transform(T_new, tm.p) - tm.c
            if float(np.einsum("ni,nij,nj,n->", e_new, tm.W, e_new, tm.w)) <= cost:
                T, step = T_new, dx
                mu = max(mu * 0.1, 1e-9)
                break
            mu *= 10.0
        if step is None or float(step @ step) < epsilon:
            break
    return T, n_used


def _two_steps(
    T: np.ndarray,
    ground: np.ndarray,
    g_res: np.ndarray,
    edges: np.ndarray,
    edge_map: Target | None,
    plane_map: Target | None,
    ground_plane: tuple[np.ndarray, float] | None,
    cfg: TwoStepConfig,
    cache: NeighbourCache | None = None,
    fixed: FixedNormals | None = None,
    scatter: tuple[np.ndarray, FeatureTarget | None] | None = None,
) -> np.ndarray:
    """T after LeGO-LOAM's two restricted steps: [roll, pitch, z] from the ground points on
    the plane map (+ E_ground when ``ground_plane`` is given), then [yaw, x, y] from the
    edges on the edge map (section III-D) and the ``scatter`` points on their map."""

    def step1(T_: np.ndarray) -> Terms:
        parts = [plane_terms(T_, ground, plane_map, cfg, cache, fixed)]
        if ground_plane is not None:
            parts.append(ground_terms(T_, g_res, ground_plane, cfg))
        return Terms.join(parts)

    T, _ = solve_restricted(T, step1, GROUND_DOF, cfg.step_iterations)

    def step2(T_: np.ndarray) -> Terms:
        parts = [edge_terms(T_, edges, edge_map, cfg, cache)]
        if scatter is not None:
            parts.append(scatter_terms(T_, *scatter, cfg))
        return Terms.join(parts)

    T, _ = solve_restricted(T, step2, EDGE_DOF, cfg.step_iterations)
    return T


def _refine(
    T: np.ndarray,
    edges: np.ndarray,
    surf: np.ndarray,
    g_res: np.ndarray,
    edge_map: Target | None,
    plane_map: Target | None,
    ground_plane: tuple[np.ndarray, float] | None,
    n_src: int,
    cfg: TwoStepConfig,
    cache: NeighbourCache | None = None,
    fixed: FixedNormals | None = None,
    cycle_tolerance: float = 0.0,
    scatter: tuple[np.ndarray, FeatureTarget | None] | None = None,
) -> RegistrationResult:
    """The 6-DoF refinement from T: E = E_edge + E_plane (+ E_ground when ``ground_plane`` is
    given), the energy of 3.3, by ``solve_weighted``; + the ``scatter`` points' terms."""

    def associate(T_: np.ndarray):
        parts = [
            edge_terms(T_, edges, edge_map, cfg, cache),
            plane_terms(T_, surf, plane_map, cfg, cache, fixed),
        ]
        if ground_plane is not None:
            parts.append(ground_terms(T_, g_res, ground_plane, cfg))
        # the fitness is the features' (``feature_icp``: a scatter point's distance to the
        # nearest map point is the map's spacing, not how well the scan fits)
        sqd = np.concatenate([t.sqd for t in parts])
        if scatter is not None:
            parts.append(scatter_terms(T_, *scatter, cfg))
        tm = Terms.join(parts)
        return tm.p, tm.c, tm.W, tm.w, sqd

    return solve_weighted(
        T,
        associate,
        n_src,
        max_iterations=cfg.max_iterations,
        transformation_epsilon=cfg.transformation_epsilon,
        fitness_epsilon=cfg.fitness_epsilon,
        residual_dims=1,
        cycle_tolerance=cycle_tolerance,
    )


def two_step_align(
    ground_xyz: np.ndarray,
    edge_xyz: np.ndarray,
    plane_xyz: np.ndarray,
    edge_map: Target | None,
    plane_map: Target | None,
    init_T: np.ndarray | None = None,
    cfg: TwoStepConfig | None = None,
    ground_plane: tuple[np.ndarray, float] | None = None,
    *,
    ground_residual_xyz: np.ndarray | None = None,
    ground_normal: FixedNormals | None = None,
    settle: bool = False,
    scatter_xyz: np.ndarray | None = None,
    scatter_map: FeatureTarget | None = None,
) -> RegistrationResult:
    """Align a scan's features to the edge/plane maps: [roll, pitch, z] from the ground
    points, [yaw, x, y] from the edges, then a 6-DoF refinement on edges + planes (+ ground
    points, which are plane features too) + E_ground when ``ground_plane`` (n, d in the
    odometry frame, the previous frame's fitted plane) is given and ground_weight > 0;
    ``ground_residual_xyz``: the points of E_ground (default: ``ground_xyz``), e.g. the
    inliers of this scan's own plane fit, whose mean distance to their plane is zero, so
    that the chained frame-to-frame constraint has no bias from kerbs or wall feet.
    ``ground_normal``: the ground points (rows of ``ground_xyz``) on the scan's fitted
    ground plane and its normal, which their point-to-plane terms use.
    ``settle``: with ``cfg.outlier_sigmas`` > 0, solve with Huber alone first and cut from
    the pose it settles on (a start that is not a tracked prediction: from far off, the
    terms that would pull the pose there are what the cut removes).
    ``scatter_xyz`` / ``scatter_map``: the open-road mode's scatter points and their map
    (``slam.odometry.open_road``), point-to-point terms in the second step and the refinement.
    Returns T_map_scan with the Hessian of the final step (``solve_weighted``); with
    ``cfg.degenerate_ratio`` > 0 its weak translation directions keep ``init_T``
    (``remapped``)."""
    cfg = cfg or TwoStepConfig()
    ground = _check_points(ground_xyz, "ground points")
    edges = _check_points(edge_xyz, "edge points")
    planes = _check_points(plane_xyz, "plane points")
    scatter = None
    if scatter_xyz is not None and len(scatter_xyz) and scatter_map is not None:
        scatter = (_check_points(scatter_xyz, "scatter points"), scatter_map)
    n_src = len(ground) + len(edges) + len(planes)
    if n_src < 6:
        raise RegistrationError(f"two-step matching needs at least 6 feature points, got {n_src}")
    T = np.eye(4) if init_T is None else np.asarray(init_T, dtype=np.float64).copy()
    gp = ground_plane if cfg.ground_weight > 0 else None
    g_res = (
        ground
        if ground_residual_xyz is None
        else _check_points(ground_residual_xyz, "E_ground points")
    )
    T_start = T.copy()
    cache = NeighbourCache()
    fixed = surf_fixed = None
    if ground_normal is not None:
        if len(ground_normal.rows) != len(ground):
            raise ValueError(
                f"ground_normal has {len(ground_normal.rows)} rows for {len(ground)} points"
            )
        fixed = ground_normal
        rows = np.concatenate([fixed.rows, np.zeros(len(planes), dtype=bool)])
        surf_fixed = FixedNormals(rows, fixed.normal)
    cut = cfg.outlier_sigmas
    if settle:
        cfg = replace(cfg, outlier_sigmas=0.0)
    if cfg.two_step and cfg.step_iterations > 0:
        T = _two_steps(T, ground, g_res, edges, edge_map, plane_map, gp, cfg, cache, fixed, scatter)
    surf = np.concatenate([ground, planes])
    cycle = cfg.cycle_tolerance if ground_normal is not None else 0.0
    if scatter is not None:
        cycle = max(cycle, cfg.scatter_cycle_tolerance)
    n_src += 0 if scatter is None else len(scatter[0])
    res = _refine(
        T, edges, surf, g_res, edge_map, plane_map, gp, n_src, cfg, cache, surf_fixed, cycle,
        scatter,
    )  # fmt: skip
    if settle and cut > 0:
        res = _refine(
            res.T_target_source, edges, surf, g_res, edge_map, plane_map, gp, n_src,
            replace(cfg, outlier_sigmas=cut), cache, surf_fixed, cycle, scatter,
        )  # fmt: skip
    if cfg.degenerate_ratio > 0:
        res, _ = remapped(res, T_start, cfg.degenerate_ratio)
    return res
