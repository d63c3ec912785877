"""Statistical outlier removal: the classic PCL/open3d filter and the paper's weighted,
density-adaptive variant (improved FLOAM, paper 000, section 2.3, eqs. (4)-(9)).

Both return a boolean keep-mask over the input points, so callers can filter every
per-point field of a scan (``scan.select(mask)``).

Exactness and its price (issue 12, measured on one scan each of the simulated urban HDL-64
and the real KITTI-raw HDL-64E, one thread, CPU ms): the statistics mu, sigma (eqs. (8),
(9)), d_avg (5) and rho_avg are sums over every point's k-NN distances, so the exact filter
needs the exact k-NN of every raw point; nothing cheaper decides it exactly. Estimating them
from a plain sample fails: sigma is set by a few isolated points (KITTI-raw: 0.111 m for the
scan, 0.063 m from every 4th point, 2.6 % of the decisions flipped; corridor: every 16th
point gave sigma 0.005 against 0.036). ``weighted_sor_estimated`` (opt-in,
``SorConfig.stats_stride``) therefore searches the sparse points in full and lets only the
points that are certain to be kept stop early (``safe_keep_radius``): stride 8 flips 0-3 of
117-133k decisions (urban HDL-64 APE over 100 frames 4.97 -> 4.88 cm, OS-128 3.83 -> 3.84 cm,
KITTI-raw per-frame motion vs small_gicp 0.69 / 1.86 cm mean / max, both unchanged), and
takes the k-NN + statistics from 67.9 to 56.4 ms (urban) and 88.1 to 67.7 ms (KITTI-raw).
In the pipeline the curvature correction then asks for the exact rows of ~10k features, and
completing the stopped ones costs a fresh window search each (~1 us per row, 2 ms per call):
CPU per frame, 2 threads, machine under load (15-22 on 2 cores), same run: SOR 111 -> 105
(urban) and 127 -> 113 ms (KITTI-raw), completion +21 / +17 ms, the frame 194 -> 213 /
209 -> 208 ms; with OMP_WAIT_POLICY=passive (OpenMP's idle threads spinning inflate every
parallel region's CPU time, small_gicp's 2.5x) on KITTI-raw: SOR 115 -> 91, completion
+10, the frame 204 -> 182 ms, while wall time per frame grew (two more parallel regions per
scan, each barrier dear on a loaded machine). Not shown to pay on a quiet machine yet, hence
off by default. ``benchmarks/bench_preprocess.py --estimated`` (filter plus the exact rows
of 10k kept points, min of 5, load average 25, CPU ms): 1 thread urban 73.0 -> 68.9,
KITTI-raw 99.6 -> 86.6; 2 threads 95.4 -> 113.5, 110.7 -> 132.2 (its 3 parallel regions per
scan against 1); 16-beam scans 10-13 -> 16-19 (stats_min_points keeps them exact).
Writing no neighbour indices at all (distances only) saved
3-4 % of the window search (urban, KITTI-raw), less than the second search the curvature's
rows would then need.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import ConfigError, InputError
from slam.preprocess.knn import knn, self_knn
from slam.preprocess.sor_kernels import (
    safe_keep_radius,
    stratified_sor_kernel,
    weighted_sor_kernel_simd,
)

SOR_METHODS = ("weighted", "classic")
SOR_MODES = ("paper", "banded")
STATS_TRIM = 0.001  # share of the sample's largest d left out of the early-exit radius
STATS_ROUNDS = 3  # rounds of statistics and re-searched unsafe exits before the exact filter


@dataclass
class SorConfig:
    """Outlier-removal settings. k neighbours, alpha threshold coefficient, delta (eq. 9).

    range_adaptive and max_density_ratio only affect the weighted method (see weighted_sor).

    mode: "paper" = one statistic (mu, sigma, d_avg, rho_avg of eqs. (5)-(9)) for the whole
    scan, as printed; "banded" = the same equations with the statistics of each range band
    (``band_edges``, m from the sensor; ``banded_sor``), so that the sparse far field of a
    dense sensor is judged against far points, not against the near field that sets the
    scan-wide statistic. A band of fewer than band_min_points points joins its inner
    neighbour (the first band its outer one).

    stats_stride / stats_min_points: the opt-in estimated statistics of the weighted method
    (``weighted_sor_estimated``) for scans of at least stats_min_points points with a ring
    field: one point in stats_stride (of the range-image order) gets its exact k-NN for the
    statistics of eqs. (5), (8), (9), the others stop their search as soon as they are
    certain to be kept. 0 = the exact statistics (default; the module doc has the numbers:
    0-3 decisions of ~120k flipped, no net gain per frame once the curvature's rows are
    completed).
    """

    enabled: bool = True
    method: str = "weighted"
    k: int = 10
    alpha: float = 1.0
    delta: float = 1e-5
    range_adaptive: bool = False
    max_density_ratio: float = 1.0
    stats_stride: int = 0
    stats_min_points: int = 100000
    mode: str = "paper"
    band_edges: tuple[float, ...] = (15.0, 30.0, 50.0)
    band_min_points: int = 500

    def __post_init__(self) -> None:
        if self.mode not in SOR_MODES:
            raise ConfigError(f"unknown SOR mode '{self.mode}'; valid: {', '.join(SOR_MODES)}")
        self.band_edges = tuple(float(e) for e in self.band_edges)
        if any(e <= 0 for e in self.band_edges) or list(self.band_edges) != sorted(
            set(self.band_edges)
        ):
            raise ConfigError("SOR band_edges must be increasing ranges > 0 (m)")
        if self.band_min_points < 3:
            raise ConfigError(f"SOR band_min_points must be >= 3, got {self.band_min_points}")
        if self.method not in SOR_METHODS:
            raise ConfigError(
                f"unknown SOR method '{self.method}'; valid: {', '.join(SOR_METHODS)}"
            )
        if self.k < 1:
            raise ConfigError(f"SOR k must be >= 1, got {self.k}")
        if self.alpha < 0 or self.delta < 0 or self.max_density_ratio < 0:
            raise ConfigError("SOR alpha, delta and max_density_ratio must be >= 0")
        if self.stats_stride < 0 or self.stats_stride == 1 or self.stats_min_points < 0:
            raise ConfigError(
                "SOR stats_stride must be 0 (exact statistics) or >= 2, stats_min_points >= 0"
            )


def _check_xyz(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    # a finite sum proves every value finite (NaN and inf propagate); the elementwise check
    # (an (N, 3) temporary) only when it does not, e.g. for huge finite values
    with np.errstate(invalid="ignore", over="ignore"):
        total = xyz.sum()
    if not np.isfinite(total) and not np.all(np.isfinite(xyz)):
        raise InputError("points contain NaN or inf; drop invalid returns before filtering")
    return xyz


class Neighbourhoods:
    """The one k-NN query SOR makes, kept for reuse (e.g. the curvature correction).

    idx: (N, k+1) indices of each point's nearest points, itself first; dist: (N, k)
    distances (m) to the k nearest other points, ascending. Built by ``neighbourhoods``,
    the search runs when first needed: ``apply_sor`` may then search with early exits
    (``SorConfig.stats_stride``), after which ``idx`` completes the rows asked for
    (``idx[rows, :k]``) with their exact neighbours on demand (``np.asarray(idx)``: all).
    """

    def __init__(
        self,
        idx: np.ndarray | None = None,
        dist: np.ndarray | None = None,
        *,
        xyz: np.ndarray | None = None,
        k: int = 0,
        ring: np.ndarray | None = None,
    ) -> None:
        self._idx, self._dist = idx, dist
        self._xyz, self._k, self._ring = xyz, k, ring
        self._image = None  # slam.preprocess.range_image.RangeImage of an early-exit search
        self._res = None  # its RangeImageKnn
        self._inexact: np.ndarray | None = None  # (N,) rows not yet exact

    @property
    def searched(self) -> bool:
        return self._dist is not None

    def _search(self) -> None:
        if self._dist is None:
            self._idx, self._dist = self_knn(self._xyz, self._k, ring=self._ring)

    def complete(self, rows: np.ndarray | None = None) -> None:
        """Make the given rows (all when None) exact k-NN rows."""
        self._search()
        if self._inexact is None:
            return
        todo = np.flatnonzero(self._inexact) if rows is None else np.asarray(rows).ravel()
        todo = np.unique(todo[self._inexact[todo]]) if len(todo) else todo
        if len(todo):
            left = self._image.exact_rows(self._res, todo)
            if len(left):  # the box search declined: a KD-tree over the whole scan
                from slam.preprocess.knn import fallback_tree

                k = self._dist.shape[1]
                fb_dist, fb_idx = fallback_tree(self._xyz).query(self._xyz[left], k + 1)
                others = fb_idx != left[:, None]
                others[others.all(axis=1), -1] = False
                self._idx[left, 0] = left
                self._idx[left, 1:] = fb_idx[others].reshape(-1, k)
                self._dist[left] = fb_dist[others].reshape(-1, k)
            self._inexact[todo] = False
        if rows is None or not self._inexact.any():
            self._inexact = None
            self._image = self._res = None

    @property
    def idx(self):
        self._search()
        return self._idx if self._inexact is None else _LazyRows(self)

    @property
    def dist(self) -> np.ndarray:
        self.complete()
        return self._dist


class _LazyRows:
    """``Neighbourhoods.idx`` while some rows are not exact: indexing by rows first
    completes those rows; ``np.asarray`` completes all."""

    def __init__(self, nbh: Neighbourhoods) -> None:
        self._nbh = nbh

    @property
    def shape(self) -> tuple[int, ...]:
        return self._nbh._idx.shape

    def __len__(self) -> int:
        return len(self._nbh._idx)

    def __getitem__(self, key):
        first = key[0] if isinstance(key, tuple) else key
        self._nbh.complete(np.arange(len(self._nbh._idx))[first])
        return self._nbh._idx[key]

    def __array__(self, dtype=None, copy=None):
        self._nbh.complete()
        return self._nbh._idx if dtype is None else self._nbh._idx.astype(dtype)


def neighbourhoods(xyz: np.ndarray, k: int, *, ring: np.ndarray | None = None) -> Neighbourhoods:
    """k nearest other points of every point.

    ring: (N,) beam index of each point (``scan.ring``) when known: the exact range-image
    search (``slam.preprocess.range_image``; same distances as the KD-tree, same index sets
    up to ties; 1.3-2.5x less time than the KD-tree on 16- and 64-beam scans, measured in
    benchmarks/bench_preprocess.py --scans), run when first needed (``Neighbourhoods``).
    Without it: one KD-tree build and one batch query."""
    k_eff = min(k, len(xyz) - 1)
    if k_eff < 1:
        idx, dist = knn(xyz, xyz, k_eff + 1)
        return Neighbourhoods(idx, dist[:, 1:])
    if ring is None:
        return Neighbourhoods(*self_knn(xyz, k_eff))
    return Neighbourhoods(xyz=np.ascontiguousarray(xyz, dtype=np.float64), k=k_eff, ring=ring)


def knn_distances(xyz: np.ndarray, k: int) -> np.ndarray:
    """(N, k) distances (m) to the k nearest other points, ascending; one KD-tree query."""
    return neighbourhoods(xyz, k).dist


def classic_sor(
    xyz: np.ndarray, k: int = 10, alpha: float = 1.0, *, dist: np.ndarray | None = None
) -> np.ndarray:
    """PCL/open3d statistical outlier removal: keep d_i <= mu + alpha*sigma.

    d_i is the mean distance (m) to the k nearest neighbours; mu and sigma (ddof=1) are over
    all points. PCL semantics (self excluded); open3d counts the point itself, so this equals
    open3d ``remove_statistical_outlier(nb_neighbors=k + 1, std_ratio=alpha)`` exactly.
    dist: the (N, k) neighbour distances when already known (``neighbourhoods``).
    """
    xyz = _check_xyz(xyz)
    if len(xyz) <= 2:
        return np.ones(len(xyz), dtype=bool)
    d = (knn_distances(xyz, k) if dist is None else dist).mean(axis=1)
    return d <= d.mean() + alpha * d.std(ddof=1)


def weighted_sor(
    xyz: np.ndarray,
    k: int = 10,
    alpha: float = 1.0,
    delta: float = 1e-5,
    *,
    range_adaptive: bool = False,
    max_density_ratio: float = 1.0,
    dist: np.ndarray | None = None,
) -> np.ndarray:
    """Weighted density-adaptive SOR (paper 000, eqs. (4)-(9)); returns a keep-mask.

    w_it = exp(-||p_i - p_it|| / d_avg) (4), d_avg the global mean kNN distance (5);
    d_i = sum_t w_it ||p_i - p_it|| / sum_t w_it (6); mu = mean d_i (8),
    sigma = std(d_i, ddof=1) + delta (9); point i is an outlier when d_i > Theta_i with
    Theta_i = mu + alpha*sigma*(1 + min(rho_avg/rho_i, max_density_ratio)) (7).

    Reading of (7): the printed "1 + 1/(rho_i/rho_avg)" is taken literally, i.e. the factor
    grows as the local density rho_i falls below the average (sparse -> lenient) and tends to 1
    (the classic threshold) for dense neighbourhoods (dense -> strict). rho_i = k / V_i with V_i
    the volume of the sphere holding the k neighbours (radius = k-th neighbour distance),
    rho_avg the mean rho_i. The ratio is clamped to ``max_density_ratio`` so an isolated point
    cannot earn an unbounded threshold.

    Density and range (our choice, measured on a simulated 16-beam scan, see tests/test_sor.py):
    the default runs (4)-(9) in metres as printed. On a spinning lidar rho_i falls with range
    squared, so the density term itself acts as the range compensation: far surfaces and thin
    poles are sparse and get the lenient threshold, while the clamp (default 1, i.e. a factor
    between 1 and 2) bounds what isolated returns can gain. range_adaptive=True divides every
    distance of point i by its range (metres -> radians) first; that makes the d_i of all
    surfaces nearly equal, so sigma is set by the outliers themselves and removal drops
    (about 86 % vs 96 % of injected outliers at 0.5 %), hence it is off by default.
    dist: the (N, k) neighbour distances when already known (``neighbourhoods``).
    """
    xyz = _check_xyz(xyz)
    n = len(xyz)
    if n <= 2:
        return np.ones(n, dtype=bool)
    dist = knn_distances(xyz, k) if dist is None else dist
    if range_adaptive:
        rng = np.maximum(np.linalg.norm(xyz, axis=1), 0.1)
        dist = dist / rng[:, None]
    terms = weighted_sor_terms_fast(dist, alpha, delta, max_density_ratio)
    return terms.d <= terms.theta


@dataclass
class SorTerms:
    """The quantities of eqs. (4)-(9) per point (m unless noted): d (N,) weighted mean
    neighbour distance (6), mu (8), sigma (9), rho (N,) local density (points/m^3), theta (N,)
    threshold (7)."""

    d: np.ndarray
    mu: float
    sigma: float
    rho: np.ndarray
    theta: np.ndarray


def weighted_sor_terms(
    dist: np.ndarray, alpha: float = 1.0, delta: float = 1e-5, max_density_ratio: float = 1.0
) -> SorTerms:
    """Eqs. (4)-(9) of paper 000 from the (N, k) ascending neighbour distances (m), N >= 2."""
    d_avg = max(float(dist.mean()), 1e-12)  # eq. (5)
    w = np.exp(-dist / d_avg)  # eq. (4)
    d = (w * dist).sum(axis=1) / w.sum(axis=1)  # eq. (6)
    mu = float(d.mean())  # eq. (8)
    sigma = float(d.std(ddof=1)) + delta  # eq. (9)
    radius = np.maximum(dist[:, -1], 1e-9)
    rho = dist.shape[1] / (4.0 / 3.0 * np.pi * radius**3)
    ratio = np.minimum(rho.mean() / rho, max_density_ratio)
    theta = mu + alpha * sigma * (1.0 + ratio)  # eq. (7)
    return SorTerms(d, mu, sigma, rho, theta)


def weighted_sor_terms_fast(
    dist: np.ndarray, alpha: float = 1.0, delta: float = 1e-5, max_density_ratio: float = 1.0
) -> SorTerms:
    """``weighted_sor_terms`` in fused numba passes with a vectorised exp (~5x faster than
    numpy, 1.7x than libm's exp in the same pass; same values to rounding, same keep-masks:
    tests/test_sor.py)."""
    d, mu, sigma, rho, theta = weighted_sor_kernel_simd(
        np.ascontiguousarray(dist, dtype=np.float64),
        float(alpha),
        float(delta),
        float(max_density_ratio),
    )
    return SorTerms(d, mu, sigma, rho, theta)


def apply_sor(
    xyz: np.ndarray,
    cfg: SorConfig,
    nbh: Neighbourhoods | None = None,
    *,
    ring: np.ndarray | None = None,
) -> np.ndarray:
    """Keep-mask from the configured method; all True when ``cfg.enabled`` is False.
    nbh: the k-NN of ``xyz`` (``neighbourhoods(xyz, cfg.k)``) when the caller keeps it.
    ring: (N,) beam index (``scan.ring``), passed on to ``neighbourhoods`` when nbh is None."""
    if not cfg.enabled:
        return np.ones(len(xyz), dtype=bool)
    if nbh is None and len(xyz) > 2:
        nbh = neighbourhoods(_check_xyz(xyz), cfg.k, ring=ring)
    if (
        cfg.method == "weighted"
        and cfg.stats_stride
        and not cfg.range_adaptive
        and nbh is not None
        and not nbh.searched
        and len(xyz) >= max(cfg.stats_min_points, 3)
    ):
        _check_xyz(xyz)
        keep = weighted_sor_estimated(nbh, cfg)
        if keep is not None:
            return keep
    dist = None if nbh is None else nbh.dist
    if cfg.mode == "banded" and len(xyz) > 2:
        dist = knn_distances(_check_xyz(xyz), cfg.k) if dist is None else dist
        return banded_sor(xyz, dist, cfg)
    if cfg.method == "classic":
        return classic_sor(xyz, cfg.k, cfg.alpha, dist=dist)
    if cfg.method == "weighted":
        return weighted_sor(
            xyz,
            cfg.k,
            cfg.alpha,
            cfg.delta,
            range_adaptive=cfg.range_adaptive,
            max_density_ratio=cfg.max_density_ratio,
            dist=dist,
        )
    raise ConfigError(f"unknown SOR method '{cfg.method}'; valid: {', '.join(SOR_METHODS)}")


def range_bands(
    xyz: np.ndarray, edges: tuple[float, ...], min_points: int
) -> tuple[np.ndarray, int]:
    """(N,) band label of each point by its range (m) from the origin (the sensor) and the
    number of bands; bands below ``min_points`` points are merged into their inner
    neighbour (the innermost into the next one out), so every band holds >= min_points
    points unless the whole scan has fewer (then one band)."""
    r = np.sqrt(np.einsum("ij,ij->i", xyz, xyz))
    label = np.searchsorted(np.asarray(edges, dtype=np.float64), r, side="right")
    counts = np.bincount(label, minlength=len(edges) + 1)
    keep = [b for b in range(len(counts)) if counts[b]]
    merged = True
    while merged and len(keep) > 1:
        merged = False
        for j, b in enumerate(keep):
            if counts[b] < min_points:
                into = keep[j - 1] if j else keep[1]
                counts[into] += counts[b]
                counts[b] = 0
                label[label == b] = into
                keep.pop(j)
                merged = True
                break
    remap = np.zeros(len(counts), dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    return remap[label], len(keep)


def banded_sor(xyz: np.ndarray, dist: np.ndarray, cfg: SorConfig) -> np.ndarray:
    """Keep-mask of the configured method with its statistics taken per range band
    (``SorConfig.mode`` "banded"): eqs. (4)-(9) (or the classic mu + alpha sigma) within each
    band of ``range_bands``. dist: (N, k) ascending neighbour distances (m)."""
    label, n_bands = range_bands(xyz, cfg.band_edges, cfg.band_min_points)
    keep = np.ones(len(xyz), dtype=bool)
    for b in range(n_bands):
        rows = np.flatnonzero(label == b)
        if len(rows) <= 2:
            continue
        sub = dist[rows]
        if cfg.method == "classic":
            d = sub.mean(axis=1)
            keep[rows] = d <= d.mean() + cfg.alpha * d.std(ddof=1)
            continue
        if cfg.range_adaptive:
            sub = sub / np.maximum(np.linalg.norm(xyz[rows], axis=1), 0.1)[:, None]
        t = weighted_sor_terms_fast(sub, cfg.alpha, cfg.delta, cfg.max_density_ratio)
        keep[rows] = t.d <= t.theta
    return keep


def weighted_sor_estimated(nbh: Neighbourhoods, cfg: SorConfig) -> np.ndarray | None:
    """The weighted SOR keep-mask (eqs. (4)-(9)) with estimated statistics, for the
    not yet searched range-image neighbourhoods ``nbh``; None where it does not apply (the
    caller then runs the exact filter on the same ``nbh``).

    One point in ``cfg.stats_stride`` of the range-image order is searched in full first;
    eq. (7) on their statistics gives a keep radius (``safe_keep_radius``: a point whose
    k-th distance is below it is kept whatever its exact distances). Every other point
    stops its search as soon as its k-th distance found is below that radius (kept); the
    others are searched in full. The statistics are then the exact rows' sums plus, for the
    points that stopped, the mean of the sampled points of the same stratum (k-th distance
    below the radius) times their number; the exact rows are decided on them. If the radius
    is not safe under these statistics, the stopped rows are completed and the exact filter
    decides (None). The stopped rows of ``nbh.idx`` are completed when asked for."""
    from slam.preprocess.range_image import range_image_of

    xyz, k, ring = nbh._xyz, nbh._k, nbh._ring
    n = len(xyz)
    image = range_image_of(xyz, ring, k)
    if not image.beams:
        return None
    a, dr = cfg.alpha, cfg.max_density_ratio
    sample = image.order[:: cfg.stats_stride]  # input indices, spread over every ring
    job = np.zeros(n, dtype=np.int8)
    job[sample] = 1
    res = image.knn(k, complete=True, job=job)
    if not res.complete:
        return None
    # the radius from the sample's statistics without its largest d (a few isolated points
    # in the sample make its sigma 2x the scan's; a radius too small only costs time) and
    # half its mean density (its mean is the densest points')
    st = weighted_sor_terms_fast(res.dist[sample], a, cfg.delta, dr)
    d_s = np.sort(st.d)[: max(int(len(st.d) * (1.0 - STATS_TRIM)), 2)]
    sigma_s = float(d_s.std(ddof=1)) + cfg.delta
    radius = safe_keep_radius(float(d_s.mean()), sigma_s, 0.5 * float(st.rho.mean()), k, a, dr)
    job[:] = 2
    job[sample] = 0
    res = image.knn(k, complete=True, job=job, exit_below=radius, into=res)
    if not res.complete:
        return None
    exited = res.exited.copy()
    nbh._idx, nbh._dist = res.idx, res.dist
    nbh._image, nbh._res, nbh._inexact = image, res, exited
    stand_in = np.zeros(n, dtype=bool)
    stand_in[sample] = res.dist[sample, -1] <= radius
    for _ in range(STATS_ROUNDS):
        n_unknown = int(np.count_nonzero(exited))
        if n_unknown and not stand_in.any():
            return None
        d, mu, sigma, rho_avg, theta = stratified_sor_kernel(
            res.dist, ~exited, stand_in, n_unknown, a, cfg.delta, dr
        )
        safe = safe_keep_radius(mu, sigma, rho_avg, k, a, dr)
        # stopped rows the final statistics do not back (their k-th distance found, an
        # upper bound of the true one, above the safe radius): searched in full, once more
        unsafe = np.flatnonzero(exited & (res.dist[:, -1] > safe))
        if len(unsafe) == 0:
            return exited | (d <= theta)
        nbh.complete(unsafe)
        exited[unsafe] = False
    return None  # not settled: the exact filter
