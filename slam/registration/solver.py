"""The weighted Gauss-Newton / Levenberg-Marquardt solver over SE(3) that GICP (eq. (4) of
paper 000) and the point-to-edge / point-to-plane matcher of ``feature_icp`` share, each with
its own association and weights. Tangent: rotation first, perturbation on the right
(``T <- T exp(xi)``), so Hessians live in the source (sensor) frame."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from slam.registration import kernels
from slam.registration.pose_prior import PosePrior
from slam.registration.result import CONVERGED_REASONS, RegistrationError, RegistrationResult
from slam.registration.se3 import se3_exp, skew

# associate(T) -> (p source points (N, 3), q target points (N, 3), W (N, 3, 3) information in
# the target frame, robust weights (N,) or None, squared Euclidean distances (N,)), optionally
# followed by (H, b, cost) at T when the association computed them already (fused kernel)
Associate = Callable[[np.ndarray], tuple]
Linearise = Callable[..., tuple]  # (T, p, q, W, w) -> (H 6x6, b 6, cost)
CostOf = Callable[..., float]  # (T, p, q, W, w) -> cost


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


def _small(xi: np.ndarray, epsilon: float) -> bool:
    """Both the rotation and the translation part of the step below ``epsilon`` squared."""
    return float(xi[:3] @ xi[:3]) < epsilon and float(xi[3:] @ xi[3:]) < epsilon


def _tail_small(xi: np.ndarray, prev: np.ndarray | None, epsilon: float) -> bool:
    """The steps still to come, the geometric tail |xi| r / (1 - r) of the last two steps'
    contraction r < 1/2, below ``epsilon`` squared in rotation and in translation."""
    if prev is None:
        return False
    for part in (slice(0, 3), slice(3, 6)):
        now, before = float(np.linalg.norm(xi[part])), float(np.linalg.norm(prev[part]))
        if now == 0.0:
            continue
        r = now / before if before > 0 else 1.0
        if r >= 0.5 or (now * r / (1.0 - r)) ** 2 >= epsilon:
            return False
    return True


def _apart(A: np.ndarray, B: np.ndarray) -> float:
    """The larger of the translation (m) and rotation (rad) between two poses."""
    D = np.linalg.inv(A) @ B
    angle = np.arccos(np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
    return max(float(np.linalg.norm(D[:3, 3])), float(angle))


def _cycles(T: np.ndarray, visited: list[np.ndarray], tolerance: float) -> bool:
    """Whether T came back within ``tolerance`` of a pose 2-4 iterations before after the
    poses in between went more than 2.5 ``tolerance`` away from it (slow steady progress
    is no cycle)."""
    for m in (2, 3, 4):
        if len(visited) < m:
            break
        E = visited[-m]
        away = max(_apart(E, V) for V in visited[-m + 1 :])
        if _apart(E, T) < tolerance and away > 2.5 * tolerance:
            return True
    return False


def _associate_and_linearise(
    associate: Associate, T: np.ndarray, lin: Linearise, reference: bool, min_inliers: int
) -> tuple:
    """(p, q, W, w, squared distances, H, b, cost) at T; RegistrationError when fewer than
    ``min_inliers`` pairs were found."""
    terms = associate(T)
    p, q, W, w, sqd = terms[:5]
    if len(p) < min_inliers:
        raise RegistrationError(
            f"only {len(p)} correspondences within the distance limit (need {min_inliers});"
            " the initial guess is too far off or the clouds do not overlap"
        )
    H, b, cost = terms[5] if len(terms) > 5 and not reference else lin(T, p, q, W, w)
    return p, q, W, w, sqd, H, b, cost


def _damped_step(
    T: np.ndarray,
    H: np.ndarray,
    b: np.ndarray,
    cost: float,
    mu: float,
    cost_of: CostOf,
    pairs: tuple,
) -> tuple[np.ndarray, float, np.ndarray | None, np.ndarray | None]:
    """Solve (H + mu diag H) xi = -b and accept the step when the cost with these ``pairs``
    (p, q, W, w) drops, else raise mu and retry (8 tries). Returns (T, mu, the accepted step
    or None, the first step tried or None)."""
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
        if cost_of(T_new, *pairs) <= cost:
            return T_new, max(mu * 0.1, 1e-9), xi, first_step
        mu *= 10.0
    return T, mu, None, first_step


def _result(
    T: np.ndarray,
    H: np.ndarray,
    b: np.ndarray,
    cost: float,
    sqd: np.ndarray,
    n_in: int,
    num_source: int,
    iterations: int,
    reason: str,
    residual_dims: int,
) -> RegistrationResult:
    """The result of the last association: ``sqd`` the squared distances of its pairs within
    the distance limit, ``n_in`` the pairs the step used."""
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


def _with_prior(cost_of: CostOf, prior: PosePrior) -> CostOf:
    """The cost of a pose with these pairs plus the prior's."""

    def cost(T, *pairs) -> float:
        return cost_of(T, *pairs) + prior.cost(T)

    return cost


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
    prior: PosePrior | None = None,
    cycle_tolerance: float = 0.0,
    least_cost: bool = False,
) -> RegistrationResult:
    """Gauss-Newton / Levenberg-Marquardt on SE(3) with re-association every iteration.

    Each iteration: associate at T, build H = sum J^T W J and b = sum J^T W e, take the damped
    step (``_damped_step``). Stops when the step is below ``transformation_epsilon`` (squared
    metres and squared radians) or the cost changes by less than ``fitness_epsilon``
    relative. ``residual_dims`` counts scalar residuals per correspondence (for dof).
    reference: H, b and the cost by the numpy reference (``_linearise`` / ``_cost``) instead
    of the compiled kernels (``slam.registration.kernels``, same numbers).
    predict_convergence: stop ("step") as well when the steps still to come are below the
    epsilon (``_tail_small``): the association that would only measure the next, smaller
    step is saved (docs/paper000.md). The Hessian returned is the last association's.
    prior: a Gaussian prior on the pose (``PosePrior``) added to every step and its cost;
    the Hessian and cost returned are the scan's alone (its own information).
    cycle_tolerance (m, 0 = off): stop ("cycle", converged) when the pose comes back within
    this distance and cycle_tolerance rad of the pose 2-4 iterations before, having gone
    more than 2.5x as far in between (``_cycles``): the
    re-association cycles through a few sets of pairs around the minimum (a weakly
    constrained direction: a motorway's length) and no further step settles it.
    least_cost: at max_iterations, when the re-associated cost is above the least it had,
    end at that pose ("least_cost", converged): each step lowered the cost of its own pairs
    but the next association rose it, so the steps chased the pairing (a sparse map behind
    a scan at speed), not the fit. A run that converges is unchanged.
    """
    lin, cost_of = (_linearise, _cost) if reference else (kernels.linearise, kernels.cost)
    step_cost = cost_of if prior is None else _with_prior(cost_of, prior)
    T = np.asarray(init_T, dtype=np.float64).copy()
    mu = 1e-6
    prev_cost, prev_xi = None, None
    reason = "max_iterations"
    H, b = np.zeros((6, 6)), np.zeros(6)
    cost, n_in, sqd, iterations = 0.0, 0, np.zeros(0), 0
    visited: list[np.ndarray] = []
    best = None  # (cost, T, H, b, sqd, n_in) of the least re-associated cost
    for it in range(1, max_iterations + 1):
        iterations = it
        p, q, W, w, sqd, H, b, cost = _associate_and_linearise(
            associate, T, lin, reference, min_inliers
        )
        n_in = len(p)
        if least_cost and (best is None or cost < best[0]):
            best = (cost, T.copy(), H, b, sqd, n_in)
        H_step, b_step, total = H, b, cost
        if prior is not None:
            H_p, b_p, c_p = prior.linearised(T)
            H_step, b_step, total = H + H_p, b + b_p, cost + c_p
        if prev_cost is not None and abs(prev_cost - total) <= fitness_epsilon * max(total, 1e-12):
            reason = "fitness"
            break
        prev_cost = total
        T, mu, xi, first_step = _damped_step(T, H_step, b_step, total, mu, step_cost, (p, q, W, w))
        if xi is None:
            # no damped step lowers the cost: at the minimum when even the least damped step
            # was already below the epsilon (rounding), else stuck short of it
            small = first_step is not None and _small(first_step, transformation_epsilon)
            reason = "step" if small else "stalled"
            break
        if _small(xi, transformation_epsilon) or (
            predict_convergence and _tail_small(xi, prev_xi, transformation_epsilon)
        ):
            reason = "step"
            break
        prev_xi = xi
        if cycle_tolerance > 0:
            if _cycles(T, visited, cycle_tolerance):
                reason = "cycle"
                break
            visited.append(T.copy())
    if reason == "max_iterations" and best is not None and best[0] < cost:
        cost, T, H, b, sqd, n_in = best
        reason = "least_cost"
    return _result(T, H, b, cost, sqd, n_in, num_source, iterations, reason, residual_dims)
