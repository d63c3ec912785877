"""LeGO-LOAM's range-image ground marking and image-based segmentation (Shan and Englot
2018, section III-B; the baseline of paper 001, section 3.1.2).

The sweep is projected onto a range image: one row per beam (rows sorted by the beam's
elevation, bottom first), one column per azimuth step (``n_columns``, inferred from the
azimuth spacing of the points when 0). A cell keeps its nearest return.

Ground: between two vertically adjacent cells of the lower rows (beam elevation up to
``ground_max_elevation_deg``), the slope angle of the segment joining the two returns,
atan2(dz, sqrt(dx^2 + dy^2)), within ``ground_max_angle_deg`` of the sensor mount angle
marks both cells as ground.

Segmentation: a breadth-first search over the non-ground cells (4-neighbourhood, columns
wrap around) joins two neighbours when the angle beta between the beam and the line through
the two returns is large, beta = atan2(d2 sin(alpha), d1 - d2 cos(alpha)) > theta (d1 >= d2
their ranges, alpha the angular step between them: the column step horizontally, the
elevation difference of the two beams vertically). A cluster is kept if it has at least
``min_cluster_points`` cells, or at least ``min_line_points`` cells spanning at least
``min_cluster_rows`` rows (LeGO-LOAM: 30, 5, 3); the rest (foliage scatter, spurious
returns, small debris) are dropped as noise. The BFS is a numba kernel (one pass, explicit
queue); ``_label_reference`` states it with scipy's connected components (tested equal).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from slam.errors import ConfigError, InputError

LABEL_GROUND = -1  # ground cell
LABEL_NOISE = 0  # in a dropped (small) cluster
LABEL_UNPROJECTED = -2  # not in the range image (no usable ring)


@dataclass
class SegmentationConfig:
    """Range-image ground and segmentation settings (LeGO-LOAM defaults; angles in deg).

    n_columns: azimuth steps of the range image; 0 = inferred from the median azimuth
    spacing of the points within a beam (any sensor, 360-4096 columns).
    ground_max_angle_deg: slope between vertically adjacent returns below which both are
    ground (LeGO: 10). sensor_mount_angle_deg: sensor pitch (LeGO: 0).
    ground_max_elevation_deg: only beams at or below this elevation take part in ground
    marking (LeGO's groundScanInd: the 8 lowest of a VLP-16's beams, -15..-1 deg).
    segment_theta_deg: beta threshold (LeGO: 60). min_cluster_points / min_line_points /
    min_cluster_rows: cluster validity (LeGO: 30 / 5 / 3).
    """

    enabled: bool = True
    n_columns: int = 0
    ground_max_angle_deg: float = 10.0
    sensor_mount_angle_deg: float = 0.0
    ground_max_elevation_deg: float = 0.0
    segment_theta_deg: float = 60.0
    min_cluster_points: int = 30
    min_line_points: int = 5
    min_cluster_rows: int = 3
    wall_foot_gap: float = 0.05

    def __post_init__(self) -> None:
        if self.n_columns != 0 and not 16 <= self.n_columns <= 1 << 14:
            raise ConfigError(
                f"segmentation.n_columns must be 0 or 16..16384, got {self.n_columns}"
            )
        if not 0.0 < self.segment_theta_deg < 90.0:
            raise ConfigError("segmentation.segment_theta_deg must be in (0, 90) degrees")
        if not 0.0 < self.ground_max_angle_deg < 90.0:
            raise ConfigError("segmentation.ground_max_angle_deg must be in (0, 90) degrees")
        if min(self.min_cluster_points, self.min_line_points, self.min_cluster_rows) < 1:
            raise ConfigError("segmentation cluster sizes must be >= 1")


@dataclass
class Segmentation:
    """Per-point result (same order as the input points).

    ground: (N,) bool. label: (N,) int32, a cluster id >= 1 for kept segments, LABEL_GROUND,
    LABEL_NOISE (dropped cluster) or LABEL_UNPROJECTED. row/col: range-image cell of each
    point (row = beam rank by elevation). n_columns: image width used. row_elevation_deg:
    (rows,) elevation of each image row.
    """

    ground: np.ndarray
    label: np.ndarray
    row: np.ndarray
    col: np.ndarray
    n_columns: int
    row_elevation_deg: np.ndarray

    @property
    def segmented(self) -> np.ndarray:
        """(N,) bool: the points LeGO-LOAM keeps for features (ground + kept clusters)."""
        return self.ground | (self.label > 0)

    @property
    def n_clusters(self) -> int:
        return int(self.label.max(initial=0))


@njit(cache=True)
def _azimuth_steps(azimuth, ring, n_rings):
    """The steps > 1e-6 rad between consecutive azimuths within each ring (0..n_rings-1)."""
    counts = np.zeros(n_rings + 1, dtype=np.int64)
    for i in range(len(ring)):
        counts[ring[i] + 1] += 1
    for r in range(n_rings):
        counts[r + 1] += counts[r]
    fill = counts[:-1].copy()
    grouped = np.empty(len(ring))
    for i in range(len(ring)):
        grouped[fill[ring[i]]] = azimuth[i]
        fill[ring[i]] += 1
    steps = np.empty(len(ring))
    n = 0
    for r in range(n_rings):
        a = np.sort(grouped[counts[r] : counts[r + 1]])
        for i in range(1, len(a)):
            d = a[i] - a[i - 1]
            if d > 1e-6:
                steps[n] = d
                n += 1
    return steps[:n]


def infer_columns(azimuth: np.ndarray, ring: np.ndarray, *, reference: bool = False) -> int:
    """Range-image width from the median azimuth step between consecutive returns of a beam.
    ``reference``: the numpy statement (one lexsort) instead of the kernel (same steps)."""
    if reference or len(ring) == 0 or ring.min() < 0:
        order = np.lexsort((azimuth, ring))
        a, r = azimuth[order], ring[order]
        step = np.diff(a)
        step = step[(r[1:] == r[:-1]) & (step > 1e-6)]
    else:
        ring = np.asarray(ring, dtype=np.int64)
        step = _azimuth_steps(np.asarray(azimuth, dtype=np.float64), ring, int(ring.max()) + 1)
    if step.size < 10:
        return 1800
    return int(np.clip(np.rint(2 * np.pi / np.median(step)), 360, 4096))


@njit(cache=True)
def _beam_medians(elev, inv, n_beams):
    """Median of ``elev`` over the points of each beam 0..n_beams-1 (``inv`` (N,) beam of
    each point): a counting sort by beam, then a sort within each beam."""
    counts = np.zeros(n_beams, dtype=np.int64)
    for i in range(len(inv)):
        counts[inv[i]] += 1
    start = np.zeros(n_beams + 1, dtype=np.int64)
    for b in range(n_beams):
        start[b + 1] = start[b] + counts[b]
    fill = start[:-1].copy()
    grouped = np.empty(len(inv))
    for i in range(len(inv)):
        grouped[fill[inv[i]]] = elev[i]
        fill[inv[i]] += 1
    med = np.empty(n_beams)
    for b in range(n_beams):
        seg = np.sort(grouped[start[b] : start[b + 1]])
        c = counts[b]
        med[b] = 0.5 * (seg[(c - 1) // 2] + seg[c // 2])
    return med


@njit(cache=True)
def _cell_owner(cell, rng, n_cells):
    """Index of the nearest return of each cell (-1: empty); ties: the first point."""
    owner = np.full(n_cells, -1, dtype=np.int64)
    best = np.full(n_cells, np.inf)
    for i in range(len(cell)):
        c = cell[i]
        if rng[i] < best[c]:
            best[c] = rng[i]
            owner[c] = i
    return owner


def project(
    xyz: np.ndarray, ring: np.ndarray, n_columns: int = 0, *, reference: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """Range-image cell of each point: (row, col, owner (rows, cols) index of the point
    held by each cell or -1, n_columns, row elevation in deg). A cell holds its nearest
    return; row = rank of the point's beam by median elevation (bottom first).
    ``reference``: the numpy statement (sorts) instead of the numba kernels (tested equal)."""
    rng = np.linalg.norm(xyz, axis=1)
    elev = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    beams, inv, counts = np.unique(ring, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    if reference:
        # median elevation of each beam: one sort by (beam, elevation), the middle of each run
        srt = elev[np.lexsort((elev, inv))]
        start = np.r_[0, np.cumsum(counts)[:-1]]
        med = 0.5 * (srt[start + (counts - 1) // 2] + srt[start + counts // 2])
    else:
        med = _beam_medians(elev, inv.astype(np.int64), len(beams))
    rank = np.empty(len(beams), dtype=np.int64)
    rank[np.argsort(med, kind="stable")] = np.arange(len(beams))
    row = rank[inv]
    az = np.arctan2(xyz[:, 1], xyz[:, 0])
    if n_columns <= 0:
        n_columns = infer_columns(az, row)
    col = (np.floor((az + np.pi) / (2 * np.pi) * n_columns).astype(np.int64)) % n_columns
    cell = row * n_columns + col
    if reference:
        owner = np.full(len(beams) * n_columns, -1, dtype=np.int64)
        order = np.lexsort((rng, cell))  # by cell, nearest first
        first = np.r_[True, cell[order][1:] != cell[order][:-1]]
        owner[cell[order][first]] = order[first]
    else:
        owner = _cell_owner(cell, rng, len(beams) * n_columns)
    return row, col, owner.reshape(len(beams), n_columns), n_columns, np.sort(med)


def mark_ground(
    xyz: np.ndarray, owner: np.ndarray, row_elev: np.ndarray, cfg: SegmentationConfig
) -> np.ndarray:
    """(rows, cols) bool: LeGO-LOAM's ground cells (slope between vertical neighbours)."""
    ground = np.zeros(owner.shape, dtype=bool)
    # pairs (i, i+1) of rows both at or below the elevation limit (LeGO: i < groundScanInd)
    top = int(np.searchsorted(row_elev, cfg.ground_max_elevation_deg, side="right"))
    if top < 2:
        return ground
    lo, hi = owner[: top - 1], owner[1:top]
    both = (lo >= 0) & (hi >= 0)
    d = xyz[hi[both]] - xyz[lo[both]]
    ang = np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))
    flat = np.abs(ang - cfg.sensor_mount_angle_deg) <= cfg.ground_max_angle_deg
    sel_lo = np.zeros(lo.shape, dtype=bool)
    sel_lo[both] = flat
    ground[: top - 1] |= sel_lo
    ground[1:top] |= sel_lo
    if cfg.wall_foot_gap > 0:
        # the foot of a wall: the return of the beam above lies (nearly) straight above this
        # one; a long flat stretch to the ground ring below made it look like ground
        lo, hi = owner[:top], owner[1 : top + 1]
        both = (lo >= 0) & (hi >= 0) & ground[:top]
        a, b = xyz[lo[both]], xyz[hi[both]]
        rho_a = np.hypot(a[:, 0], a[:, 1])
        gap = np.abs(np.hypot(b[:, 0], b[:, 1]) - rho_a)  # horizontal range step
        foot = (gap < cfg.wall_foot_gap * (1.0 + rho_a / 10.0)) & (np.abs(b[:, 2] - a[:, 2]) > gap)
        sel = np.zeros(lo.shape, dtype=bool)
        sel[both] = foot
        ground[:top] &= ~sel
    return ground


@njit(cache=True)
def _label_kernel(rng_img, valid, alpha_row, alpha_col, tan_theta, min_pts, min_line, min_rows):
    """BFS labelling of the range image (see module doc). rng_img (R, C) ranges, valid (R, C)
    cells to segment, alpha_row (R-1,) elevation step between rows i and i+1 (rad),
    alpha_col column step (rad). Returns (R, C) int32: >= 1 kept cluster, 0 dropped/none."""
    R, C = rng_img.shape
    labels = np.zeros((R, C), dtype=np.int32)
    seen = np.zeros((R, C), dtype=np.bool_)
    qr = np.empty(R * C, dtype=np.int64)
    qc = np.empty(R * C, dtype=np.int64)
    row_hit = np.zeros(R, dtype=np.bool_)
    sin_c, cos_c = np.sin(alpha_col), np.cos(alpha_col)
    next_label = 1
    for r0 in range(R):
        for c0 in range(C):
            if not valid[r0, c0] or seen[r0, c0]:
                continue
            head, tail = 0, 1
            qr[0], qc[0] = r0, c0
            seen[r0, c0] = True
            while head < tail:
                r, c = qr[head], qc[head]
                head += 1
                d_here = rng_img[r, c]
                for k in range(4):
                    if k == 0:
                        nr, nc, s, co = r - 1, c, 0.0, 0.0
                        if nr < 0:
                            continue
                        s, co = np.sin(alpha_row[nr]), np.cos(alpha_row[nr])
                    elif k == 1:
                        nr, nc = r + 1, c
                        if nr >= R:
                            continue
                        s, co = np.sin(alpha_row[r]), np.cos(alpha_row[r])
                    elif k == 2:
                        nr, nc, s, co = r, (c - 1) % C, sin_c, cos_c
                    else:
                        nr, nc, s, co = r, (c + 1) % C, sin_c, cos_c
                    if not valid[nr, nc] or seen[nr, nc]:
                        continue
                    d_nb = rng_img[nr, nc]
                    d1 = max(d_here, d_nb)
                    d2 = min(d_here, d_nb)
                    # beta > theta  <=>  d2 sin(a) > tan(theta) (d1 - d2 cos(a))
                    if d2 * s > tan_theta * (d1 - d2 * co):
                        seen[nr, nc] = True
                        qr[tail], qc[tail] = nr, nc
                        tail += 1
            n_rows = 0
            for i in range(tail):
                row_hit[qr[i]] = True
            for i in range(R):
                if row_hit[i]:
                    n_rows += 1
                    row_hit[i] = False
            if tail >= min_pts or (tail >= min_line and n_rows >= min_rows):
                for i in range(tail):
                    labels[qr[i], qc[i]] = next_label
                next_label += 1
    return labels


def _label_reference(rng_img, valid, alpha_row, alpha_col, tan_theta, min_pts, min_line, min_rows):
    """The numpy/scipy statement of ``_label_kernel`` (the tested reference): the clusters
    are the connected components of the graph whose edges join neighbouring valid cells
    passing the beta test, numbered by their first cell in row-major order."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    R, C = rng_img.shape
    idx = np.arange(R * C).reshape(R, C)
    pairs = []
    # vertical pairs (r, r+1) with the elevation step of row r; horizontal (c, c+1) wrapping
    for a, b, alpha in (
        (idx[:-1], idx[1:], np.broadcast_to(alpha_row[: R - 1, None], (R - 1, C))),
        (idx, np.roll(idx, -1, axis=1), np.full((R, C), alpha_col)),
    ):
        a, b, alpha = a.ravel(), b.ravel(), alpha.ravel()
        ra, rb = rng_img.ravel()[a], rng_img.ravel()[b]
        d1, d2 = np.maximum(ra, rb), np.minimum(ra, rb)
        ok = valid.ravel()[a] & valid.ravel()[b]
        ok &= d2 * np.sin(alpha) > tan_theta * (d1 - d2 * np.cos(alpha))
        pairs.append((a[ok], b[ok]))
    i = np.concatenate([p[0] for p in pairs])
    j = np.concatenate([p[1] for p in pairs])
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(R * C, R * C))
    _, comp = connected_components(graph, directed=False)
    v = np.flatnonzero(valid.ravel())
    n_comp = int(comp.max()) + 1
    size = np.bincount(comp[v], minlength=n_comp)
    rows_of = np.unique(comp[v] * R + v // C) // R  # one entry per (component, row)
    n_rows = np.bincount(rows_of, minlength=n_comp)
    first = np.full(n_comp, R * C)
    np.minimum.at(first, comp[v], v)
    keep = (size >= min_pts) | ((size >= min_line) & (n_rows >= min_rows))
    kept = np.flatnonzero(keep)
    new_id = np.zeros(n_comp, dtype=np.int32)
    new_id[kept[np.argsort(first[kept])]] = np.arange(1, len(kept) + 1)
    labels = np.zeros(R * C, dtype=np.int32)
    labels[v] = new_id[comp[v]]
    return labels.reshape(R, C)


def _checked_inputs(
    xyz: np.ndarray, ring: np.ndarray | None, ground: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """(xyz, ring) as arrays; InputError for a wrong shape or a missing ring."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InputError(f"points must be an (N, 3) array, got shape {xyz.shape}")
    n = len(xyz)
    if ring is None:
        raise InputError("range-image segmentation needs the beam (ring) of every point")
    ring = np.asarray(ring)
    if ring.shape != (n,):
        raise InputError(f"ring must have shape ({n},), got {ring.shape}")
    if ground is not None and np.shape(ground) != (n,):
        raise InputError(f"ground mask must have shape ({n},), got {np.shape(ground)}")
    return xyz, ring


def _ground_image(
    sub: np.ndarray,
    owner: np.ndarray,
    row_elev: np.ndarray,
    ground_sub: np.ndarray | None,
    cfg: SegmentationConfig,
) -> np.ndarray:
    """(rows, cols) bool ground cells: the slope test, or the given per-point mask read at
    each cell's owner point."""
    if ground_sub is None:
        return mark_ground(sub, owner, row_elev, cfg)
    ground_img = np.zeros(owner.shape, dtype=bool)
    held = owner >= 0
    ground_img[held] = ground_sub[owner[held]]
    return ground_img


def _cluster_labels(
    sub: np.ndarray,
    owner: np.ndarray,
    valid: np.ndarray,
    row_elev: np.ndarray,
    n_cols: int,
    cfg: SegmentationConfig,
) -> np.ndarray:
    """(rows, cols) int32 cluster label of each valid cell (LeGO-LOAM's angle criterion on the
    range image, m; 0 = dropped); every valid cell is 1 when segmentation is disabled."""
    if not cfg.enabled:
        return valid.astype(np.int32)
    rng_img = np.zeros(owner.shape)
    has = owner >= 0
    rng_img[has] = np.linalg.norm(sub[owner[has]], axis=1)
    alpha_row = np.radians(np.maximum(np.diff(row_elev), 1e-3))
    if len(alpha_row) == 0:
        alpha_row = np.zeros(1)
    return _label_kernel(
        rng_img,
        valid,
        alpha_row,
        2 * np.pi / n_cols,
        np.tan(np.radians(cfg.segment_theta_deg)),
        cfg.min_cluster_points,
        cfg.min_line_points,
        cfg.min_cluster_rows,
    )


def segment(
    xyz: np.ndarray,
    ring: np.ndarray | None,
    cfg: SegmentationConfig | None = None,
    *,
    ground: np.ndarray | None = None,
) -> Segmentation:
    """Ground marking and segmentation of one sweep (LeGO-LOAM); ``ring`` (N,) beam index
    (negative = unusable). ``ground``: (N,) bool ground mask from elsewhere (e.g. RANSAC,
    LeGO-LOAM-LPB) used instead of the slope test. With ``cfg.enabled`` False no cluster is
    dropped (every non-ground point gets label 1). Raises InputError without a ring."""
    cfg = cfg or SegmentationConfig()
    xyz, ring = _checked_inputs(xyz, ring, ground)
    n = len(xyz)
    label = np.full(n, LABEL_UNPROJECTED, dtype=np.int32)
    ground_pts = np.zeros(n, dtype=bool)
    use = np.flatnonzero(ring >= 0)
    if use.size == 0:
        z = np.zeros(n, dtype=np.int64)
        return Segmentation(ground_pts, label, z, z, max(cfg.n_columns, 1), np.zeros(0))
    sub = xyz[use]
    g = None if ground is None else np.asarray(ground, dtype=bool)[use]
    row_s, col_s, owner, n_cols, row_elev = project(sub, ring[use], cfg.n_columns)
    ground_img = _ground_image(sub, owner, row_elev, g, cfg)
    valid = (owner >= 0) & ~ground_img
    labels = _cluster_labels(sub, owner, valid, row_elev, n_cols, cfg)
    # every point takes its cell's label (a point that lost the cell to a nearer return of
    # the same beam and azimuth step lies on the same surface or just behind it)
    lab_sub = np.where(ground_img, LABEL_GROUND, labels)[row_s, col_s].astype(np.int32)
    if g is not None:  # the given mask decides each point, not its cell's owner
        lab_sub = np.where(g, LABEL_GROUND, np.where(lab_sub == LABEL_GROUND, 1, lab_sub))
    label[use] = lab_sub
    ground_pts[use] = lab_sub == LABEL_GROUND
    row = np.zeros(n, dtype=np.int64)
    col = np.zeros(n, dtype=np.int64)
    row[use], col[use] = row_s, col_s
    return Segmentation(ground_pts, label, row, col, n_cols, row_elev)
