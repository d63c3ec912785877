"""Per-point covariances of GICP, eq. (1) of paper 000, with the ring-aware supports.

Sigma = 1/(k-1) sum (p_t - mean)(p_t - mean)^T + lambda I over the k nearest neighbours.
A support whose neighbours all lie on one scan line cannot tell a surface's normal; in mode
"raw" it borrows the nearest points of the other scan lines (the "span", ``_span_scan_lines``),
in mode "shape" it is made isotropic (docs/paper000.md explains why).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from slam.errors import ConfigError
from slam.registration import kernels
from slam.registration.neighbours import KnnTree, _workers
from slam.registration.result import RegistrationError, _check_points

COVARIANCE_MODES = ("raw", "plane", "shape")


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


def _span_from_wide(
    xyz: np.ndarray,
    idx: np.ndarray,
    rows: np.ndarray,
    labels: np.ndarray,
    d: np.ndarray,
    j: np.ndarray,
    m: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``rows`` their wide k-NN (d, j) settles: (those with >= 2 points of other lines,
    their (n, 3, 3) covariances, the rows it cannot settle: fewer than m found and the set
    does not exhaust the span distance)."""
    k = idx.shape[1]
    found = np.isfinite(d)
    j = np.where(found, j, 0)
    other = found & (labels[j] != labels[idx[rows, :1]])
    take = other & (np.cumsum(other, axis=1) <= m)  # the m nearest points of other lines
    n_take = take.sum(axis=1)
    exact = (n_take >= m) | ~found[:, -1]
    fast = exact & (n_take >= 2)
    covs = _covariances_of(
        np.concatenate([xyz[idx[rows[fast]]], xyz[j[fast]]], axis=1),
        np.concatenate([np.ones((int(fast.sum()), k)), take[fast]], axis=1),
    )
    return rows[fast], covs, rows[~exact]


def _span_per_line(
    xyz: np.ndarray,
    query: np.ndarray,
    idx: np.ndarray,
    rows: np.ndarray,
    labels: np.ndarray,
    m: int,
    span_distance: float,
    threads: int,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``_span_from_wide`` for the rows it could not settle, by a KD-tree of the other lines'
    points, one per scan line: (the rows with >= 2 such points, their covariances) per line."""
    k = idx.shape[1]
    done, covs = [], []
    own = labels[idx[rows, 0]]
    for line in np.unique(own):
        sel = rows[own == line]
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
    return done, covs


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
    neighbours (one query on ``tree``); rows where that set may miss some query a KD-tree of
    the other lines' points, one per scan line (<= the number of beams); no per-point loop.
    """
    k = idx.shape[1]
    m = max(k // 2, 3)
    k_wide = min(4 * k, len(xyz))
    own = labels[idx[rows, 0]]
    d, j = _wide_neighbours(tree, query[rows], k_wide, own, labels, m, span_distance, threads)
    done, covs, slow = _span_from_wide(xyz, idx, rows, labels, d, j, m)
    more, more_covs = _span_per_line(xyz, query, idx, slow, labels, m, span_distance, threads)
    return np.concatenate([done, *more]), np.concatenate([covs, *more_covs])


def _neighbour_indices(
    xyz: np.ndarray,
    query: np.ndarray,
    k: int,
    tree: cKDTree | KnnTree | None,
    threads: int,
    neighbours: np.ndarray | None,
) -> tuple[np.ndarray, cKDTree | KnnTree | None]:
    """(the (M, k) indices into ``xyz`` of each query's k nearest points, the tree that
    answered, if any): ``neighbours`` when the caller has them, else one k-NN query."""
    if neighbours is not None:
        idx = np.asarray(neighbours, dtype=np.int64)
        if idx.shape != (len(query), k):
            raise RegistrationError(f"neighbours must be ({len(query)}, {k}), got {idx.shape}")
        return idx, tree
    tree = KnnTree(xyz) if tree is None else tree
    _, idx = tree.query(query, k=k, workers=_workers(len(query), threads))
    return idx.reshape(len(query), k), tree


def _sample_covariances(xyz: np.ndarray, idx: np.ndarray, reference: bool) -> np.ndarray:
    """(M, 3, 3) eq. (1) without lambda of the neighbour sets ``xyz[idx]`` (m^2); reference:
    numpy einsum instead of the compiled kernel (same numbers)."""
    if not reference:
        return kernels.neighbour_covariances(xyz, idx)
    nb = xyz[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    return np.einsum("nki,nkj->nij", centred, centred) / (idx.shape[1] - 1)


def _span_or_isotropic(
    cov: np.ndarray,
    single: np.ndarray,
    xyz: np.ndarray,
    query: np.ndarray,
    idx: np.ndarray,
    labels: np.ndarray,
    tree: cKDTree | KnnTree | None,
    span_distance: float,
    threads: int,
) -> None:
    """Mode "raw" on the one-line supports ``single``, in place: eq. (1) across the scan lines
    where they are within ``span_distance`` (m, 0 = off), else isotropic at the support's
    extent (largest eigenvalue): "somewhere along this scan line", no direction."""
    if span_distance > 0:
        spanned, spanned_cov = _span_scan_lines(
            xyz,
            query,
            idx,
            np.flatnonzero(single),
            labels,
            KnnTree(xyz) if tree is None else tree,
            span_distance,
            threads,
        )
        cov[spanned] = spanned_cov
        single = single.copy()
        single[spanned] = False
    cov[single] = np.eye(3) * np.linalg.eigvalsh(cov[single])[:, 2, None, None]


def _regularise(
    cov: np.ndarray,
    mode: str,
    single: np.ndarray | None,
    plane_epsilon: float,
    line_ratio: float,
) -> np.ndarray:
    """Mode "plane": eigenvalues (eps, 1, 1) (Segal et al.); "shape": (eps, 1, 1) for a
    surface, (eps, eps, 1) for a line (l2 < line_ratio * l1), (1, 1, 1) for a one-line
    (``single``) or degenerate support; "raw": unchanged. Dimensionless except "raw"."""
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
    return cov


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
    covariance is isotropic at the support's extent (largest eigenvalue). Why: see
    docs/paper000.md ("Supports on one scan line").

    mode "shape" regularises by the shape the support really has (dimensionless as well):
    with eigenvalues l1 >= l2 >= l3, a support with l2 >= line_ratio * l1 is a surface ->
    (eps, 1, 1) with the normal of the smallest eigenvalue; a line (l2 < line_ratio * l1) ->
    (eps, eps, 1) along the largest; a support whose neighbours all carry the same ``labels``
    value -> isotropic (1, 1, 1).

    ``tree``: a cKDTree of ``xyz`` or anything with its ``query`` (the local map). reference:
    eq. (1) by numpy einsum instead of the compiled kernel (same numbers). neighbours:
    the (M, k) indices into ``xyz`` of each query's k nearest points when the caller has
    them already (the same query is then not repeated).
    """
    xyz = _check_points(xyz, "points")
    query = xyz if query is None else _check_points(query, "query points")
    if len(xyz) < 3:
        raise RegistrationError(f"need at least 3 points for covariances, got {len(xyz)}")
    idx, tree = _neighbour_indices(xyz, query, min(k, len(xyz)), tree, threads, neighbours)
    cov = _sample_covariances(xyz, idx, reference)
    single = None
    if labels is not None:  # supports sampled by one scan line only
        lab = np.asarray(labels)[idx]
        single = np.all(lab == lab[:, :1], axis=1)
    if mode == "raw" and single is not None and single.any():
        _span_or_isotropic(
            cov, single, xyz, query, idx, np.asarray(labels), tree, span_distance, threads
        )
    cov = _regularise(cov, mode, single, plane_epsilon, line_ratio)
    cov[:, [0, 1, 2], [0, 1, 2]] += lambda_reg
    return cov


def add_beam_angle_noise(points: np.ndarray, covs: np.ndarray, sigma_rad: float) -> np.ndarray:
    """``covs`` (n, 3, 3, m^2) plus the beam's angular uncertainty at each point: (r sigma)^2
    across the ray from the sensor origin, 0 along it (r = |point|, m; sigma, rad). A far
    point's position is as uncertain as its beam is wide, so a far surface claims no more
    than the beam resolves (what eq. (1) of paper 000 leaves out; docs/paper000.md)."""
    if sigma_rad <= 0:
        return covs
    r2 = np.einsum("ij,ij->i", points, points)
    u = points / np.sqrt(np.maximum(r2, 1e-12))[:, None]
    across = np.eye(3) - u[:, :, None] * u[:, None, :]
    return covs + (sigma_rad**2 * r2)[:, None, None] * across
