"""A 2D laser scanner in floor plans: the simulated sequences with ground truth of the 2D
pipeline (paper 003, DPCR-SLAM). A scene is a set of wall segments (the 3D scenes sliced at
the scanner's height would give the same; walls are what an indoor single-beam laser
sees); the scanner sweeps 360 deg at 0.5 deg with Gaussian range noise, a maximum range
and dropouts. Pure numpy ray casting (every beam against every segment), fast enough for
thousands of scans.

Scenes: ``rooms2d`` - three rooms in a row (21 x 5 m, the paper's region-width test
environment, section 4.2) with doors, furniture boxes and a loop route through them;
``office2d`` - a 10 x 10 m floor with 1.5 m corridors, workstation blocks and room
partitions (the paper's evaluation environment, section 5.1), driven twice around.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam.errors import InputError


@dataclass(frozen=True)
class Scanner2D:
    """beams over ``fov_deg`` centred forward; range noise sigma (m); max/min range (m);
    dropout: share of beams with no return; rate_hz: scans per second."""

    beams: int = 720
    fov_deg: float = 360.0
    max_range: float = 12.0
    min_range: float = 0.1
    sigma: float = 0.01
    dropout: float = 0.01
    rate_hz: float = 10.0

    def angles(self) -> np.ndarray:
        fov = np.radians(self.fov_deg)
        full = np.isclose(self.fov_deg, 360.0)
        n = self.beams
        step = fov / n if full else fov / (n - 1)
        return -fov / 2 + step * np.arange(n)


@dataclass
class FloorPlan:
    """Wall segments (K, 2, 2) in metres, a closed route (M, 2) and its description."""

    name: str
    segments: np.ndarray
    route: np.ndarray
    description: str = ""
    extent: tuple[float, float] = (0.0, 0.0)


def _box(x0: float, y0: float, x1: float, y1: float) -> list[list[list[float]]]:
    return [
        [[x0, y0], [x1, y0]],
        [[x1, y0], [x1, y1]],
        [[x1, y1], [x0, y1]],
        [[x0, y1], [x0, y0]],
    ]


def _wall_with_doors(a, b, doors: list[tuple[float, float]]) -> list[list[list[float]]]:
    """Segment a -> b with openings (centre along the wall from a, width), in metres."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = np.linalg.norm(b - a)
    u = (b - a) / length
    cuts = [0.0]
    for centre, width in sorted(doors):
        cuts += [centre - width / 2, centre + width / 2]
    cuts.append(length)
    return [
        [list(a + u * cuts[i]), list(a + u * cuts[i + 1])]
        for i in range(0, len(cuts), 2)
        if cuts[i + 1] - cuts[i] > 1e-6
    ]


def rooms() -> FloorPlan:
    """Three 7 x 5 m rooms in a row (21 x 5 m), doors between them, and a 2 m return
    corridor along the south reached through two doors, so the route is a loop; tables
    and cabinets as boxes, one pillar."""
    segs: list = [[[0, 5], [21, 5]], [[0, -2], [0, 5]], [[21, -2], [21, 5]], [[0, -2], [21, -2]]]
    segs += _wall_with_doors((0, 0), (21, 0), [(2.0, 1.0), (19.0, 1.0)])
    for x in (7.0, 14.0):
        segs += _wall_with_doors((x, 0), (x, 5), [(2.5, 1.0)])
    for box in ((2.0, 3.5, 3.2, 4.4), (9.0, 3.6, 10.5, 4.4), (16.5, 3.4, 17.3, 4.6)):
        segs += _box(*box)
    segs += _box(11.5, 1.0, 12.0, 1.5)  # a pillar
    route = np.array(
        [[2.0, -1.0], [2.0, 1.0], [3.5, 2.5], [17.5, 2.5], [19.0, 1.0], [19.0, -1.0],
         [2.0, -1.0]]
    )  # fmt: skip
    return FloorPlan("rooms2d", np.array(segs, float), route, "three rooms 21 x 5 m", (21.0, 7.0))


def office() -> FloorPlan:
    """A 10 x 10 m office floor: 1.5 m corridors around a block of workstations, rooms
    with partitions and doors (paper 003, section 5.1)."""
    segs: list = []
    segs += _box(0, 0, 10, 10)
    segs += _wall_with_doors((1.5, 1.5), (8.5, 1.5), [(3.5, 0.9)])
    segs += _wall_with_doors((8.5, 1.5), (8.5, 8.5), [(3.5, 0.9)])
    segs += _wall_with_doors((8.5, 8.5), (1.5, 8.5), [(3.5, 0.9)])
    segs += [[[1.5, 8.5], [1.5, 1.5]]]
    segs += [[[5.0, 1.5], [5.0, 4.0]], [[5.0, 6.0], [5.0, 8.5]], [[1.5, 5.0], [3.5, 5.0]]]
    for x in (2.2, 3.4):
        for y in (2.2, 3.4, 6.0, 7.2):
            segs += _box(x, y, x + 0.8, y + 0.5)
    segs += _box(6.2, 6.2, 7.6, 7.6)
    route = np.array(
        [[0.75, 0.75], [9.25, 0.75], [9.25, 5.0], [7.0, 5.0], [9.25, 5.0], [9.25, 9.25],
         [0.75, 9.25], [0.75, 0.75]]
    )  # fmt: skip
    return FloorPlan("office2d", np.array(segs, float), route, "office floor 10 x 10 m", (10, 10))


PLANS = {"rooms2d": rooms, "office2d": office}


def cast(
    plan: FloorPlan, pose: np.ndarray, scanner: Scanner2D, rng: np.random.Generator
) -> np.ndarray:
    """Ranges (beams,) of one scan from ``pose`` (x, y, theta); NaN for no return."""
    ang = scanner.angles() + pose[2]
    d = np.column_stack([np.cos(ang), np.sin(ang)])  # (B, 2)
    a, b = plan.segments[:, 0], plan.segments[:, 1]  # (K, 2)
    e = b - a
    w = a - pose[:2]
    # solve pose + t d = a + u e  for t (range) and u in [0, 1], every beam x segment
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / den
        u = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(hit, t, np.inf).min(axis=1)
    r = r + rng.normal(0.0, scanner.sigma, len(r))
    r[(r > scanner.max_range) | (r < scanner.min_range) | ~np.isfinite(r)] = np.nan
    r[rng.random(len(r)) < scanner.dropout] = np.nan
    return r


def route_poses(route: np.ndarray, speed: float, rate_hz: float, laps: float = 1.0) -> np.ndarray:
    """Poses (N, 3) along the polyline ``route`` at ``speed`` (m/s), heading along the path
    (turns smoothed over 0.5 m), sampled at ``rate_hz``."""
    seg = np.diff(route, axis=0)
    length = np.linalg.norm(seg, axis=1)
    s_knots = np.concatenate([[0.0], np.cumsum(length)])
    total = s_knots[-1] * laps
    s = np.arange(0.0, total, speed / rate_hz) % s_knots[-1]
    x = np.interp(s, s_knots, route[:, 0])
    y = np.interp(s, s_knots, route[:, 1])
    # heading from points 0.5 m ahead and behind: smooth through corners
    ahead = (s + 0.5) % s_knots[-1]
    behind = (s - 0.5) % s_knots[-1]
    dx = np.interp(ahead, s_knots, route[:, 0]) - np.interp(behind, s_knots, route[:, 0])
    dy = np.interp(ahead, s_knots, route[:, 1]) - np.interp(behind, s_knots, route[:, 1])
    theta = np.unwrap(np.arctan2(dy, dx))
    return np.column_stack([x, y, theta])


@dataclass
class Sequence2D:
    """A simulated 2D sequence: stamps (N,), ground-truth poses (N, 3), ranges (N, B) and
    beam angles (B,)."""

    plan: FloorPlan
    scanner: Scanner2D
    stamps: np.ndarray
    poses: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def points(self, k: int) -> np.ndarray:
        """Scan ``k`` as points (M, 2) in the scanner frame (no-return beams dropped)."""
        r = self.ranges[k]
        ok = np.isfinite(r)
        return np.column_stack([r[ok] * np.cos(self.angles[ok]), r[ok] * np.sin(self.angles[ok])])


def simulate2d(
    plan: str | FloorPlan = "rooms2d",
    *,
    frames: int | None = None,
    speed: float = 0.5,
    laps: float = 2.0,
    scanner: Scanner2D | None = None,
    seed: int = 0,
    stamp0: float = 1_700_000_000.0,
) -> Sequence2D:
    """Simulate a 2D sequence along the plan's route (``laps`` times at ``speed``)."""
    if isinstance(plan, str):
        if plan not in PLANS:
            raise InputError(f"unknown 2D floor plan {plan!r}; choose one of {sorted(PLANS)}")
        plan = PLANS[plan]()
    scanner = scanner or Scanner2D()
    rng = np.random.default_rng(seed)
    poses = route_poses(plan.route, speed, scanner.rate_hz, laps)
    if frames is not None:
        poses = poses[:frames]
    ranges = np.array([cast(plan, p, scanner, rng) for p in poses])
    stamps = stamp0 + np.arange(len(poses)) / scanner.rate_hz
    return Sequence2D(plan, scanner, stamps, poses, ranges, scanner.angles())


def iter_points(seq: Sequence2D) -> Iterator[np.ndarray]:
    for k in range(len(seq.stamps)):
        yield seq.points(k)


def wheel_odometry(
    poses: np.ndarray,
    seed: int = 0,
    slip: float = 0.02,
    yaw_slip: float = 0.02,
    heading_deg_per_sqrt_m: float = 0.1,
) -> np.ndarray:
    """Wheel odometry (N, 3) of a ground-truth path: every step's travel scaled by a
    random slip (``slip`` sigma, relative) and its turn by ``yaw_slip``, plus a heading
    random walk of ``heading_deg_per_sqrt_m`` - the drift a real robot's encoders have."""
    rng = np.random.default_rng(seed + 7)
    out = np.zeros_like(poses)
    out[0] = poses[0]
    for k in range(1, len(poses)):
        c, s = np.cos(poses[k - 1, 2]), np.sin(poses[k - 1, 2])
        d = poses[k, :2] - poses[k - 1, :2]
        local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
        dist = float(np.linalg.norm(local))
        local = local * (1.0 + rng.normal(0.0, slip))
        dth = (poses[k, 2] - poses[k - 1, 2]) * (1.0 + rng.normal(0.0, yaw_slip))
        dth += rng.normal(0.0, np.radians(heading_deg_per_sqrt_m) * np.sqrt(max(dist, 1e-9)))
        c, s = np.cos(out[k - 1, 2]), np.sin(out[k - 1, 2])
        out[k, :2] = out[k - 1, :2] + [c * local[0] - s * local[1], s * local[0] + c * local[1]]
        out[k, 2] = out[k - 1, 2] + dth
    return out


def write_carmen(seq: Sequence2D, path: str | Path, odometry: np.ndarray | None = None) -> Path:
    """The sequence as a CARMEN log of ``ROBOTLASER1`` lines (start angle, fov, resolution,
    max range, ranges; no return = max range; laser pose = ground truth, robot pose = the
    wheel ``odometry`` (default :func:`wheel_odometry`), the format ``slam run`` reads like
    the real Intel / FR079 logs."""
    path = Path(path)
    odo = wheel_odometry(seq.poses) if odometry is None else odometry
    sc = seq.scanner
    step = float(seq.angles[1] - seq.angles[0]) if len(seq.angles) > 1 else 0.0
    lines = [f"# simulated by slam.sim.floorplan2d: {seq.plan.description}\n"]
    for k, stamp in enumerate(seq.stamps):
        r = np.where(np.isfinite(seq.ranges[k]), seq.ranges[k], sc.max_range)
        x, y, th = seq.poses[k]
        ox, oy, oth = odo[k]
        ranges = " ".join(f"{v:.3f}" for v in r)
        lines.append(
            f"ROBOTLASER1 0 {seq.angles[0]:.9f} {np.radians(sc.fov_deg):.9f} {step:.9f} "
            f"{sc.max_range:.3f} 0.01 0 {len(r)} {ranges} 0 {x:.6f} {y:.6f} {th:.6f} "
            f"{ox:.6f} {oy:.6f} {oth:.6f} 0 0 0 0 0 {stamp:.6f} sim {stamp:.6f}\n"
        )
    path.write_text("".join(lines))
    return path


def write_sequence(
    seq: Sequence2D, out: str | Path, odometry: np.ndarray | None = None
) -> tuple[Path, Path]:
    """``<out>/<plan>.clf`` and ``<out>/ground_truth.tum`` (planar poses, z = 0);
    ``odometry``: the wheel odometry written in the log (default :func:`wheel_odometry`)."""
    from slam.io.trajectory import write_tum

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log = write_carmen(seq, out / f"{seq.plan.name}.clf", odometry)
    T = np.repeat(np.eye(4)[None], len(seq.poses), axis=0)
    c, s = np.cos(seq.poses[:, 2]), np.sin(seq.poses[:, 2])
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3], T[:, 1, 3] = seq.poses[:, 0], seq.poses[:, 1]
    gt = out / "ground_truth.tum"
    write_tum(gt, seq.stamps, T)
    return log, gt
