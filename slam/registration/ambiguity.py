"""Is an alignment unique along its weakest horizontal direction? The slide test.

A registration along a plain corridor converges, and its Hessian may even look healthy
(the walls fix the two directions across the corridor, and yaw), yet the corridor's walls
say nothing about the position along it: only surfaces facing that direction (door jambs,
pillars, an end wall) do. The test (used by loop verification and by the front ends'
keyframe odometry information): take the weakest horizontal direction v of the
registration Hessian (Schur complement of the rotation; Zhang et al. 2016), score only the
source points whose normals face v (:func:`alignment_score`: share of points meeting a
target surface) at the result and slid by d along v; the ambiguity is the best slid score
over the result's. A periodic or plain corridor keeps its score when slid (~1), a room's
end walls miss at a metre (< 0.5). Too few facing points is degeneracy itself (1).

Ordering and side are GTSAM's (rotation first, right perturbation ``T Exp(delta)``), as the
registrations here produce them, so v is in the source (sensor) frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import small_gicp

from slam.errors import ConfigError

# fewer facing (or judged) points than this and the score is not meaningful
MIN_JUDGED_POINTS = 50
# a source point faces v when |normal . v| exceeds this
FACING = 0.5
# steep (wall-like) points: |normal_z| below this after the rotation
STEEP = 0.7


class ScoreParams(Protocol):
    """What :func:`alignment_score` reads (``VerifyParams`` and
    ``OdometryAmbiguityConfig`` have these fields)."""

    inlier_distance: float
    beam_gap_deg: float
    plane_tolerance: float
    plane_range_ratio: float
    num_threads: int


@dataclass
class Prepared:
    """A cloud downsampled at one voxel size with its normals/covariances and KD-tree."""

    cloud: small_gicp.PointCloud
    tree: small_gicp.KdTree
    points: np.ndarray
    normals: np.ndarray


def prepare(points: np.ndarray, voxel: float, num_threads: int = 1) -> Prepared:
    """``points`` (N, 3) voxel-downsampled with small_gicp's normals and KD-tree."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :3])
    cloud, tree = small_gicp.preprocess_points(pts, voxel, num_threads=num_threads)
    return Prepared(
        cloud, tree, np.asarray(cloud.points())[:, :3], np.asarray(cloud.normals())[:, :3]
    )


def alignment_score(
    judged: np.ndarray, target: Prepared, T: np.ndarray, p: ScoreParams
) -> tuple[float, float]:
    """(overlap 0-1, fitness m) of ``judged`` source points moved by T onto the target.

    A point is an inlier when its nearest target point lies within
    max(inlier_distance, tan(beam_gap) x range) and its distance to that point's plane
    within plane_tolerance + plane_range_ratio x range (range: from the target's sensor).
    fitness: RMS point-to-plane distance of the inliers (inf without inliers).
    """
    moved = judged @ T[:3, :3].T + T[:3, 3]
    idx, sq = target.tree.batch_nearest_neighbor_search(moved, num_threads=p.num_threads)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    sq = np.asarray(sq, dtype=np.float64).reshape(-1)
    if len(sq) == 0:
        return 0.0, float("inf")
    rng = np.linalg.norm(moved, axis=1)
    radius = np.maximum(p.inlier_distance, np.tan(np.radians(p.beam_gap_deg)) * rng)
    found = (idx >= 0) & (sq < radius**2)
    k = np.where(found, idx, 0)
    plane = np.abs(np.einsum("ij,ij->i", moved - target.points[k], target.normals[k]))
    inl = found & (plane < p.plane_tolerance + p.plane_range_ratio * rng)
    overlap = float(inl.mean())
    fitness = float(np.sqrt(np.mean(plane[inl] ** 2))) if inl.any() else float("inf")
    return overlap, fitness


def weakest_horizontal(H: np.ndarray) -> np.ndarray:
    """Unit (3,) direction in the source frame, horizontal, that the registration Hessian
    (6x6, rotation first, right perturbation T Exp(delta)) constrains least: the weaker
    eigenvector of the horizontal 2x2 block of the translation information with the
    rotation marginalised out (Schur complement; Zhang et al. 2016, the eigenvalue test)."""
    H = 0.5 * (np.asarray(H, dtype=np.float64) + np.asarray(H, dtype=np.float64).T)
    if not np.all(np.isfinite(H)):
        return np.array([1.0, 0.0, 0.0])
    Hrr, Hrt, Htt = H[:3, :3], H[:3, 3:], H[3:, 3:]
    S = Htt - Hrt.T @ np.linalg.pinv(Hrr) @ Hrt
    _, vec = np.linalg.eigh(S[:2, :2])
    return np.array([vec[0, 0], vec[1, 0], 0.0])


def slide_shifts(min_shift: float, max_shift: float, step: float) -> np.ndarray:
    """The slides (m) of the test: min_shift..max_shift in steps of ``step``, both ways."""
    if step <= 0 or min_shift <= 0 or max_shift < min_shift:
        raise ConfigError(
            f"slide range needs 0 < min_shift <= max_shift and step > 0 "
            f"(got {min_shift}, {max_shift}, {step})"
        )
    s = np.arange(min_shift, max_shift + 1e-9, step)
    return np.concatenate([s, -s])


def ambiguous_axis(
    judged: np.ndarray,
    normals: np.ndarray,
    target: Prepared,
    T: np.ndarray,
    H: np.ndarray,
    p: ScoreParams,
    ratio: float,
    shifts: np.ndarray,
) -> tuple[np.ndarray, float]:
    """Whether the alignment T is unique along its weakest horizontal direction v.

    Only surfaces facing v (``judged`` source points with |normal . v| > 0.5, ``normals``
    their unit normals in the source frame: door jambs, pillars, the end of a corridor) fix
    the position along it, so only they are scored (:func:`alignment_score`): at the
    result, and slid by each d of ``shifts`` (m) along v (source frame, T Exp(d v)). The
    ambiguity is the best slid overlap over the result's: a periodic corridor meets its next
    bay again (~1), a room's end walls miss at a metre (< 0.5). Fewer than
    MIN_JUDGED_POINTS facing points (a plain corridor) is degeneracy itself (ambiguity 1).
    Returns (v in the target frame (1, 3), or (0, 3) when the ambiguity is below ``ratio``;
    the ambiguity). ``ratio`` <= 0 or no judged points: never ambiguous.
    """
    none = np.zeros((0, 3))
    if ratio <= 0 or len(judged) == 0:
        return none, 0.0
    v = weakest_horizontal(H)
    facing = np.abs(np.asarray(normals) @ v) > FACING
    axis = (T[:3, :3] @ v)[None, :]
    if facing.sum() < MIN_JUDGED_POINTS:
        return axis, 1.0
    pts = judged[facing]
    base = alignment_score(pts, target, T, p)[0]
    if base <= 0:
        return axis, 1.0
    best = 0.0
    for d in np.asarray(shifts, dtype=np.float64):
        Ts = np.array(T, dtype=np.float64)
        Ts[:3, 3] = T[:3, 3] + T[:3, :3] @ (d * v)
        best = max(best, alignment_score(pts, target, Ts, p)[0])
    amb = best / base
    return (axis if amb >= ratio else none), float(amb)


def free_information(info: np.ndarray, axes_source: np.ndarray, free_sigma: float) -> np.ndarray:
    """``info`` (6x6, rotation first) with the translation directions ``axes_source`` (k, 3,
    the factor's tangent frame) left to the other factors: their information becomes
    1 / free_sigma^2 and their coupling to the other directions is removed; across them the
    information is unchanged."""
    out = np.asarray(info, dtype=np.float64)
    for a in np.asarray(axes_source, dtype=np.float64).reshape(-1, 3):
        u = np.zeros(6)
        u[3:] = a / np.linalg.norm(a)
        P = np.eye(6) - np.outer(u, u)
        out = P @ out @ P + np.outer(u, u) / free_sigma**2
    return 0.5 * (out + out.T)


# ----------------------------------------------------------------------------- odometry


@dataclass
class OdometryAmbiguityConfig:
    """Degeneracy-aware odometry information (front ends, keyframes only).

    At each keyframe its cloud (sensor frame, thinned to ``voxel`` m) is slid along the
    registration's weakest horizontal direction against the clouds of the previous
    ``window`` keyframes (put in its frame by the odometry): the facing points (at most
    ``max_points``, an even subsample) are scored at 0 and at min_shift..max_shift m in
    steps of ``step`` m both ways; when some slide keeps ``ratio`` of the score, the
    keyframe's odometry information along that axis is replaced by 1 / sigma^2 (sigma in
    m), its coupling removed, the rest unchanged. The odometry itself is not changed (only
    a graph with loops sees it). inlier_distance .. plane_range_ratio: the inlier test of
    the score (as the loop verification's).
    """

    enabled: bool = False
    ratio: float = 0.8
    min_shift: float = 1.0
    max_shift: float = 8.0
    step: float = 0.5
    sigma: float = 0.3
    window: int = 10
    voxel: float = 0.25
    max_points: int = 1000
    inlier_distance: float = 0.3
    beam_gap_deg: float = 2.0
    plane_tolerance: float = 0.1
    plane_range_ratio: float = 0.002
    num_threads: int = 1

    def __post_init__(self) -> None:
        if self.sigma <= 0 or self.voxel <= 0 or self.window < 1 or self.max_points < 1:
            raise ConfigError("odometry_ambiguity: sigma, voxel > 0, window, max_points >= 1")
        slide_shifts(self.min_shift, self.max_shift, self.step)


@dataclass
class OdometryAmbiguity:
    """axis: (3,) unit direction in the keyframe's sensor frame that was tested (the
    registration's weakest horizontal one); ratio: best slid score / score at the result
    (1 = no facing structure at all); ambiguous: ratio >= the config's."""

    axis: np.ndarray
    ratio: float
    ambiguous: bool


def facing_points(
    source: Prepared, v: np.ndarray, max_points: int
) -> tuple[np.ndarray, np.ndarray]:
    """(points, normals) of the steep source points facing ``v`` (sensor frame), at most
    ``max_points`` of them (an even subsample)."""
    n = source.normals
    idx = np.flatnonzero((np.abs(n[:, 2]) < STEEP) & (np.abs(n @ v) > FACING))
    if len(idx) > max_points:
        idx = idx[np.linspace(0, len(idx) - 1, max_points).astype(np.intp)]
    return source.points[idx], n[idx]


def odometry_ambiguity(
    source: np.ndarray,
    target: np.ndarray,
    H: np.ndarray,
    cfg: OdometryAmbiguityConfig,
) -> OdometryAmbiguity:
    """The slide test of a keyframe: ``source`` (N, 3) its cloud and ``target`` (M, 3) the
    previous keyframes' clouds, both in the keyframe's sensor frame (the alignment is the
    identity), ``H`` the registration Hessian (6x6, rotation first) giving the axis."""
    v = weakest_horizontal(H)
    if len(source) < MIN_JUDGED_POINTS or len(target) < MIN_JUDGED_POINTS:
        return OdometryAmbiguity(v, 1.0, True)
    src = prepare(source, cfg.voxel, cfg.num_threads)
    pts, normals = facing_points(src, v, cfg.max_points)
    if len(pts) < MIN_JUDGED_POINTS:
        return OdometryAmbiguity(v, 1.0, True)
    tgt = prepare(target, cfg.voxel, cfg.num_threads)
    shifts = slide_shifts(cfg.min_shift, cfg.max_shift, cfg.step)
    axis, amb = ambiguous_axis(pts, normals, tgt, np.eye(4), H, cfg, cfg.ratio, shifts)
    return OdometryAmbiguity(v, amb, bool(len(axis)))


def loosened_information(info: np.ndarray, axis: np.ndarray, sigma: float) -> np.ndarray:
    """Odometry information (6x6, rotation first) with sigma (m) along the translation
    ``axis`` (3,) and unchanged across it (:func:`free_information`)."""
    return free_information(info, np.asarray(axis, dtype=np.float64)[None, :], sigma)
