"""Point-to-edge / point-to-plane scan-to-map matching of FLOAM / A-LOAM (the paper's baseline).

For each edge point of the scan: its 5 nearest edge-map points; when their covariance has a
dominant direction (largest eigenvalue > ``edge_ratio`` x the second) they form a line and
the residual is the distance of the point to that line. For each plane point: its 5 nearest
plane-map points; when a least-squares plane fits them (all within ``plane_threshold``) the
residual is the point-to-plane distance; plane points on the scan's fitted ground plane use
its normal instead (the 5 map neighbours of a ground point lie on one ring, whose fitted
"plane" may stand across the ring and hold the scan at the map's rings: docs/paper000.md,
"The ground's rings"). Both are written as e^T W e with W the projector
onto the line's normal space (I - v v^T) or the plane normal (n n^T), so the weighted SE(3)
Gauss-Newton solver of ``gicp`` minimises them jointly, with Huber weights (FLOAM: 0.1 m),
re-associating every iteration, all correspondences vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError
from slam.registration.ground_plane import FixedNormals
from slam.registration.neighbours import KnnTree, _workers
from slam.registration.result import RegistrationError, RegistrationResult, _check_points
from slam.registration.se3 import transform
from slam.registration.solver import solve_weighted


@dataclass
class FeatureIcpConfig:
    """k_neighbors: map points per correspondence (LOAM: 5). max_neighbor_distance: all of
    them must lie within this distance (m). edge_ratio: line test on eigenvalues.
    plane_threshold: max point-to-plane distance of the neighbours (m). huber_delta: robust
    kernel width (m), 0 disables it. scatter_cycle_tolerance (m, rad): with scatter points
    (the open-road mode) a pose that comes back within this of one 2-4 iterations before,
    having gone 2.5x as far in between, has converged (``solver.solve_weighted``): their
    nearest-point pairs change from one iteration to the next and the pose cycles within
    millimetres instead of meeting the 1e-6 epsilons (a 21 m/s motorway start: its second
    frame, 2 cm from the truth, was rejected as unconverged); 0 = off. least_cost: a
    registration that reaches max_iterations after its re-associated cost rose ends at the
    pose of least cost (``solver.solve_weighted``; the front end asks only from a tracked
    prediction): its steps chased the pairs of a sparse map behind the scan (a 21 m/s VLP-16
    start crept back 4 cm per iteration against its two-scan map)."""

    k_neighbors: int = 5
    max_neighbor_distance: float = 1.0
    edge_ratio: float = 3.0
    plane_threshold: float = 0.2
    huber_delta: float = 0.1
    max_iterations: int = 20
    transformation_epsilon: float = 1e-6
    fitness_epsilon: float = 1e-6
    threads: int = 2
    scatter_cycle_tolerance: float = 0.002
    least_cost: bool = True

    def __post_init__(self) -> None:
        if self.k_neighbors < 3:
            raise ConfigError(f"k_neighbors must be >= 3, got {self.k_neighbors}")
        if self.max_neighbor_distance <= 0 or self.edge_ratio < 1 or self.max_iterations < 1:
            raise ConfigError(
                "need max_neighbor_distance > 0, edge_ratio >= 1, max_iterations >= 1"
            )
        if self.scatter_cycle_tolerance < 0:
            raise ConfigError("scatter_cycle_tolerance must be >= 0 (0 = off)")


class FeatureTarget:
    """Map points (M, 3) of one feature class with their KD-tree, or anything with cKDTree's
    ``query`` (the local map ``VoxelHashMap`` answers it through its voxel hash)."""

    def __init__(self, points: np.ndarray, tree: cKDTree | None = None):
        self.points = _check_points(points, "feature map points")
        self.tree = cKDTree(self.points) if tree is None and len(self.points) else tree

    def __len__(self) -> int:
        return len(self.points)


class MapTreeCache:
    """A local map (``points`` (M, 3) view, ``version`` counting its changes) as a
    FeatureTarget whose KD-tree is rebuilt only when the map changed: small_gicp's
    (``gicp.KnnTree``: the same neighbours as a cKDTree at about half the query cost; a
    front end queries each map 8-20 times per insert)."""

    def __init__(self) -> None:
        self._version = -1
        self._tree: KnnTree | None = None

    def target(self, local_map) -> FeatureTarget:
        if self._version != local_map.version:
            pts = local_map.points
            self._tree = KnnTree(pts) if len(pts) else None
            self._version = local_map.version
        return FeatureTarget(local_map.points, self._tree)


class _Neighbourhoods:
    """Analysis (centroid, eigen-decomposition) of the k-NN map neighbourhood of each scan
    point, remembered between the solver's iterations: it depends on the neighbour indices
    only, so a point whose neighbours (and their order) did not change since the last
    iteration keeps its analysis instead of a new eigh (same numbers; most points keep their
    neighbours once the solver is near the optimum)."""

    def __init__(self, target: FeatureTarget | None, n: int, cfg: FeatureIcpConfig):
        self.target, self.cfg = target, cfg
        k = cfg.k_neighbors
        self.j = np.full((n, k), -1, dtype=np.int64)
        self.c = np.zeros((n, 3))
        self.w = np.zeros((n, 3))
        self.V = np.zeros((n, 3, 3))
        self.centred = np.zeros((n, k, 3))

    def __call__(self, moved: np.ndarray):
        """(valid mask, centroids, eigenvalues ascending, eigenvectors, centred neighbours) of
        the valid rows (k neighbours within ``max_neighbor_distance``), or None."""
        cfg, target = self.cfg, self.target
        k = cfg.k_neighbors
        if target is None or len(target) < k or len(moved) == 0:
            return None
        # bounded search: a neighbourhood whose k-th point is beyond the limit is not used
        d, j = target.tree.query(
            moved,
            k=k,
            distance_upper_bound=cfg.max_neighbor_distance,
            workers=_workers(len(moved), cfg.threads),
        )
        j = np.asarray(j, dtype=np.int64).reshape(len(moved), k)
        ok = d.reshape(len(moved), k)[:, -1] < cfg.max_neighbor_distance
        new = ok & np.any(j != self.j, axis=1)
        if new.any():
            nb = target.points[j[new]]
            c = nb.mean(axis=1)
            centred = nb - c[:, None, :]
            w, V = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred) / k)
            self.c[new], self.centred[new], self.w[new], self.V[new] = c, centred, w, V
            self.j[new] = j[new]
        return ok, self.c[ok], self.w[ok], self.V[ok], self.centred[ok]


def _huber(r: np.ndarray, delta: float) -> np.ndarray:
    """(N,) Huber IRLS weight of residuals r (m): 1 within delta, delta / r beyond."""
    if delta <= 0:
        return np.ones_like(r)
    return np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-12))


Terms = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # (p, q, W, |residual|)


def _edge_terms(edges: np.ndarray, moved: np.ndarray, nh, cfg: FeatureIcpConfig) -> Terms:
    """Point-to-line terms of the edge points whose map neighbourhood is a line (largest
    eigenvalue > edge_ratio x the middle one): W = I - v v^T, residual |W (p - c)| (m)."""
    ok, c, w, V, _ = nh
    line = w[:, 2] > cfg.edge_ratio * w[:, 1]
    v = V[line, :, 2]
    P = np.eye(3) - v[:, :, None] * v[:, None, :]
    e = np.einsum("nij,nj->ni", P, moved[ok][line] - c[line])
    return edges[ok][line], c[line], P, np.linalg.norm(e, axis=1)


def _plane_terms(
    planes: np.ndarray,
    moved: np.ndarray,
    nh,
    cfg: FeatureIcpConfig,
    ground: FixedNormals | None = None,
    R: np.ndarray | None = None,
) -> Terms:
    """Point-to-plane terms of the plane points whose map neighbours all lie within
    plane_threshold (m) of their plane: W = n n^T, residual |n . (p - c)| (m). ``ground``:
    the points on the scan's ground, whose plane normal (rotated by the pose's R) is its."""
    ok, c, w, V, centred = nh
    n = V[:, :, 0]
    if ground is not None:
        n = ground.applied(n, ok, R)
    flat = np.max(np.abs(np.einsum("nki,ni->nk", centred, n)), axis=1) < cfg.plane_threshold
    n = n[flat]
    r = np.abs(np.einsum("ni,ni->n", moved[ok][flat] - c[flat], n))
    return planes[ok][flat], c[flat], n[:, :, None] * n[:, None, :], r


HORIZONTAL = np.diag([1.0, 1.0, 0.0])  # W of a term across the horizontal only


def nearest_pairs(
    moved: np.ndarray, target: FeatureTarget | None, max_distance: float, threads: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) bool rows of ``moved`` (N, 3) with a ``target`` point within ``max_distance``
    (m), those nearest points (n_ok, 3) and their distances (n_ok,) m."""
    if target is None or not len(target) or not len(moved):
        return np.zeros(len(moved), dtype=bool), np.zeros((0, 3)), np.zeros(0)
    d, j = target.tree.query(
        moved, k=1, distance_upper_bound=max_distance, workers=_workers(len(moved), threads)
    )
    d, j = np.asarray(d).reshape(-1), np.asarray(j, dtype=np.int64).reshape(-1)
    ok = d < max_distance
    return ok, target.points[j[ok]], d[ok]


def horizontal_pairs(
    moved: np.ndarray, target: FeatureTarget | None, max_distance: float, threads: int = 2
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``nearest_pairs`` with the horizontal distance (m) of each pair: the open-road mode's
    scatter terms, whose heights are the rings' (``HORIZONTAL``)."""
    ok, q, _ = nearest_pairs(moved, target, max_distance, threads)
    return ok, q, np.linalg.norm(moved[ok][:, :2] - q[:, :2], axis=1)


def _scatter_terms(
    points: np.ndarray, moved: np.ndarray, target: FeatureTarget | None, cfg: FeatureIcpConfig
) -> Terms | None:
    """Point-to-point terms of scatter points (vegetation, clutter: the open-road mode,
    ``slam.odometry.open_road``) with their nearest map point within
    ``max_neighbor_distance``, horizontal only: W = diag(1, 1, 0) in the odometry frame
    (whose z is the first scan's up), residual the horizontal distance (m). Ragged surfaces
    have no normal to project on (their neighbourhoods' least-spread directions point
    anywhere: as point-to-plane terms they held a 16-beam motorway scan at rest); what they
    show is where they stand. Their heights are the rings' (a beam meets a trunk at another
    height from every pose), not the surface's: as 3D terms they pitched the scan (floam on
    a 1238 m city drive: APE 2.41 -> 4.07 m once the mode came on); the ground holds the
    height. Against the scan's ground normal instead of the frame's z, the motorway starts
    were worse (three of 18 more failed)."""
    ok, q, d = horizontal_pairs(moved, target, cfg.max_neighbor_distance, cfg.threads)
    if not len(q):
        return None
    return points[ok], q, np.broadcast_to(HORIZONTAL, (len(q), 3, 3)), d


def feature_icp_align(
    edge_xyz: np.ndarray,
    plane_xyz: np.ndarray,
    edge_map: FeatureTarget | None,
    plane_map: FeatureTarget | None,
    init_T: np.ndarray | None = None,
    cfg: FeatureIcpConfig | None = None,
    ground: FixedNormals | None = None,
    scatter_xyz: np.ndarray | None = None,
    scatter_map: FeatureTarget | None = None,
) -> RegistrationResult:
    """Align scan edge/plane points to the edge/plane maps; returns T_map_scan and H.
    ``ground``: the plane points on the scan's ground plane, which constrain along its
    normal only."""
    cfg = cfg or FeatureIcpConfig()
    edges = _check_points(edge_xyz, "edge points")
    planes = _check_points(plane_xyz, "plane points")
    if ground is not None and len(ground.rows) != len(planes):
        raise ValueError(f"ground has {len(ground.rows)} rows for {len(planes)} plane points")
    if len(edges) + len(planes) < 6:
        raise RegistrationError(
            f"feature ICP needs at least 6 feature points, got {len(edges) + len(planes)}"
        )
    edge_nh = _Neighbourhoods(edge_map, len(edges), cfg)
    plane_nh = _Neighbourhoods(plane_map, len(planes), cfg)
    # scatter points count (in the pairs, the inlier share) only where they have a map: the
    # mode's first scan after a stretch off it has none, and counted it halved the share,
    # the gate rejected the scan and no scan entered the map again (a 1238 m city drive)
    has_map = scatter_map is not None and len(scatter_map) > 0
    scatter = np.zeros((0, 3))
    if scatter_xyz is not None and has_map:
        scatter = _check_points(scatter_xyz, "scatter")

    def associate(T):
        terms = []
        moved = transform(T, edges)
        nh = edge_nh(moved)
        if nh is not None:
            terms.append(_edge_terms(edges, moved, nh, cfg))
        moved = transform(T, planes)
        nh = plane_nh(moved)
        if nh is not None:
            terms.append(_plane_terms(planes, moved, nh, cfg, ground, T[:3, :3]))
        # the fitness (RMSE) is the features': a scatter point's distance to the nearest
        # map point is the map's spacing, not how well the scan fits (the gate compares it
        # between frames, across the mode's switches)
        sqd = np.concatenate([t[3] for t in terms] + [np.zeros(0)]) ** 2
        if len(scatter):
            st = _scatter_terms(scatter, transform(T, scatter), scatter_map, cfg)
            if st is not None:
                terms.append(st)
        if not terms:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), None, np.zeros(0)
        ps, qs, Ws, rs = zip(*terms, strict=True)
        r = np.concatenate(rs)
        return (
            np.concatenate(ps),
            np.concatenate(qs),
            np.concatenate(Ws),
            _huber(r, cfg.huber_delta),
            sqd,
        )

    init = np.eye(4) if init_T is None else np.asarray(init_T, dtype=np.float64)
    return solve_weighted(
        init,
        associate,
        len(edges) + len(planes) + len(scatter),
        max_iterations=cfg.max_iterations,
        transformation_epsilon=cfg.transformation_epsilon,
        fitness_epsilon=cfg.fitness_epsilon,
        residual_dims=1,
        cycle_tolerance=cfg.scatter_cycle_tolerance if len(scatter) else 0.0,
        least_cost=cfg.least_cost,
        # the numpy solver: FLOAM's Huber-weighted solve stops on 1e-6 epsilons, and the
        # kernels' last-bit rounding moved the corridor APE by 12 % over 300 frames (chaotic,
        # 2.07 -> 2.32 cm); its association, not the 6x6 algebra, is what costs here
        reference=True,
    )
