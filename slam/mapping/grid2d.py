"""Probabilistic 2D occupancy grids (paper 003, DPCR-SLAM: submaps, regional maps, the
global map) and the regional division of the workspace (eqs. (3)-(5)).

A grid stores log-odds as int16 (the paper's ``unit`` = 2 bytes per cell) in a dense
array that grows in blocks as scans land outside it. A scan updates the cells of its end
points (hit) and the cells its rays cross before them (miss). Cell (r, c) covers world
``x in origin_x + [c, c+1) * res``, ``y in origin_y + [r, r+1) * res``.

Beside the log-odds a grid keeps, sparsely, the mean position of the hit points in each
hit cell (:class:`HitMeans`): ``obstacle_points()`` gives obstacle cells at their hits'
mean instead of their centre, so that lines fitted to them are not tilted by the 5 cm
quantisation (a wall two cells thick, worn unevenly by grazing rays, tilts a line fitted
to cell centres by 0.1-0.3 deg).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import ConfigError

LOG_ODDS_SCALE = 100  # int16 log-odds units per nat


@dataclass
class GridConfig:
    """resolution (m per cell, the paper's w_g = 5 cm); hit/miss: log-odds added for an end
    point / a crossed cell (nats); clamp: |log-odds| bound (nats); occupied: log-odds above
    which a cell is an obstacle (nats); block (cells): growth step of the dense array;
    subcell: keep the mean hit position of every hit cell (``obstacle_points``)."""

    resolution: float = 0.05
    hit: float = 0.85
    miss: float = -0.4
    clamp: float = 3.5
    occupied: float = 0.6
    block: int = 256
    subcell: bool = True

    def __post_init__(self) -> None:
        if not self.resolution > 0:
            raise ConfigError(f"grid resolution must be > 0, got {self.resolution}")
        if not (self.hit > 0 > self.miss):
            raise ConfigError("grid hit must be > 0 and miss < 0 (log-odds)")


def ray_cells(origin: np.ndarray, ends: np.ndarray, res: float) -> np.ndarray:
    """World points sampled every cell along each ray from ``origin`` (2,) to each end point
    (N, 2), end excluded: the cells a ray crosses before its hit (a diagonal step may skip
    a corner cell). (M, 2)."""
    d = ends - origin
    length = np.linalg.norm(d, axis=1)
    steps = np.maximum((length / res).astype(np.int64), 0)
    if steps.sum() == 0:
        return np.zeros((0, 2))
    ray = np.repeat(np.arange(len(ends)), steps)
    first = np.cumsum(steps) - steps
    k = np.arange(steps.sum()) - np.repeat(first, steps)
    # stop one cell short of the end point, so that a hit is never cleared by its own ray
    frac = k / np.maximum(steps[ray], 1) * np.maximum(1.0 - res / np.maximum(length[ray], res), 0)
    return origin + d[ray] * frac[:, None]


_CELL_OFFSET = 1 << 21  # world cell indices +- 2^21 (+- 105 km at 5 cm) fit a key


class HitMeans:
    """Sparse per-cell sums of hit points: for every world cell (floor(xy / res)) that was
    hit, the sum of the hits' offsets inside the cell (cell units, float32) and their
    count. Removing a scan (weight -1) subtracts it exactly; cells whose count drops to
    zero are dropped. Keys are world cells, so growing the grid does not move them."""

    def __init__(self, resolution: float):
        self.resolution = resolution
        self.keys = np.zeros(0, dtype=np.int64)  # sorted
        self.sums = np.zeros((0, 2), dtype=np.float32)
        self.count = np.zeros(0, dtype=np.float32)

    @property
    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.sums.nbytes + self.count.nbytes)

    def __len__(self) -> int:
        return len(self.keys)

    @staticmethod
    def encode(cells: np.ndarray) -> np.ndarray:
        """int64 keys of world cells (N, 2) (ix, iy)."""
        c = cells.astype(np.int64) + _CELL_OFFSET
        return (c[:, 0] << 22) | c[:, 1]

    def add(self, xy: np.ndarray, weight: float | np.ndarray = 1.0) -> None:
        """Add (weight > 0) or remove (weight < 0) the hit points ``xy`` (N, 2, world m);
        an array of weights (N,) adds each point as that many hits (fusing grids)."""
        if len(xy) == 0:
            return
        f = xy / self.resolution
        cell = np.floor(f)
        off = f - cell
        keys, inv = np.unique(self.encode(cell), return_inverse=True)
        w = np.broadcast_to(np.asarray(weight, dtype=np.float64), (len(xy),))
        n = np.bincount(inv, weights=w, minlength=len(keys))
        sx = np.bincount(inv, weights=w * off[:, 0], minlength=len(keys))
        sy = np.bincount(inv, weights=w * off[:, 1], minlength=len(keys))
        pos = np.searchsorted(self.keys, keys)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == keys[found]
        at = pos[found]
        self.count[at] += n[found].astype(np.float32)
        self.sums[at, 0] += sx[found].astype(np.float32)
        self.sums[at, 1] += sy[found].astype(np.float32)
        new = ~found & (n > 0)
        if new.any():
            self.keys = np.insert(self.keys, pos[new], keys[new])
            self.count = np.insert(self.count, pos[new], n[new].astype(np.float32))
            self.sums = np.insert(
                self.sums, pos[new], np.column_stack([sx[new], sy[new]]).astype(np.float32), 0
            )
        if (n < 0).any():
            keep = self.count > 0.5
            if not keep.all():
                self.keys, self.sums, self.count = (
                    self.keys[keep],
                    self.sums[keep],
                    self.count[keep],
                )

    def lookup(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean hit positions (N, 2, world m) of world cells (N, 2) and their hit counts
        (N,); cells never hit give their centre and count 0."""
        keys = self.encode(cells)
        pos = np.minimum(np.searchsorted(self.keys, keys), max(len(self.keys) - 1, 0))
        out = (cells + 0.5) * self.resolution
        count = np.zeros(len(cells))
        if len(self.keys) == 0:
            return out, count
        hit = self.keys[pos] == keys
        n = self.count[pos[hit]].astype(np.float64)
        out[hit] = (cells[hit] + self.sums[pos[hit]] / n[:, None]) * self.resolution
        count[hit] = n
        return out, count

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean hit positions (M, 2, world m) of every hit cell and their counts (M,)."""
        c = self.keys
        cells = np.column_stack([(c >> 22) - _CELL_OFFSET, (c & ((1 << 22) - 1)) - _CELL_OFFSET])
        n = self.count.astype(np.float64)
        return (cells + self.sums / n[:, None]) * self.resolution, n


class OccupancyGrid:
    """A growing dense log-odds grid. ``add_scan(points_world, origin)`` fuses one scan;
    ``obstacles()`` gives the centres of occupied cells, ``obstacle_points()`` their mean
    hit positions; ``add_grid`` fuses another grid."""

    def __init__(self, cfg: GridConfig | None = None):
        self.cfg = cfg or GridConfig()
        self.data = np.zeros((0, 0), dtype=np.int16)
        self.origin = np.zeros(2)  # world position of cell (0, 0)'s corner
        self.hits = HitMeans(self.cfg.resolution) if self.cfg.subcell else None

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape  # type: ignore[return-value]

    @property
    def nbytes(self) -> int:
        """Storage of the cells (bytes): the log-odds and the sparse hit means."""
        return int(self.data.nbytes) + (0 if self.hits is None else self.hits.nbytes)

    def cells_of(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) int64 (row, col) of world points (may lie outside the array)."""
        return np.floor((xy - self.origin) / self.cfg.resolution).astype(np.int64)[:, ::-1]

    def centres(self, rc: np.ndarray) -> np.ndarray:
        """World centres (N, 2) of cells (row, col)."""
        return self.origin + (rc[:, ::-1] + 0.5) * self.cfg.resolution

    def _ensure(self, xy: np.ndarray) -> None:
        """Grow the array (in blocks) so that every point of ``xy`` falls inside it."""
        if len(xy) == 0:
            return
        res, block = self.cfg.resolution, self.cfg.block
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        if self.data.size == 0:
            self.origin = np.floor(lo / res / block) * block * res
            rows = int(np.ceil((hi[1] - self.origin[1]) / res / block) + 1) * block
            cols = int(np.ceil((hi[0] - self.origin[0]) / res / block) + 1) * block
            self.data = np.zeros((rows, cols), dtype=np.int16)
            return
        rows, cols = self.data.shape
        top = self.origin + np.array([cols, rows]) * res
        pad_lo = np.maximum(np.ceil((self.origin - lo) / res / block), 0).astype(int) * block
        pad_hi = np.maximum(np.ceil((hi - top) / res / block) + 1, 0).astype(int) * block
        pad_hi[(hi < top)] = 0
        if pad_lo.any() or pad_hi.any():
            self.data = np.pad(self.data, ((pad_lo[1], pad_hi[1]), (pad_lo[0], pad_hi[0])))
            self.origin = self.origin - pad_lo * res

    # ------------------------------------------------------------------ updates
    def _add(self, rc: np.ndarray, value: float) -> None:
        if len(rc) == 0:
            return
        flat = np.ravel_multi_index((rc[:, 0], rc[:, 1]), self.data.shape)
        flat = np.unique(flat)  # one update per cell and scan
        lim = int(self.cfg.clamp * LOG_ODDS_SCALE)
        view = self.data.reshape(-1)
        new = view[flat].astype(np.int32) + int(round(value * LOG_ODDS_SCALE))
        view[flat] = np.clip(new, -lim, lim).astype(np.int16)

    def add_scan(
        self,
        points: np.ndarray,
        origin: np.ndarray,
        weight: float = 1.0,
        free_space: bool = True,
    ) -> None:
        """Fuse one scan: ``points`` (N, 2) end points and ``origin`` (2,) sensor position,
        world frame. ``weight`` -1 removes a scan fused before (a sliding submap);
        ``free_space`` False updates the hit cells only (no ray tracing)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        origin = np.asarray(origin, dtype=np.float64)[:2]
        if free_space:
            free = ray_cells(origin, points, self.cfg.resolution)
        else:
            free = np.zeros((0, 2))
        self._ensure(np.vstack([points, origin[None]]))
        hit_rc = self.cells_of(points)
        free_rc = self.cells_of(free)
        # a cell holding an end point of this scan is not also cleared by it
        if len(free_rc) and len(hit_rc):
            shape = self.data.shape
            hit_flat = np.ravel_multi_index((hit_rc[:, 0], hit_rc[:, 1]), shape)
            free_flat = np.ravel_multi_index((free_rc[:, 0], free_rc[:, 1]), shape)
            free_rc = free_rc[~np.isin(free_flat, hit_flat)]
        self._add(free_rc, self.cfg.miss * weight)
        self._add(hit_rc, self.cfg.hit * weight)
        if self.hits is not None:
            self.hits.add(points, weight)

    def add_grid(self, other: OccupancyGrid, T: np.ndarray | None = None) -> None:
        """Fuse the log-odds of ``other`` (moved by the 2D pose ``T`` = (x, y, theta) when
        given): every known cell of ``other`` adds its log-odds at its moved centre."""
        rc = np.argwhere(other.data != 0)
        if len(rc) == 0:
            return
        xy = other.centres(rc)
        if T is not None:
            xy = transform2d(T, xy)
        self._ensure(xy)
        values = other.data[rc[:, 0], rc[:, 1]].astype(np.int32)
        dst = self.cells_of(xy)
        flat = np.ravel_multi_index((dst[:, 0], dst[:, 1]), self.data.shape)
        acc = np.zeros(self.data.size, dtype=np.int32)
        np.add.at(acc, flat, values)
        touched = np.unique(flat)
        lim = int(self.cfg.clamp * LOG_ODDS_SCALE)
        view = self.data.reshape(-1)
        view[touched] = np.clip(view[touched] + acc[touched], -lim, lim).astype(np.int16)
        if self.hits is not None and other.hits is not None and len(other.hits):
            pts, n = other.hits.points()
            self.hits.add(pts if T is None else transform2d(T, pts), n)

    # ------------------------------------------------------------------ queries
    def occupied_mask(self) -> np.ndarray:
        return self.data > int(self.cfg.occupied * LOG_ODDS_SCALE)

    def obstacles(self) -> np.ndarray:
        """World centres (M, 2) of the obstacle cells (log-odds above ``occupied``)."""
        return self.centres(np.argwhere(self.occupied_mask()))

    def obstacle_hits(self) -> tuple[np.ndarray, np.ndarray]:
        """The obstacle cells (M, 2, world m) at the mean position of their hit points
        (sub-cell), in the order of :meth:`obstacles`, and their hit counts (M,): the
        weights of a line fit that equals the fit to every hit in those cells. Cells
        without recorded hits (or a grid without ``subcell``) give their centre, weight 1."""
        rc = np.argwhere(self.occupied_mask())
        if self.hits is None:
            return self.centres(rc), np.ones(len(rc))
        corner = np.round(self.origin / self.cfg.resolution).astype(np.int64)
        pts, count = self.hits.lookup(rc[:, ::-1] + corner)
        return pts, np.maximum(count, 1.0)

    def obstacle_points(self) -> np.ndarray:
        """The obstacle cells (M, 2, world m) at their hits' mean (see obstacle_hits)."""
        return self.obstacle_hits()[0]

    def obstacle_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """World centres (M, 2) of the obstacle cells and their log-odds (nats)."""
        rc = np.argwhere(self.occupied_mask())
        return self.centres(rc), self.data[rc[:, 0], rc[:, 1]] / LOG_ODDS_SCALE

    def probability(self) -> np.ndarray:
        """Occupancy probability per cell (0.5 = unknown)."""
        return 1.0 / (1.0 + np.exp(-self.data.astype(np.float64) / LOG_ODDS_SCALE))


def transform2d(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points ``xy`` (N, 2) moved by the 2D pose T = (x, y, theta)."""
    c, s = np.cos(T[2]), np.sin(T[2])
    return xy @ np.array([[c, s], [-s, c]]) + T[:2]


def compose2d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose a * b, poses (x, y, theta)."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2])])


def inverse2d(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap(-a[2])])


def wrap(angle: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def pose2_to_matrix(p: np.ndarray) -> np.ndarray:
    """4x4 T of the planar pose (x, y, theta)."""
    c, s = np.cos(p[2]), np.sin(p[2])
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = p[:2]
    return T


def matrix_to_pose2(T: np.ndarray) -> np.ndarray:
    """(x, y, theta) of a 4x4 T (its projection on the plane)."""
    return np.array([T[0, 3], T[1, 3], np.arctan2(T[1, 0], T[0, 0])])


def predict2d(
    pose: np.ndarray,
    motion: np.ndarray,
    odom_prev: np.ndarray | None,
    odom: np.ndarray | None,
) -> np.ndarray:
    """The next planar pose: ``pose`` moved by the wheel odometry since the last scan
    (odom_prev^-1 o odom, in the robot's frame) when both readings exist, else by the last
    frame-to-frame ``motion`` (constant velocity)."""
    if odom_prev is not None and odom is not None:
        return compose2d(pose, compose2d(inverse2d(odom_prev), odom))
    return compose2d(pose, motion)


@dataclass
class StaleWheels:
    """The wheel readings' stale parts: xy_new the last reading whose position was new and
    since_xy the motion the scans registered since its scan (SE(2), that scan's frame;
    None: the position has not repeated since); heading_new (rad) and since_heading
    (rad) the same for the heading."""

    xy_new: np.ndarray | None = None
    since_xy: np.ndarray | None = None
    heading_new: float | None = None
    since_heading: float | None = None

    def update(self, odom: np.ndarray, stale_xy: bool, stale_heading: bool) -> None:
        """After a reading: a part that is new becomes the anchor, its registered motion
        cleared."""
        if not stale_xy:
            self.xy_new, self.since_xy = odom, None
        if not stale_heading:
            self.heading_new, self.since_heading = float(odom[2]), None

    def registered(self, step: np.ndarray, stale_xy: bool, stale_heading: bool) -> None:
        """The scans' motion of a scan (SE(2), the last scan's frame) added to the stale
        parts' registered motion."""
        if stale_xy:
            self.since_xy = step if self.since_xy is None else compose2d(self.since_xy, step)
        if stale_heading:
            self.since_heading = float(step[2]) + (self.since_heading or 0.0)


def stale_parts(odom_prev: np.ndarray | None, odom: np.ndarray | None) -> tuple[bool, bool]:
    """(position, heading) of the wheel reading ``odom`` repeated exactly from the last one:
    that part did not update, so it says nothing of the motion (MIT-CSAIL's odometry stalls
    for 3 - 4 scans at 5 Hz, the position alone or with the heading, while the robot
    moves; a robot at rest repeats both, which changes nothing here)."""
    if odom_prev is None or odom is None:
        return False, False
    return bool(np.array_equal(odom_prev[:2], odom[:2])), bool(odom_prev[2] == odom[2])


def wheel_step(
    odom_prev: np.ndarray,
    odom: np.ndarray,
    motion: np.ndarray,
    stale: StaleWheels,
    stall_m: float,
    stall_rad: float,
) -> tuple[np.ndarray, bool, bool]:
    """The wheel odometry's motion (x, y m, theta rad; the last scan's frame) from the
    last scan (reading ``odom_prev``) to this one (``odom``), and whether its position /
    heading were taken as a stall's catch-up. A part of the reading that repeated exactly
    on the scans before (``stale``: the last reading where it was new and the motion the
    scans registered since) is either

    - a stall's catch-up: the wheels' motion since that reading less what the scans
      registered meanwhile (MIT-CSAIL's odometry stalls for 2 - 4 scans at 5 Hz, then
      reports up to 0.95 m / 86 deg in one 0.2 s step: taken as one step, the stall's
      motion is counted twice), or
    - the robot at rest in that part (in place, or turning in place): the plain step
      odom_prev^-1 o odom.

    It is a catch-up when the plain step departs from the robot's last motion ``motion``
    (the constant-velocity step) by more than ``stall_m`` (m) / ``stall_rad`` and the
    catch-up lies closer to it: a robot's speed changes little between two scans."""
    plain = compose2d(inverse2d(odom_prev), odom)
    step = plain.copy()
    caught_xy = caught_heading = False
    if stale.xy_new is not None and stale.since_xy is not None:
        t = compose2d(inverse2d(stale.since_xy), compose2d(inverse2d(stale.xy_new), odom))[:2]
        off = float(np.hypot(*(plain[:2] - motion[:2])))
        if off > stall_m and float(np.hypot(*(t - motion[:2]))) < off:
            step[:2], caught_xy = t, True
    if stale.heading_new is not None and stale.since_heading is not None:
        r = float(wrap(float(odom[2]) - stale.heading_new - stale.since_heading))
        off = abs(float(wrap(plain[2] - motion[2])))
        if off > stall_rad and abs(float(wrap(r - motion[2]))) < off:
            step[2], caught_heading = r, True
    return step, caught_xy, caught_heading


def planar_information(relative: np.ndarray) -> np.ndarray:
    """6x6 information (rotation first) of a planar motion: 2 cm + 2 % of the distance
    and 0.5 deg + 2 % of the turn in the plane; z, roll and pitch held at 1 mm / 0.06 deg
    (a 2D back end drops them). The odometry model of the 2D front ends, so that their
    graphs weigh odometry alike."""
    dist = float(np.linalg.norm(relative[:2, 3]))
    turn = abs(float(np.arctan2(relative[1, 0], relative[0, 0])))
    s_t = 0.02 + 0.02 * dist
    s_r = np.radians(0.5) + 0.02 * turn
    sig = np.array([1e-3, 1e-3, s_r, s_t, s_t, 1e-3])
    return np.diag(1.0 / sig**2)


def planar_points(xyz: np.ndarray, max_range: float, min_range: float = 0.05) -> np.ndarray:
    """The (N, 2) x, y of a planar scan's points within (min_range, max_range) m."""
    xy = np.asarray(xyz[:, :2], dtype=np.float64)
    r = np.linalg.norm(xy, axis=1)
    return xy[(r < max_range) & (r > min_range)]


# --------------------------------------------------------------------------- regions
@dataclass(frozen=True)
class RegionDivision:
    """The regional division of a grid space (paper 003, section 3.4.1): grid width w_g
    (m), I x J cells centred on the world origin, regions of N x N cells (S = N w_g,
    eq. (4))."""

    grid_width: float
    rows: int  # I
    cols: int  # J
    cells_per_region: int  # N

    @classmethod
    def with_width(
        cls, region_width: float, grid_width: float = 0.05, extent: float = 2000.0
    ) -> RegionDivision:
        """Regions of width S (m) over a square grid space of ``extent`` m."""
        n = int(round(region_width / grid_width))
        cells = int(round(extent / grid_width))
        if not 0 < n < cells:
            raise ConfigError(f"region width {region_width} m must be in (0, {extent}) m")
        return cls(grid_width, cells, cells, n)

    @property
    def region_width(self) -> float:
        return self.cells_per_region * self.grid_width

    def grid_coords(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eq. (3): i = round(y / w_g + I / 2), j = round(x / w_g + J / 2)."""
        xy = np.atleast_2d(xy)
        i = np.round(xy[:, 1] / self.grid_width + self.rows / 2).astype(np.int64)
        j = np.round(xy[:, 0] / self.grid_width + self.cols / 2).astype(np.int64)
        return i, j

    def region_of(self, xy: np.ndarray) -> np.ndarray:
        """Eq. (5): R_k = fix(i / N) * (J / N) + fix(j / N) for world points (N, 2)."""
        i, j = self.grid_coords(xy)
        n = self.cells_per_region
        return (i // n) * (self.cols // n) + (j // n)

    def centre(self, region: int) -> np.ndarray:
        """World centre (2,) of region ``region``."""
        n = self.cells_per_region
        per_row = self.cols // n
        i0, j0 = (region // per_row) * n, (region % per_row) * n
        # cells i0 .. i0 + N - 1 hold y in [(i0 - 1/2 - I/2) w_g, (i0 + N - 1/2 - I/2) w_g)
        x = (j0 + (n - 1) / 2 - self.cols / 2) * self.grid_width
        y = (i0 + (n - 1) / 2 - self.rows / 2) * self.grid_width
        return np.array([x, y])
