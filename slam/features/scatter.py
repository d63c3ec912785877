"""When LOAM features cannot see the motion along a road, and the points that can.

A spinning LiDAR samples every surface that runs along the road (the ground, kerbs, walls,
barriers, guard rails, verges) in the same pattern from every pose: registered against a
map of earlier scans, those samples pull the scan back onto the pose the map was made from
(docs/robustness.md, "16 beams on a motorway"). What shows the motion along the road is
the structure that does not run along it; on an open road that is vegetation and clutter,
whose ragged returns LOAM's selection drops (occluded neighbours, no clear curvature).

``horizontal_observability`` measures how well the features' shapes observe a horizontal
translation; ``scatter_points`` picks the points LOAM left out, off the ground.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from slam.errors import ConfigError
from slam.features.thinning import voxel_thin

# a covariance is a plane when its smallest eigenvalue is below this share of the middle
# one, a line when the middle one is below this share of the largest
_SHAPE_RATIO = 0.1

# below this ``horizontal_observability`` a scan's features run along one direction: 87 % of
# a simulated motorway's scans (median 0.045), 1 % of a 1238 m city drive's, none of KITTI,
# Hilti or a corridor (docs/robustness.md)
ALONG_ROAD = 0.1


_MODES = ("never", "always", "auto")  # words YAML reads as strings


@dataclass
class ScatterConfig:
    """The open-road mode: register, with the features, the points that are neither edge nor
    plane candidates and lie more than ``min_height`` m off the scan's ground plane, one per
    ``voxel`` m, and treat the ground as a plane on every sensor.
    mode: ``never``; ``always`` (the recipe ``improved_floam_open_road``); ``auto`` (default,
    ``OpenRoadGate``): on once the features of at least ``on_share`` of the last ``window``
    scans ran along the road, off once fewer than ``off_share`` of the last ``hold`` scans
    did (on a city drive the mode costs accuracy, docs/robustness.md).
    confirm_distance, confirm_height (m): in the mode a point enters the map only when the
    previous inserted scan had one within that distance horizontally and height vertically
    (``slam.mapping.second_sighting``: the traffic stays out of the map; 0 = off).
    at_start: in ``auto``, the scans before the motion is known (the first scan and the
    first-motion search) are built in the mode whatever the gate says, so that a start is
    judged by the structure that shows the motion, not by ring samples that fit at rest."""

    mode: str = "auto"
    voxel: float = 0.5
    min_height: float = 0.3
    window: int = 20
    on_share: float = 0.5
    hold: int = 100
    off_share: float = 0.2
    confirm_distance: float = 0.5
    confirm_height: float = 1.0
    at_start: bool = True

    def __post_init__(self) -> None:
        if self.mode not in _MODES:
            raise ConfigError(f"scatter.mode must be one of {', '.join(_MODES)}, got {self.mode!r}")
        if self.voxel <= 0 or self.min_height < 0:
            raise ConfigError("scatter: voxel must be > 0 m and min_height >= 0 m")
        if not 1 <= self.window <= self.hold or not 0 <= self.off_share <= self.on_share <= 1:
            raise ConfigError(
                "scatter: need 1 <= window <= hold (scans) and 0 <= off_share <= on_share <= 1"
            )
        if self.confirm_distance < 0 or self.confirm_height <= 0:
            raise ConfigError("scatter: confirm_distance must be >= 0 m, confirm_height > 0 m")


class OpenRoadGate:
    """Whether the open-road mode is on for the next scan. An open road is a stretch, not a
    scan: switched on quickly (``on_share`` of the last ``window`` scans ran along the road),
    held through the bridges, junctions and woods of a motorway whose features then look
    observable but still hold the scan back (off below ``off_share`` of the last ``hold``
    scans; docs/robustness.md). Deterministic: flags in, mode out."""

    def __init__(self, cfg: ScatterConfig):
        self.cfg = cfg
        self._flags: deque[bool] = deque(maxlen=cfg.hold)
        self._on = cfg.mode == "always"

    @property
    def on(self) -> bool:
        """The mode for the scan about to be registered."""
        return self._on

    @property
    def unjudged(self) -> bool:
        """No scan recorded yet: the first scan of a run is judged by itself."""
        return self.cfg.mode == "auto" and not self._flags

    def state(self) -> tuple[tuple[bool, ...], bool]:
        """What ``update`` changes, for a front end that registers one scan several times."""
        return tuple(self._flags), self._on

    def restore(self, state: tuple[tuple[bool, ...], bool]) -> None:
        """Back to a ``state()``."""
        flags, self._on = state
        self._flags = deque(flags, maxlen=self.cfg.hold)

    def update(self, along_road: bool) -> None:
        """Record one scan's flag and decide the mode of the next."""
        if self.cfg.mode != "auto":
            return
        self._flags.append(bool(along_road))
        recent = list(self._flags)[-self.cfg.window :]
        if sum(recent) >= self.cfg.on_share * len(recent):
            self._on = True
        elif sum(self._flags) < self.cfg.off_share * len(self._flags):
            self._on = False


def horizontal_observability(covs: np.ndarray) -> float:
    """Smallest over largest eigenvalue (0..1) of the horizontal 2x2 block of
    sum(n n^T) over plane-shaped covariances (n: the normal) + sum(I - u u^T) over
    line-shaped ones (u: the direction), sensor frame (z up): 1 when the features' surfaces
    face every horizontal direction alike, near 0 when all run along one (a motorway's
    barriers, rails and verges). Isotropic covariances count for nothing; 1.0 when no
    covariance has a shape (nothing to judge)."""
    covs = np.asarray(covs, dtype=np.float64)
    if covs.ndim != 3 or covs.shape[1:] != (3, 3):
        raise ValueError(f"covariances must be (N, 3, 3), got {covs.shape}")
    w, v = np.linalg.eigh(covs)  # ascending eigenvalues
    plane = w[:, 0] < _SHAPE_RATIO * w[:, 1]
    line = ~plane & (w[:, 1] < _SHAPE_RATIO * w[:, 2])
    if not plane.any() and not line.any():
        return 1.0
    n, u = v[plane, :, 0], v[line, :, 2]
    A = n.T @ n + int(line.sum()) * np.eye(3) - u.T @ u
    lo, hi = np.linalg.eigvalsh(A[:2, :2])
    return float(lo / hi) if hi > 0 else 1.0


def scatter_points(
    xyz: np.ndarray,
    candidates: np.ndarray,
    plane: tuple[np.ndarray, float] | None,
    cfg: ScatterConfig,
) -> np.ndarray:
    """Sorted indices into ``xyz`` (N, 3, sensor frame) of the points that are not feature
    ``candidates`` ((N,) bool), more than ``cfg.min_height`` m off ``plane`` (n, d with
    n.x + d = 0; None: no ground known, every such point), one per ``cfg.voxel`` m voxel."""
    rest = np.flatnonzero(~np.asarray(candidates, dtype=bool))
    if plane is not None and len(rest):
        n, d = plane
        rest = rest[np.abs(xyz[rest] @ n + d) > cfg.min_height]
    if not len(rest):
        return rest
    return rest[voxel_thin(xyz, cfg.voxel, rest)]
