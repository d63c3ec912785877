"""The improved PLICP of paper 003 (DPCR-SLAM, section 3.2): point-to-line ICP in 2D in
which every target point is matched to the orthogonal projection of itself on the LINE
FEATURE of its nearest reference point (not on the local line through its two nearest
reference points), so that the error directions follow the walls.

Steps (3.2.1): (3) for each target point p_i the nearest reference point q_j; the match is
the foot of the perpendicular from p_i on the line feature through q_j; (5) the rigid
transform (theta, t) minimising the sum of squared point-to-line distances (Gauss-Newton
on the three parameters, exact rotation); (6) P_{k+1} = R(theta_k) P_k + t_k, eq. (1);
(7) J = sum ||p_i^{k+1} - q_ji||^2, eq. (2), here Huber-weighted so that points on walls
the reference has not seen yet do not bias the pose; (8) repeat until the update is below
the threshold or the iteration cap. Reference points on no line are matched
point-to-point.

With a ``prior`` (the wheel-odometry prediction and its information) the solve minimises
J / sigma_p^2 + e^T Lambda e, e = prior^-1 o pose (the odometry residual of the increment):
directions the matches leave weak or unconstrained (a corridor without visible ends)
follow the odometry as much as its noise model says, instead of whatever the residual
noise of a nearly flat cost gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError
from slam.mapping.grid2d import compose2d, transform2d, wrap


@dataclass
class PlicpConfig:
    """max_iterations; tolerance: stop when the update is below it (m and rad);
    max_distance (m): matches farther than this (after the prediction) are ignored;
    min_matches: fewest matches for a usable result; robust_floor (m): smallest Huber
    threshold (the threshold is 3 robust sigmas of the residuals); degeneracy_ratio:
    directions constrained less than this share of the strongest keep the prediction;
    point_matches: reference points on no line are matched point-to-point (False: only
    line features count, as in the paper; isolated or sparse cells then pull nothing);
    point_sigma (m): noise of one point-to-line residual, which weighs the matches
    against an odometry prior (only used with one)."""

    max_iterations: int = 30
    point_sigma: float = 0.03
    tolerance: float = 1e-5
    max_distance: float = 0.5
    min_matches: int = 20
    robust_floor: float = 0.03
    degeneracy_ratio: float = 0.02
    point_matches: bool = True

    def __post_init__(self) -> None:
        if self.max_iterations < 1 or not self.max_distance > 0:
            raise ConfigError("plicp: max_iterations >= 1 and max_distance > 0 required")


@dataclass
class PlicpResult:
    """pose (x, y, theta) mapping target points into the reference frame; rmse (m) of the
    final matches; matches: their count; iterations; converged; info: 3x3 information
    (x, y, theta) = J^T J / sigma^2 of the final residuals; degenerate: directions left at
    the prediction (0 = fully constrained)."""

    pose: np.ndarray
    rmse: float
    matches: int
    iterations: int
    converged: bool
    info: np.ndarray
    degenerate: int = 0


@dataclass
class LineReference:
    """A reference cloud, the line feature of each point - its direction (NaN: on no line)
    and a point of the line (the fitted line, not the cell centre) - and its KD-tree,
    built once and reused over iterations and scans."""

    points: np.ndarray
    directions: np.ndarray
    anchors: np.ndarray
    tree: cKDTree

    @classmethod
    def build(
        cls,
        points: np.ndarray,
        directions: np.ndarray | None = None,
        anchors: np.ndarray | None = None,
    ) -> LineReference:
        """``directions`` (M, 2) unit or NaN; ``anchors`` (M, 2) a point on each point's
        line (default: the point itself)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if directions is None:
            directions = np.full_like(points, np.nan)
        anchors = points if anchors is None else np.asarray(anchors, dtype=np.float64)
        return cls(points, np.asarray(directions, dtype=np.float64), anchors, cKDTree(points))

    @classmethod
    def from_lines(cls, lines) -> LineReference:
        """The reference of a :class:`slam.features.lines2d.LineSet`: every obstacle point
        with the direction and centre of its line."""
        anchors = lines.points.copy()
        on = lines.label >= 0
        anchors[on] = lines.centre[lines.label[on]]
        return cls.build(lines.points, lines.point_directions(), anchors)

    def __len__(self) -> int:
        return len(self.points)


def _residuals(
    moved: np.ndarray, ref: LineReference, max_distance: float, point_matches: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Matches of ``moved`` target points: (point index, normal rows (K, 2), residuals (K,))
    stacked so that a line match gives one row (its normal) and a point match two."""
    dist, j = ref.tree.query(moved, k=1, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    i = np.flatnonzero(ok)
    j = j[ok]
    d = ref.directions[j]
    on_line = np.isfinite(d[:, 0])
    normals = np.column_stack([-d[on_line, 1], d[on_line, 0]])
    rows_i = [i[on_line]]
    rows_n = [normals]
    rows_q = [ref.anchors[j[on_line]]]
    pts = i[~on_line] if point_matches else i[:0]
    if len(pts):  # point-to-point: both axes
        q = ref.points[j[~on_line]]
        for axis in (np.array([1.0, 0.0]), np.array([0.0, 1.0])):
            rows_i.append(pts)
            rows_n.append(np.broadcast_to(axis, (len(pts), 2)))
            rows_q.append(q)
    idx = np.concatenate(rows_i)
    n = np.concatenate(rows_n)
    q = np.concatenate(rows_q)
    r = np.einsum("ij,ij->i", moved[idx] - q, n)
    return idx, n, r, ok


def inlier_share(
    target: np.ndarray, ref: LineReference, pose: np.ndarray, inlier_m: float = 0.05
) -> float:
    """Share of ``target`` points (N, 2) that lie, moved by ``pose``, within ``inlier_m``
    of the reference: of the line feature of their nearest reference point, or of that
    point when it is on no line. How well a registration fits, comparable between two
    candidate poses of the same scan on the same reference."""
    if not len(target) or not len(ref):
        return 0.0
    moved = transform2d(pose, np.asarray(target, dtype=np.float64))
    dist, j = ref.tree.query(moved, k=1, distance_upper_bound=4 * inlier_m)
    ok = np.isfinite(dist)
    d = ref.directions[j[ok]]
    off = moved[ok] - ref.anchors[j[ok]]
    line = np.abs(off[:, 0] * -d[:, 1] + off[:, 1] * d[:, 0])
    r = np.where(np.isfinite(d[:, 0]), line, dist[ok])
    return float(np.sum(r < inlier_m) / len(target))


def _centroid_step(pose: np.ndarray, delta: np.ndarray, c: np.ndarray) -> np.ndarray:
    """pose (x, y, theta) after the step delta (dx, dy, dtheta; m, rad) that rotates the
    moved points about their centroid c (m) and shifts them: eq. (1), P' = R P + t."""
    ct, st = np.cos(delta[2]), np.sin(delta[2])
    shift = c + delta[:2] - np.array([ct * c[0] - st * c[1], st * c[0] + ct * c[1]])
    return compose2d(np.array([shift[0], shift[1], delta[2]]), pose)


def _gauss_newton(
    target: np.ndarray,
    ref: LineReference,
    pose: np.ndarray,
    cfg: PlicpConfig,
    prior: np.ndarray | None,
    prior_info: np.ndarray | None,
) -> tuple[np.ndarray, int, bool, int]:
    """(pose, iterations, converged, degenerate): steps (3)-(8) of 3.2.1, the Huber-weighted
    eq. (2) minimised until the step is below cfg.tolerance or max_iterations, or until
    fewer than min_matches reference points are matched."""
    converged, it, degenerate = False, 0, 0
    while it < cfg.max_iterations:
        it += 1
        moved = transform2d(pose, target)
        idx, n, r, _ = _residuals(moved, ref, cfg.max_distance, cfg.point_matches)
        if len(np.unique(idx)) < cfg.min_matches:
            break
        # perturbation of the moved points about their centroid c (well conditioned far
        # from the origin): m' = R(d_theta) (m - c) + c + d_t
        c = moved[idx].mean(axis=0)
        J = _jacobian(n, moved[idx] - c)
        w = _huber_weights(r, cfg.robust_floor)
        delta, weak = _constrained_step(
            J,
            w,
            r,
            moved[idx] - c,
            cfg.degeneracy_ratio,
            None if prior is None else _prior_terms(pose, c, prior, prior_info, cfg.point_sigma),
        )
        degenerate = max(degenerate, weak)
        pose = _centroid_step(pose, delta, c)
        if np.all(np.abs(delta) < cfg.tolerance):
            converged = True
            break
    return pose, it, converged, degenerate


def _final_result(
    target: np.ndarray,
    ref: LineReference,
    pose: np.ndarray,
    it: int,
    converged: bool,
    degenerate: int,
    cfg: PlicpConfig,
) -> PlicpResult:
    """The result at the solved pose: Huber-weighted RMSE (m) of the matches and their
    information (1/m^2, 1/rad^2) in the pose's tangent, sigma = max(rmse, 1 cm)."""
    moved = transform2d(pose, target)
    idx, n, r, _ = _residuals(moved, ref, cfg.max_distance, cfg.point_matches)
    if len(idx) == 0:
        return PlicpResult(pose, np.inf, 0, it, False, np.zeros((3, 3)), degenerate)
    matches = len(np.unique(idx))
    if matches == 0:
        return PlicpResult(pose, np.inf, 0, it, False, np.zeros((3, 3)))
    w = _huber_weights(r, cfg.robust_floor)
    rmse = float(np.sqrt(np.sum(w * r**2) / np.sum(w)))
    sigma2 = max(rmse, 0.01) ** 2
    J = _jacobian(n, moved[idx])  # about the world origin, then into the pose's tangent
    info = _world_to_body_info((J * w[:, None]).T @ J / sigma2, pose)
    pose[2] = float(wrap(pose[2]))
    ok = converged and matches >= cfg.min_matches
    return PlicpResult(pose, rmse, matches, it, ok, info, degenerate)


def plicp(
    target: np.ndarray,
    ref: LineReference,
    initial: np.ndarray | None = None,
    cfg: PlicpConfig | None = None,
    prior: np.ndarray | None = None,
    prior_info: np.ndarray | None = None,
) -> PlicpResult:
    """Register ``target`` points (N, 2, own frame) to ``ref``; ``initial`` (x, y, theta)
    the prediction. ``prior`` (x, y, theta) with ``prior_info`` (3x3 information of
    (x, y, theta) in the prior's own frame, 1/m^2 and 1/rad^2): a weighted residual
    prior^-1 o pose added to the solve (default start: the prior). Returns the pose
    mapping target points into the reference frame; ``info`` is the matches' alone."""
    cfg = cfg or PlicpConfig()
    target = np.asarray(target, dtype=np.float64).reshape(-1, 2)
    if initial is None and prior is not None:
        initial = prior
    pose = np.zeros(3) if initial is None else np.asarray(initial, dtype=np.float64).copy()
    if prior is not None:
        prior = np.asarray(prior, dtype=np.float64)
        if prior_info is None or np.shape(prior_info) != (3, 3):
            raise ConfigError("plicp: a prior needs its 3x3 information prior_info")
        prior_info = np.asarray(prior_info, dtype=np.float64)
    if len(ref) == 0 or len(target) == 0:
        return PlicpResult(pose, np.inf, 0, 0, False, np.zeros((3, 3)))
    pose, it, converged, degenerate = _gauss_newton(target, ref, pose, cfg, prior, prior_info)
    return _final_result(target, ref, pose, it, converged, degenerate, cfg)


def _prior_terms(
    pose: np.ndarray, c: np.ndarray, prior: np.ndarray, info: np.ndarray, point_sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """The odometry prior linearised in the step (dx, dy, d_theta) about the centroid
    ``c``, in units of the matches' cost (x point_sigma^2): (A^T L A, A^T L e0), where
    e0 = prior^-1 o pose in the prior's frame and A = de/d(step). A pose moved by the
    step is x' = c + R(d_theta)(x - c) + d_t, theta' = theta + d_theta."""
    cp, sp = np.cos(prior[2]), np.sin(prior[2])
    Rt = np.array([[cp, sp], [-sp, cp]])  # R(prior)^T
    e0 = np.concatenate([Rt @ (pose[:2] - prior[:2]), [float(wrap(pose[2] - prior[2]))]])
    v = pose[:2] - c
    A = np.zeros((3, 3))
    A[:2, :2] = Rt
    A[:2, 2] = Rt @ np.array([-v[1], v[0]])
    A[2, 2] = 1.0
    L = info * point_sigma**2
    return A.T @ L @ A, A.T @ L @ e0


def _constrained_step(
    J: np.ndarray,
    w: np.ndarray,
    r: np.ndarray,
    rel: np.ndarray,
    ratio: float,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, int]:
    """Weighted Gauss-Newton step that moves only along directions the matches constrain:
    the rotation column is scaled by the points' RMS distance L (all three in metres),
    and eigen-directions of J^T W J weaker than ``ratio`` x the strongest are left at the
    prediction (a corridor seen without its ends: no slide along it). ``prior``: the
    odometry prior's (H, g) of :func:`_prior_terms`, added to the kept directions of the
    matches (so that the directions left out follow the prior alone). Returns the step
    (dx, dy, d_theta) and the number of directions left out."""
    length = max(float(np.sqrt(np.mean(np.sum(rel**2, axis=1)))), 1e-3)
    scale = np.array([1.0, 1.0, 1.0 / length])
    Js = J * scale
    H = (Js * w[:, None]).T @ Js
    g = (Js * w[:, None]).T @ r
    lam, V = np.linalg.eigh(H)
    keep = lam > ratio * max(lam[-1], 1e-12)
    if prior is None:
        step = -V[:, keep] @ ((V[:, keep].T @ g) / lam[keep])
        return step * scale, int((~keep).sum())
    Vk = V[:, keep]
    H_kept = (Vk * lam[keep]) @ Vk.T
    g_kept = Vk @ (Vk.T @ g)
    Hp = prior[0] * scale[:, None] * scale[None, :]  # in the scaled parameters
    gp = prior[1] * scale
    step = -np.linalg.solve(H_kept + Hp, g_kept + gp)
    return step * scale, int((~keep).sum())


def _huber_weights(r: np.ndarray, floor: float) -> np.ndarray:
    """Huber weights with the threshold 3 robust sigmas of the residuals (at least
    ``floor`` m): matches to walls the reference has not seen yet (up to ``max_distance``
    away) stop pulling the pose."""
    c = max(floor, 3.0 * 1.4826 * float(np.median(np.abs(r))))
    a = np.abs(r)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-12))


def _jacobian(n: np.ndarray, m: np.ndarray) -> np.ndarray:
    """d(n . m)/d(dx, dy, d_theta) for points m rotated about the origin of their frame."""
    return np.column_stack([n[:, 0], n[:, 1], n[:, 1] * m[:, 0] - n[:, 0] * m[:, 1]])


def _world_to_body_info(info_world: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Information of a left (world-frame) perturbation turned into one of the pose's own
    (x, y, theta) tangent as gtsam's Pose2 uses: d_world = Ad(pose) d_body."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    ad = np.array([[c, -s, pose[1]], [s, c, -pose[0]], [0.0, 0.0, 1.0]])
    return ad.T @ info_world @ ad
