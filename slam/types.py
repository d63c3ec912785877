"""Data passed between the stages of the pipeline.

Conventions: arrays are float64, points (N, 3) in the sensor frame unless the
name says otherwise; poses are 4x4 homogeneous matrices named ``T_target_source``
(``T_odom_sensor`` maps sensor-frame points into the odometry frame).
Information matrices are 6x6 in GTSAM's tangent ordering: rotation first
(rx, ry, rz), then translation (tx, ty, tz).
"""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass, field
from enum import Enum
from typing import Any

import numpy as np


@dataclass
class Scan:
    """One sensor sweep.

    stamp: header time in seconds. xyz: (N, 3) float64, finite. intensity: (N,)
    float32 or None. ring: (N,) int16 beam index or None. time: (N,) float64
    seconds from the start of the sweep (>= 0) or None when the driver gives none.
    odom: the robot's wheel odometry at the stamp, (x, y, theta) in m and rad in the
    odometry's own frame, when the input carries it (2D laser logs), else None.
    layout_time: like ``time``, made up from the azimuth of a cloud stored beam by beam
    without a time field; used only once the front end finds the clouds are not
    motion-compensated (``slam.odometry.layout_time``), else None.
    """

    stamp: float
    xyz: np.ndarray
    intensity: np.ndarray | None = None
    ring: np.ndarray | None = None
    time: np.ndarray | None = None
    index: int = 0
    odom: np.ndarray | None = None
    layout_time: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def select(self, mask: np.ndarray) -> Scan:
        """A new scan holding only the points where ``mask`` (bool or index array) selects."""
        return Scan(
            stamp=self.stamp,
            xyz=self.xyz[mask],
            intensity=None if self.intensity is None else self.intensity[mask],
            ring=None if self.ring is None else self.ring[mask],
            time=None if self.time is None else self.time[mask],
            index=self.index,
            odom=self.odom,
            layout_time=None if self.layout_time is None else self.layout_time[mask],
        )


@dataclass(frozen=True)
class SkippedMessage:
    """A message or file of the input that could not be made into a Scan; the run goes on.

    Readers yield it in place of the Scan. index: the message/file index. reason: a short
    category used to count skips (e.g. "corrupt message", "no finite points", "bad field
    datatype"). detail: the full explanation for the one warning line.
    """

    index: int
    reason: str
    detail: str


class TrackingStatus(Enum):
    """How a front end got a frame's pose.

    INITIALISING: nothing usable yet (the origin, no keyframe). TRACKED: a trusted
    registration (or the scan that starts the map). RECOVERED: the first trusted
    registration after lost frames. LOST: the registration was rejected as implausible or
    failed; the pose is the motion model's prediction. PREDICTED: the scan could not be
    registered (too few points or features); the pose is the prediction.
    """

    INITIALISING = "initialising"
    TRACKED = "tracked"
    RECOVERED = "recovered"
    LOST = "lost"
    PREDICTED = "predicted"


@dataclass
class RegistrationDiagnostics:
    """The scan-to-map registration of one frame: iterations, fitness (RMSE of the inlier
    correspondences, m), converged, inliers (correspondences) and their ratio to the source
    points."""

    iterations: int
    fitness: float
    converged: bool
    inliers: int
    inlier_ratio: float


@dataclass
class FrameDiagnostics:
    """What every front end reports about one frame.

    rejected: the registration was judged implausible or failed (the pose is the
    prediction). skipped: why the scan could not be registered (None: it was). degenerate:
    the registration is unconstrained along some direction. counts: the front end's own
    per-frame scalars (feature counts, fitness, ...), averaged by the run over the frames
    that report them. timings_ms: stage name (``*_ms``) -> wall ms.
    """

    rejected: bool = False
    skipped: str | None = None
    degenerate: bool = False
    counts: dict[str, float] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def flat(self) -> dict[str, Any]:
        """This frame's scalars as one flat dict (the run averages its numbers, bools
        excluded): the counts, ``rejected`` = 1 on a rejected frame, the skip reason, the
        timings."""
        out: dict[str, Any] = dict(self.counts)
        if self.rejected:
            out["rejected"] = 1
        if self.skipped is not None:
            out["skipped"] = self.skipped
        if self.degenerate:
            out["degenerate"] = True
        out.update(self.timings_ms)
        return out


@dataclass
class OdometryDiagnostics(FrameDiagnostics):
    """The diagnostics of a scan-to-map front end (``slam.odometry``): its tracking gate's,
    map policy's and keyframe policy's per-frame results besides ``FrameDiagnostics``.

    The 0/1 tracking counters are on every frame: rejected, tracking_lost (the frame is on
    the prediction while tracking was established), recovered, reinitialised (the gate's
    running normal restarted), map_skipped (trusted but not inserted: the sensor had not
    moved). lost: why the frame is on the prediction (rejected, failed, or skipped while
    tracking). gap_hypotheses: starts tried after a long gap (0: none); start_hypotheses:
    starts tried while no velocity was known (0: none); turn_hypotheses: starts tried while
    tracking was lost (0: none). ambiguity / ambiguity_axis: the keyframe slide test's ratio
    and tested (x, y) axis (sensor frame) when it ran, and ambiguity_ms its wall time.
    """

    n_points: int = 0
    n_after_crop: int = 0
    map_points: int = 0
    tracking_lost: bool = False
    recovered: bool = False
    reinitialised: bool = False
    map_skipped: bool = False
    ambiguous: bool = False
    lost: str | None = None
    registration: RegistrationDiagnostics | None = None
    min_info_eigenvalue: float | None = None
    gap_hypotheses: int = 0
    start_hypotheses: int = 0
    turn_hypotheses: int = 0
    ambiguity: float | None = None
    ambiguity_axis: tuple[float, float] | None = None
    ambiguity_ms: float | None = None

    def flat(self) -> dict[str, Any]:
        """This frame's scalars as one flat dict: the 0/1 counters as ints (on every frame),
        the registration's numbers, the reasons under ``lost`` / ``skipped``, the front
        end's counts, the timings last."""
        out: dict[str, Any] = {
            "n_points": self.n_points,
            "rejected": int(self.rejected),
            "recovered": int(self.recovered),
            "map_skipped": int(self.map_skipped),
            "reinitialised": int(self.reinitialised),
            "n_after_crop": self.n_after_crop,
        }
        if self.gap_hypotheses:
            out["gap_hypotheses"] = self.gap_hypotheses
        if self.start_hypotheses:
            out["start_hypotheses"] = self.start_hypotheses
        if self.turn_hypotheses:
            out["turn_hypotheses"] = self.turn_hypotheses
        out.update(self.counts)
        if self.registration is not None:
            r = self.registration
            out.update(iterations=r.iterations, fitness=r.fitness, converged=r.converged,
                       inliers=r.inliers, inlier_ratio=r.inlier_ratio)  # fmt: skip
        if self.lost is not None:
            out["lost"] = self.lost
        out["tracking_lost"] = int(self.tracking_lost)
        out["map_points"] = self.map_points
        if self.min_info_eigenvalue is not None:
            out["min_info_eigenvalue"] = self.min_info_eigenvalue
        out["ambiguous"] = int(self.ambiguous)
        if self.ambiguity is not None:
            out["ambiguity"] = self.ambiguity
            out["ambiguity_axis_x"], out["ambiguity_axis_y"] = self.ambiguity_axis
            out["ambiguity_ms"] = self.ambiguity_ms
        out["degenerate"] = bool(self.degenerate)
        if self.skipped is not None:
            out["skipped"] = self.skipped
        out.update(self.timings_ms)
        return out


@dataclass(frozen=True)
class RegionAnchor:
    """A frame re-anchored on an earlier keyframe's map (2D region front ends): that
    keyframe's id and this frame's pose (x, y, theta; m, rad) in its frame."""

    keyframe: int
    pose: tuple[float, float, float]


@dataclass(frozen=True)
class RegionTag:
    """Where a 2D region front end's frame is (``dpcr2d``; read by ``region_edges``).

    region: the region id of a keyframe (None on other frames). left: the region just left
    (-1: none; its map is the keyframe's cloud). visit: the keyframe is a visit
    (``slam.visit_graph``) rather than a region event. anchor: the frame's re-anchor.
    """

    region: int | None = None
    left: int = -1
    visit: bool = False
    anchor: RegionAnchor | None = None

    def flat(self) -> dict[str, Any]:
        """The tag as flat scalars (``region``, ``region_left``, ``visit``, ``anchor_*``)."""
        out: dict[str, Any] = {}
        if self.anchor is not None:
            out["anchor_kf"] = self.anchor.keyframe
            out["anchor_x"], out["anchor_y"], out["anchor_theta"] = self.anchor.pose
        if self.region is not None:
            out.update(region=self.region, region_left=self.left)
        if self.visit:
            out["visit"] = 1
        return out


@dataclass
class Odometry:
    """What a front end returns for one scan.

    pose: T_odom_sensor at the scan stamp. relative: T_prevkf_current, the motion since
    the previous keyframe (identity for the first frame). info: 6x6 information of
    ``relative`` (rotation first), scaled to a plausible covariance. cloud: the scan's
    points in the sensor frame after deskew/filtering (voxel-thinned), kept by the pipeline
    for keyframes (float32 is stored as given; other dtypes are converted once); front
    ends may leave it empty on other frames.
    status: how the pose was obtained (``TrackingStatus``). diagnostics: the frame's typed
    scalars (``FrameDiagnostics``, ``OdometryDiagnostics`` for the scan-to-map front
    ends), what the system counts and averages. ground_plane: (4,) [nx, ny, nz, d] of the
    ground fitted in the sensor frame (n.x + d = 0, d = sensor height, m), or None.
    region: a 2D region front end's ``RegionTag``, or None.
    spread: the frame's share of the noise of its keyframe stretch's relative pose (any
    unit, only ratios count; ``slam.spread``), or None: with every frame of a stretch
    giving one, the trajectory puts the graph's correction between two keyframes where the
    noise is instead of at the next keyframe.
    extras: read by nothing in the framework; the scan-to-map front ends leave there a
    flat copy of their diagnostics and the keyframe information before the slide test
    (``_info_before_ambiguity``) for scripts written against earlier versions
    (``slam.odometry.extras.legacy_extras``).
    """

    stamp: float
    pose: np.ndarray
    is_keyframe: bool
    relative: np.ndarray
    info: np.ndarray
    cloud: np.ndarray | None = None
    extras: dict[str, Any] = field(default_factory=dict)
    status: TrackingStatus | None = None
    diagnostics: FrameDiagnostics | None = None
    ground_plane: np.ndarray | None = None
    region: RegionTag | None = None
    spread: float | None = None

    def flat(self) -> dict[str, Any]:
        """The frame's diagnostics and region tag as flat scalars (the numbers are what
        metrics.json's ``frontend_means`` average)."""
        out = {} if self.diagnostics is None else self.diagnostics.flat()
        if self.region is not None:
            out.update(self.region.flat())
        return out


@dataclass
class Keyframe:
    """A keyframe as the factor plugins see it.

    id: 0, 1, 2, ... in order. frame_index: index of the input scan. pose_odom:
    T_odom_sensor from the front end. relative/info: motion from the previous keyframe and
    its information (None/identity for id 0). cloud: (N, 3) sensor-frame points, m; the
    pipeline stores it once, float32, voxel-thinned and read-only (the one copy of the run:
    plugins read it through ``GraphView.cloud`` instead of copying it). status,
    diagnostics, ground_plane, region: the front end's ``Odometry`` fields of that frame.
    """

    id: int
    stamp: float
    frame_index: int
    pose_odom: np.ndarray
    relative: np.ndarray
    info: np.ndarray
    cloud: np.ndarray
    _: KW_ONLY  # by name: the untyped extras of earlier versions took this place
    status: TrackingStatus | None = None
    diagnostics: FrameDiagnostics | None = None
    ground_plane: np.ndarray | None = None
    region: RegionTag | None = None


@dataclass
class LoopConstraint:
    """An accepted or rejected loop candidate between two keyframes.

    T_target_source maps the source keyframe's sensor frame into the target's.
    """

    source: int
    target: int
    T_target_source: np.ndarray
    score: float
    fitness: float
    accepted: bool
    info: np.ndarray | None = None
    reason: str = ""
