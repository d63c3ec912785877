"""The live view of a run in the Rerun viewer, or its recording to an ``.rrd`` file.

:class:`RerunObserver` watches a run (the pipeline's observer calls: ``on_frame``,
``on_keyframe``, ``on_loop``, ``on_optimised``, ``close``) and logs, on the ``frame``
timeline (and ``time``, seconds from the first scan):

- ``world/sensor``: the front end's pose of every frame (Transform3D), and under it
  ``world/sensor/scan``: the scan in the sensor frame, decimated to ``scan_points``, every
  ``scan_every`` frames;
- ``world/odometry/NNNN``: the front end's trajectory, in strips of ``chunk`` frames (a
  frame re-logs only its own strip);
- ``world/map/kfNNNNN`` (Transform3D) and ``.../points``: each keyframe's cloud, decimated,
  logged once; an optimisation re-logs only the transforms of keyframes it moved;
- ``world/local_map``: the last ``local_keyframes`` keyframe clouds in the world frame,
  decimated to ``local_points``, and ``world/keyframes`` (keyframe positions), both every
  ``local_every`` keyframes;
- ``world/optimised``: the optimised keyframe path; ``world/loops``: the loop edges between
  keyframe positions (after each loop and optimisation).

Cost: a few log calls per frame on decimated arrays (about 30 kB a frame), O(1) in the
length of the run except the keyframe positions (one (K, 3) array every third keyframe);
rerun serialises and writes in its own thread, whose CPU counts too.
``benchmarks/bench_viz.py`` measures both. rerun-sdk is the optional extra ``viz``,
imported only when a view is asked for.
"""

from __future__ import annotations

import os
import sys
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import InputError

APP_ID = "pyslam-graph"
VIZ_MISSING = (
    "the live view needs rerun-sdk, the optional extra 'viz': "
    "pip install 'pyslam-graph[viz]' (in a checkout: .venv/bin/pip install -e '.[viz]')"
)
SCAN_COLOR = (255, 200, 40)
LOCAL_COLOR = (60, 200, 255)
MAP_COLOR = (170, 170, 170)
ODOM_COLOR = (255, 140, 0)
OPT_COLOR = (40, 120, 255)
KF_COLOR = (40, 120, 255)
LOOP_COLOR = (255, 0, 255)


def import_rerun() -> Any:
    """The ``rerun`` module, or an InputError saying how to install it."""
    try:
        import rerun
    except ImportError as exc:
        raise InputError(VIZ_MISSING) from exc
    return rerun


def open_stream(target: str | Path | None, app_id: str = APP_ID) -> Any:
    """A Rerun recording stream to the file ``target`` (.rrd; no display needed) or, when
    ``target`` is None or empty, to a viewer spawned on this machine's display."""
    rr = import_rerun()
    if target:
        path = Path(target)
        if path.suffix != ".rrd":
            raise InputError(f"--viz {path}: the recording file must end in .rrd")
        path.parent.mkdir(parents=True, exist_ok=True)
        rec = rr.RecordingStream(app_id)
        rec.save(path)
    else:
        if sys.platform.startswith("linux") and not (
            os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        ):
            raise InputError(
                "no display to open the Rerun viewer on: record to a file instead "
                "(--viz run.rrd) and open it where there is a screen: rerun run.rrd"
            )
        rec = rr.RecordingStream(app_id)
        rec.spawn()
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    return rec


def decimate(points: np.ndarray, limit: int) -> np.ndarray:
    """At most ``limit`` of ``points`` (every k-th, k = ceil(N / limit)), float32 (N, 3)."""
    p = np.asarray(points)[:, :3]
    step = max(1, -(-len(p) // max(limit, 1)))
    return np.ascontiguousarray(p[::step], dtype=np.float32)


@dataclass(frozen=True)
class VizConfig:
    """How much of a run is logged (points per scan / keyframe, strips, thresholds)."""

    scan_points: int = 2000
    scan_every: int = 2  # frames: the scan is shown at 5 Hz of a 10 Hz sensor
    keyframe_points: int = 800
    local_keyframes: int = 8  # the local map: the last keyframe clouds, ...
    local_points: int = 4000  # ... decimated together to this many points, ...
    local_every: int = 3  # ... re-logged (with the keyframe positions) every 3rd keyframe
    chunk: int = 200  # frames per strip of the odometry trajectory
    moved: float = 0.005  # m (or rad): an optimised keyframe is re-logged past this change


class RerunObserver:
    """Streams a run to Rerun (see the module docstring for what is logged where)."""

    def __init__(self, rec: Any, config: VizConfig | None = None):
        self.rr = import_rerun()
        self.rec = rec
        self.config = config or VizConfig()
        self._t0: float | None = None
        self._index = 0
        self._odom: list[np.ndarray] = []  # positions of the current strip
        self._kf_pose: dict[int, np.ndarray] = {}  # the pose each keyframe is shown at
        self._kf_xyz = np.zeros((0, 3))  # shown positions in keyframe id order
        self._kf_ids: list[int] = []
        self._local: deque = deque(maxlen=self.config.local_keyframes)  # (id, cloud)
        self._loops: list[tuple[int, int]] = []
        self._closed = False

    # ------------------------------------------------------------------ observer calls
    def on_frame(self, index: int, scan: Any, odom: Any) -> None:
        rr, rec, T = self.rr, self.rec, np.asarray(odom.pose, dtype=float)
        self._set_time(index, float(scan.stamp))
        rec.log("world/sensor", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        if index % self.config.scan_every == 0:
            pts = decimate(scan.xyz, self.config.scan_points)
            rec.log("world/sensor/scan", rr.Points3D(pts, colors=SCAN_COLOR, radii=0.05))
        chunk = index // self.config.chunk
        if index % self.config.chunk == 0 and self._odom:
            self._odom = self._odom[-1:]  # strips join: the new one starts at the last point
        self._odom.append(T[:3, 3].copy())
        if len(self._odom) > 1:
            rec.log(
                f"world/odometry/{chunk:04d}",
                rr.LineStrips3D([np.asarray(self._odom)], colors=ODOM_COLOR, radii=0.08),
            )

    def on_keyframe(self, kf_id: int, frame_index: int, pose: np.ndarray, cloud: Any) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=frame_index)  # called before the frame's on_frame
        pose = np.asarray(pose, dtype=float)
        pts = decimate(cloud, self.config.keyframe_points)
        self._log_kf_pose(kf_id, pose)
        rec.log(f"world/map/kf{kf_id:05d}/points", rr.Points3D(pts, colors=MAP_COLOR, radii=0.04))
        self._kf_ids.append(kf_id)
        self._kf_xyz = np.vstack([self._kf_xyz, pose[:3, 3]])
        self._local.append((kf_id, pts))
        if (len(self._kf_ids) - 1) % self.config.local_every == 0:
            local = [
                c @ self._kf_pose[k][:3, :3].T + self._kf_pose[k][:3, 3] for k, c in self._local
            ]
            local_map = decimate(np.vstack(local), self.config.local_points)
            rec.log("world/local_map", rr.Points3D(local_map, colors=LOCAL_COLOR, radii=0.05))
            rec.log("world/keyframes", rr.Points3D(self._kf_xyz, colors=KF_COLOR, radii=0.15))

    def on_loop(self, kf_a: int, kf_b: int) -> None:
        self._loops.append((int(kf_a), int(kf_b)))
        self._log_loops()

    def on_optimised(self, poses: dict[int, np.ndarray]) -> None:
        moved = False
        for kf_id, T in poses.items():
            T = np.asarray(T, dtype=float)
            old = self._kf_pose.get(kf_id)
            if old is None or self._changed(old, T):
                self._log_kf_pose(kf_id, T)
                moved = True
        if not moved:
            return
        index = {k: i for i, k in enumerate(self._kf_ids)}
        for kf_id, T in self._kf_pose.items():
            if kf_id in index:
                self._kf_xyz[index[kf_id]] = T[:3, 3]
        rr = self.rr
        self.rec.log("world/keyframes", rr.Points3D(self._kf_xyz, colors=KF_COLOR, radii=0.15))
        if len(self._kf_xyz) > 1:
            self.rec.log(
                "world/optimised",
                rr.LineStrips3D([self._kf_xyz], colors=OPT_COLOR, radii=0.1),
            )
        self._log_loops()

    def close(self) -> None:
        """Flush and end the stream (the .rrd file is complete after this); idempotent."""
        if self._closed:
            return
        self._closed = True
        self.rec.flush()
        self.rec.disconnect()

    # ------------------------------------------------------------------ helpers
    def _set_time(self, index: int, stamp: float) -> None:
        if self._t0 is None:
            self._t0 = stamp
        self._index = index
        self.rec.set_time("frame", sequence=index)
        self.rec.set_time("time", duration=stamp - self._t0)

    def _changed(self, old: np.ndarray, new: np.ndarray) -> bool:
        m = self.config.moved
        return bool(
            np.abs(new[:3, 3] - old[:3, 3]).max() > m or np.abs(new[:3, :3] - old[:3, :3]).max() > m
        )

    def _log_kf_pose(self, kf_id: int, T: np.ndarray) -> None:
        self._kf_pose[kf_id] = T
        self.rec.log(
            f"world/map/kf{kf_id:05d}", self.rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])
        )

    def _log_loops(self) -> None:
        segs = [
            np.stack([self._kf_pose[a][:3, 3], self._kf_pose[b][:3, 3]])
            for a, b in self._loops
            if a in self._kf_pose and b in self._kf_pose
        ]
        if segs:
            self.rec.log("world/loops", self.rr.LineStrips3D(segs, colors=LOOP_COLOR, radii=0.12))


def viz_observer(target: str | Path | None, config: VizConfig | None = None) -> RerunObserver:
    """The observer of ``slam run --viz [FILE.rrd]`` (see :func:`open_stream`)."""
    return RerunObserver(open_stream(target), config)
