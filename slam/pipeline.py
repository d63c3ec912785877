"""The SLAM pipeline: scans -> front end -> factor plugins -> back end -> trajectory.

Orchestration only: algorithms live in the plugins. The pipeline keeps, for every
input frame, its keyframe and its pose relative to that keyframe, so that the final
trajectory of every frame follows the optimised keyframes.
"""

from __future__ import annotations

import logging
import time
from array import array
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from itertools import islice
from typing import Any

import numpy as np

from slam import plugins
from slam.config import SlamConfig
from slam.errors import BackendError, ConfigError, InputError, SlamError
from slam.factors import GraphView, key, pose3
from slam.interrupts import StopRequest
from slam.io.stamps import Reorder
from slam.types import Keyframe, Scan, SkippedMessage

log = logging.getLogger(__name__)

MEMORY_REFERENCE_FRAME = 100  # frames after which the map, models and kernels are warm
# this many scans in a row whose stamps are not after the last kept one stop the run (bad
# input): the rest of the input would be dropped, a useless trajectory without an error
STAMP_RUN_LIMIT = 10


@dataclass
class FactorSource:
    """One enabled factor plugin with the name it was configured under."""

    name: str
    plugin: Any

    @property
    def is_loop(self) -> bool:
        return bool(getattr(self.plugin, "is_loop", False))


def build_factor_plugins(factors: dict[str, dict[str, Any]]) -> list[FactorSource]:
    """Instantiate the enabled factor plugins, in config order.

    A section's name is the plugin name, or give ``plugin: package.module:Class`` to
    load a user's class under any section name.
    """
    out = []
    for name, params in factors.items():
        params = dict(params)
        spec = params.pop("plugin", name)
        cls = plugins.load("slam.factors", spec)
        cfg = plugins.plugin_config(cls, params, f"factors.{name}")
        if cfg is not None and not getattr(cfg, "enabled", True):
            continue
        out.append(FactorSource(name, cls(cfg) if cfg is not None else cls()))
    return out


@dataclass
class RunState:
    """Everything a run has computed so far (written out even when the run stops early)."""

    stamps: list[float] = field(default_factory=list)
    odom_poses: list[np.ndarray] = field(default_factory=list)
    frame_kf: list[int] = field(default_factory=list)
    T_kf_frame: list[np.ndarray] = field(default_factory=list)
    keyframes: list[Keyframe] = field(default_factory=list)
    factor_counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    stage_seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    diagnostic_sums: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    diagnostic_counts: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    # per-frame wall time (s) of step() and back-end update time (s) per keyframe: compact
    # arrays (8 bytes an entry), so that metrics can compare the start and end of a run
    frame_seconds: array = field(default_factory=lambda: array("d"))
    # the same step's CPU seconds of this process (all its threads, not worker processes):
    # on a shared machine the wall time is partly waiting for a core, the CPU time is not
    frame_cpu_seconds: array = field(default_factory=lambda: array("d"))
    backend_seconds: array = field(default_factory=lambda: array("d"))
    stage_max_seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    # per-frame seconds of each stage (front end, each factor plugin, back end; 0 on frames
    # where a stage did not run), aligned with frame_seconds: where a run's time grows
    stage_frame_seconds: dict[str, array] = field(default_factory=dict)
    stage_frame_cpu_seconds: dict[str, array] = field(default_factory=dict)  # CPU s, the same
    path_length: float = 0.0  # odometric distance travelled (m), summed frame to frame
    # (peak memory MiB, path length m) after MEMORY_REFERENCE_FRAME frames: the growth of the
    # peak from there per km travelled is metrics.json's memory_mb_per_km
    memory_reference: tuple[float, float] | None = None
    skipped_frames: int = 0  # frames the front end could not register (prediction kept)
    # (message index, s added to its and every later stamp) where the stamps' clock stepped
    # back and the run went on on its own clock
    clock_steps: list[tuple[int, float]] = field(default_factory=list)
    skipped_messages: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    degenerate_frames: int = 0
    loops_closed: int = 0
    estimates: dict[int, np.ndarray] = field(default_factory=dict)
    wall_seconds: float = 0.0
    stopped_by: str | None = None
    sensor: str | None = None  # the beam model, as inferred or read (BeamModel.describe)

    @property
    def frames(self) -> int:
        return len(self.stamps)

    @property
    def messages_skipped(self) -> int:
        """Input messages dropped before the front end (damaged, duplicated, out of order)."""
        return int(sum(self.skipped_messages.values()))

    def add_diagnostics(self, extras: dict[str, Any]) -> None:
        """Accumulate a frame's numeric front-end diagnostics (counts, *_ms timings)."""
        for k, v in extras.items():
            if (
                isinstance(v, (int, float, np.integer, np.floating))
                and not isinstance(v, bool)
                and np.isfinite(v)
            ):
                self.diagnostic_sums[k] += float(v)
                self.diagnostic_counts[k] += 1

    def diagnostic_means(self) -> dict[str, float]:
        """Per-frame mean of each numeric diagnostic over the frames that reported it."""
        return {k: self.diagnostic_sums[k] / n for k, n in self.diagnostic_counts.items() if n}

    def trajectory(self) -> np.ndarray:
        """(N,4,4) optimised pose of every frame: keyframe estimate composed with T_kf_frame."""
        if not self.stamps:
            return np.zeros((0, 4, 4))
        kf_poses = np.stack([self.estimates[k] for k in self.frame_kf])
        return kf_poses @ np.stack(self.T_kf_frame)


def keyframe_cloud(cloud: np.ndarray | None) -> np.ndarray:
    """The one stored copy of a keyframe's cloud: (N, 3) float32, C-contiguous, read-only.

    The front end's ``Odometry.cloud`` is already voxel-thinned; a float32 contiguous cloud
    is kept as it is (no copy), anything else is converted once. Read-only because factor
    plugins share it (``GraphView.cloud``) instead of keeping copies.
    """
    if cloud is None or len(cloud) == 0:
        out = np.zeros((0, 3), dtype=np.float32)
    else:
        out = np.ascontiguousarray(np.asarray(cloud)[:, :3], dtype=np.float32)
    out = out.view()
    out.flags.writeable = False
    return out


def scalar_extras(extras: dict[str, Any]) -> dict[str, Any]:
    """The front end's per-frame diagnostics a keyframe keeps: scalars only (numbers, bools,
    strings), never arrays or private ``_`` entries (they would hold scans in memory)."""
    keep = (bool, int, float, str, np.generic)
    return {k: v for k, v in extras.items() if isinstance(v, keep) and not k.startswith("_")}


class Pipeline:
    """Runs one configuration over a scan source."""

    def __init__(
        self,
        config: SlamConfig,
        *,
        frontend: Any = None,
        backend: Any = None,
        factor_sources: list[FactorSource] | None = None,
        observers: Iterable[Any] = (),
    ):
        self.config = config
        # watchers of the run (``slam.viz``: on_frame, on_keyframe, on_loop, on_optimised)
        self.observers = list(observers)
        self.frontend = frontend or plugins.instantiate(
            "slam.frontends", config.frontend, "frontend"
        )
        self.backend = backend or plugins.instantiate("slam.backends", config.backend, "backend")
        self.factor_sources = (
            factor_sources if factor_sources is not None else build_factor_plugins(config.factors)
        )
        self.state = RunState()
        self.beams: Any = None  # slam.sensor.BeamModel once estimated from the first scans
        self._buffer: list[Scan] = []  # the first scans, held until the beam model exists
        self._period = 0.1  # sweep period (s): median stamp step of the first scans
        # per-point time from the layout for beam-by-beam clouds without one: only when asked
        # for (KITTI-style clouds, in folders or bags, are published motion-compensated)
        self._layout_time = config.source.layout_time == "always"
        self._estimate_cache: dict[int, np.ndarray] = {}  # cleared on every back-end update
        self._pending: tuple[int, np.ndarray] | None = None  # new keyframe: initial guess
        self._frame_stages: dict[str, float] = {}  # seconds per stage in the current step
        self._frame_stages_cpu: dict[str, float] = {}  # CPU seconds of the same
        self._backend_failed = False  # an update failed: the run stops, outputs are written
        # scans not after the last kept one, in a row, with that last stamp: skipped when a
        # scan in order comes, or the clock stepped back (STAMP_RUN_LIMIT of them)
        self._held_back: list[tuple[Scan, float]] = []
        self._offset = 0.0  # s added to every stamp since the clock stepped back
        self._notes: list[str] | None = None  # the source's notes (a clock step is noted)
        self._clock = config.source.stamps  # "auto" | "header" | "record"
        self._has_record = False  # the source has a second clock (bags: the record time)
        self._reorder: Reorder | None = None  # the reorder buffer in front of the run
        self.view = GraphView(self.state.keyframes, self._estimate)

    # ------------------------------------------------------------------ graph view
    def _estimate(self, kf_id: int) -> np.ndarray:
        if self._pending is not None and kf_id == self._pending[0]:
            return self._pending[1]
        cached = self._estimate_cache.get(kf_id)
        if cached is None:
            cached = self._estimate_cache[kf_id] = self.backend.pose(kf_id).matrix()
        return cached

    # ------------------------------------------------------------------ sensor
    def _estimate_beams(self, scans: list[Scan]) -> None:
        """The beam table from the first scans: the ring field when the driver gives one,
        else the point layout / elevation histogram (slam.sensor). Logged once."""
        from slam.sensor import beams_from_rings, estimate_beams

        scans = [s for s in scans if len(s) >= 100]  # empty / nearly empty scans tell nothing
        try:
            if not scans:
                raise InputError("no scan with points among the first ones")
            if all(s.ring is not None for s in scans):
                self.beams = beams_from_rings([s.xyz for s in scans], [s.ring for s in scans])
            else:
                self.beams = estimate_beams([s.xyz for s in scans])
        except (InputError, ValueError, IndexError) as exc:  # e.g. a 2D laser: no beams
            log.info("no beam model: %s", exc)
            self.beams = False
            return
        self.state.sensor = self.beams.describe()
        log.info("sensor: %s", self.state.sensor)

    def _with_rings(self, scan: Scan) -> Scan:
        """Fill what the driver left out: the ring from the beam table and, for clouds
        stored beam by beam in firing order, the per-point time from the azimuth."""
        if not (self.beams and len(scan)):
            return scan
        need_ring = scan.ring is None
        need_time = scan.time is None and self.beams.layout and self._layout_time
        if need_ring or need_time:  # one pass: the azimuth computed once for both
            ring, t = self.beams.fill(scan.xyz, self._period, ring=need_ring, time=need_time)
            if need_ring:
                scan.ring = ring
            if need_time:
                scan.time = t
        return scan

    def _feed(self, scan: Scan) -> None:
        """Hold the first ``source.beam_scans`` scans until the beam model exists."""
        n = self.config.source.beam_scans
        if self.beams is None and n > 0:
            self._buffer.append(scan)
            if len(self._buffer) >= n:
                self._flush()
            return
        self.step(self._with_rings(scan))

    def _flush(self) -> None:
        """Estimate the beam model from the held scans (if not yet), then process them."""
        if not self._buffer:
            return
        if self.beams is None:
            stamps = np.array([s.stamp for s in self._buffer])
            if len(stamps) > 1 and 0.0 < np.median(np.diff(stamps)) < 1.0:
                self._period = float(np.median(np.diff(stamps)))  # the sweep period (s)
            self._estimate_beams(self._buffer)
        held, self._buffer = self._buffer, []
        for scan in held:
            self.step(self._with_rings(scan))

    # ------------------------------------------------------------------ per frame
    def step(self, scan: Scan) -> None:
        """Process one scan through front end, factor plugins and back end (O(1) per frame:
        nothing here scans the frames or keyframes so far)."""
        st = self.state
        t0, c0 = time.perf_counter(), time.process_time()
        odom = self.frontend.process(scan)
        self._timed("frontend", time.perf_counter() - t0, time.process_time() - c0)
        if odom.extras.get("skipped"):
            st.skipped_frames += 1
        if odom.extras.get("degenerate"):
            st.degenerate_frames += 1
        st.add_diagnostics(odom.extras)
        if odom.is_keyframe or not st.keyframes:
            self._add_keyframe(scan, odom)
        kf = st.keyframes[-1]
        pose = np.asarray(odom.pose, dtype=float)
        if st.odom_poses:
            st.path_length += float(np.linalg.norm(pose[:3, 3] - st.odom_poses[-1][:3, 3]))
        # appended together so that an interrupt never leaves the per-frame lists ragged
        st.stamps.append(float(scan.stamp))
        st.odom_poses.append(pose)
        st.frame_kf.append(kf.id)
        st.T_kf_frame.append(np.linalg.solve(kf.pose_odom, pose))
        st.frame_seconds.append(time.perf_counter() - t0)
        st.frame_cpu_seconds.append(time.process_time() - c0)
        self._close_frame_stages()
        for obs in self.observers:
            obs.on_frame(st.frames - 1, scan, odom)
        if st.frames == MEMORY_REFERENCE_FRAME:
            from slam.outputs import peak_memory_mb

            st.memory_reference = (peak_memory_mb(), st.path_length)

    def _timed(self, stage: str, seconds: float, cpu: float = 0.0) -> None:
        st = self.state
        st.stage_seconds[stage] += seconds
        st.stage_max_seconds[stage] = max(st.stage_max_seconds[stage], seconds)
        self._frame_stages[stage] = self._frame_stages.get(stage, 0.0) + seconds
        self._frame_stages_cpu[stage] = self._frame_stages_cpu.get(stage, 0.0) + cpu

    def _close_frame_stages(self) -> None:
        """Append this frame's seconds per stage to ``state.stage_frame_seconds`` (0 for a
        stage that did not run; a stage seen for the first time is 0 on earlier frames)."""
        st = self.state
        n = len(st.frame_seconds)
        for per_frame, out in ((self._frame_stages, st.stage_frame_seconds),
                               (self._frame_stages_cpu, st.stage_frame_cpu_seconds)):  # fmt: skip
            for stage in per_frame:
                if stage not in out:
                    out[stage] = array("d", bytes(8 * (n - 1)))
            for stage, series in out.items():
                series.append(per_frame.get(stage, 0.0))
        self._frame_stages, self._frame_stages_cpu = {}, {}

    def _add_keyframe(self, scan: Scan, odom: Any) -> None:
        st = self.state
        kf_id = len(st.keyframes)
        kf = Keyframe(
            id=kf_id,
            stamp=float(scan.stamp),
            frame_index=len(st.stamps),
            pose_odom=np.asarray(odom.pose, dtype=float),
            relative=np.asarray(odom.relative, dtype=float),
            info=np.asarray(odom.info, dtype=float),
            cloud=keyframe_cloud(odom.cloud),
            extras=scalar_extras(odom.extras),
        )
        t_guess, c_guess = time.perf_counter(), time.process_time()  # back-end time too
        if kf_id == 0:
            initial_T = kf.pose_odom
        else:
            initial_T = self._estimate(kf_id - 1) @ kf.relative
        t_guess, c_guess = time.perf_counter() - t_guess, time.process_time() - c_guess
        st.keyframes.append(kf)
        for obs in self.observers:
            obs.on_keyframe(kf_id, kf.frame_index, kf.pose_odom, kf.cloud)
        self._pending = (kf_id, initial_T)
        factors: list[Any] = []
        loop_closed = False
        for source in self.factor_sources:
            t0, c0 = time.perf_counter(), time.process_time()
            new = list(source.plugin.on_keyframe(kf, self.view))
            self._timed(f"factor:{source.name}", time.perf_counter() - t0, time.process_time() - c0)
            st.factor_counts[source.name] += len(new)
            if new and source.is_loop:
                loop_closed = True
                st.loops_closed += len(new)
                self._observe_loops(new)
            factors.extend(new)
        t0, c0 = time.perf_counter(), time.process_time()
        self._backend_update(factors, {kf_id: pose3(initial_T)}, loop_closed)
        dt = time.perf_counter() - t0 + t_guess
        self._timed("backend", dt, time.process_time() - c0 + c_guess)
        st.backend_seconds.append(dt)
        self._estimate_cache = {}
        self._pending = None
        if loop_closed:
            self._observe_optimised()
        self._graph_feedback()

    def _graph_feedback(self) -> None:
        """The front end's optional ``on_graph_update(view)``, called after each back-end
        update of a keyframe with the graph view (``view.estimate`` gives the optimised
        poses): a front end that keeps maps (``dpcr2d``) moves them, and its pose, to where
        the graph put them. Front ends without the method are not touched."""
        hook = getattr(self.frontend, "on_graph_update", None)
        if callable(hook):
            t0, c0 = time.perf_counter(), time.process_time()
            hook(self.view)
            self._timed("frontend_feedback", time.perf_counter() - t0, time.process_time() - c0)

    def _backend_update(self, factors: list[Any], initial: dict[int, Any], loop: bool) -> None:
        """``backend.update``; a failure stops the run (``BackendError``) with what it has."""
        try:
            self.backend.update(factors, initial, loop_closed=loop)
        except (InputError, ConfigError):
            raise
        except (SlamError, RuntimeError, ValueError) as exc:
            self._backend_failed = True
            raise BackendError(str(exc).strip().splitlines()[0]) from exc

    def _recovered_estimate(self) -> dict[int, Any]:
        """After a failed update the incremental solver's state cannot be trusted: the
        factors it had taken before (``backend.graph()`` / ``values()``, when it keeps
        them) go through the batch back end (Levenberg-Marquardt); keyframes without an
        estimate then keep their odometry pose (``finish``)."""
        graph, values = getattr(self.backend, "graph", None), getattr(self.backend, "values", None)
        if not (callable(graph) and callable(values)):
            return {}
        g, v = graph(), values()
        initial = {k.id: v.atPose3(key(k.id)) for k in self.state.keyframes if v.exists(key(k.id))}
        batch = plugins.instantiate("slam.backends", {"name": "batch"}, "backend")
        try:
            batch.update([g.at(i) for i in range(g.size())], initial)
            return batch.finalize()
        except SlamError as exc:
            log.warning("batch re-optimisation after the back-end failure failed too (%s): "
                        "the keyframes keep their odometry poses", exc)  # fmt: skip
            return {}

    # ------------------------------------------------------------------ whole run
    def _skip(self, item: SkippedMessage, strict: bool) -> None:
        """Count a message that cannot be used; one warning per reason (``strict``: stop)."""
        if strict:
            raise InputError(f"message {item.index}: {item.detail} (--strict stops at the first)")
        st = self.state
        if st.skipped_messages[item.reason] == 0:
            log.warning(
                "skipping message %d: %s (further '%s' messages are skipped and counted "
                "without a warning)",
                item.index,
                item.detail,
                item.reason,
            )
        st.skipped_messages[item.reason] += 1

    def _consume(self, item: Scan | SkippedMessage, strict: bool) -> None:
        """One input item: a damaged message is skipped; a scan whose stamp is not after the
        last one is held back until the next scan in order (then skipped) or until
        STAMP_RUN_LIMIT of them in a row show that the clock stepped back."""
        if isinstance(item, SkippedMessage):
            self._skip(item, strict)
            return
        if self._offset:
            item.stamp = float(item.stamp) + self._offset
        self._place(item, strict)

    def _place(self, item: Scan, strict: bool) -> None:
        """A scan on the run's clock: fed on, or held back when not after the last one."""
        last = self._last_stamp()
        if last is not None and not float(item.stamp) > last:
            if strict:
                self._skip(self._out_of_order(item, last), strict)
            self._held_back.append((item, last))
            if len(self._held_back) >= STAMP_RUN_LIMIT:
                self._clock_stepped_back()
            return
        self._settle_held_back()
        self._feed(item)

    def _last_stamp(self) -> float | None:
        st = self.state
        return self._buffer[-1].stamp if self._buffer else (st.stamps[-1] if st.stamps else None)

    @staticmethod
    def _out_of_order(item: Scan, last: float) -> SkippedMessage:
        kind = "duplicated stamp" if item.stamp == last else "stamp out of order"
        detail = (
            f"stamp {item.stamp:.9f} s is not after the previous scan's {last:.9f} s"
            " (dropped: the trajectory is never written out of order)"
        )
        return SkippedMessage(item.index, kind, detail)

    def _settle_held_back(self) -> None:
        """The scans held back were out of order: skipped and counted."""
        for scan, last in self._held_back:
            self._skip(self._out_of_order(scan, last), False)
        self._held_back = []

    def _clock_stepped_back(self) -> None:
        """STAMP_RUN_LIMIT scans in a row not after the last kept one. When their stamps go
        on at the sweep period, the clock stepped back (a PTP/NTP correction, a driver that
        restarted its clock): unless ``source.stamps`` is "header" (stamps exactly as
        recorded), every scan from there on is stamped on the run's clock (the step added,
        one warning), the held scans included. Else, or forced, the run stops (bad input)."""
        run = [scan for scan, _ in self._held_back]
        t = np.array([scan.stamp for scan in run])
        step = np.diff(t)
        steady = bool(np.all(step > 0) and 0.5 < np.median(step) / self._period < 1.5)
        if not steady or self._clock in ("header", "record"):
            raise InputError(self._stamps_gone_wrong(self._held_back[-1][1], steady))
        # the reorder buffer holds the scans recorded before the step (after the last kept
        # one) and maybe some after it: those before go first, as they are
        last = self._last_stamp()
        held = self._reorder.drain() if self._reorder is not None else []
        before = [scan for scan in held if scan.stamp > last]
        later = [scan for scan in held if not scan.stamp > last]
        for scan in before:
            self._feed(scan)
        last = self._last_stamp()
        offset = last + self._period - float(t[0])
        self._offset += offset
        log.warning(
            "the clock of the stamps stepped back by %.3f s at message %d (%.9f s after "
            "%.9f s): this and every later scan is stamped %.3f s later, on the clock of the "
            "scans before (set source.stamps=header to stop instead)",
            offset - self._period, run[0].index, t[0], last, offset,
        )  # fmt: skip
        self.state.clock_steps.append((run[0].index, offset))
        for scan in later:
            scan.stamp = float(scan.stamp) + self._offset
        for scan in run:
            scan.stamp = float(scan.stamp) + offset
        self._held_back = []
        if self._notes is not None:
            self._notes.append(
                f"the clock of the stamps stepped back by {offset - self._period:.3f} s at "
                f"message {run[0].index}: the scans from there on are stamped {offset:.3f} s "
                "later than their header stamps"
            )
        for scan in sorted(run + later, key=lambda s: s.stamp):
            self._place(scan, False)

    def _stamps_gone_wrong(self, last: float, steady: bool) -> str:
        """The message of a run stopped by STAMP_RUN_LIMIT stamps in a row not after ``last``
        (``steady``: they go on at the sweep period, the run was told to keep them as is)."""
        run = [(scan.index, float(scan.stamp)) for scan, _ in self._held_back]
        (i0, t0), (i1, t1) = run[0], run[-1]
        n = len(run)
        if t0 == t1 == last:
            how = f"all equal the last kept scan's ({last:.9f} s): the stamps are not set?"
        else:
            how = (
                f"all before the last kept scan's ({last:.9f} s; the first one by "
                f"{last - t0:.3f} s): "
            )
            how += (
                f"the clock stepped back and source.stamps={self._clock} takes them as they are."
                if steady
                else "and not at the sweep period: the clock is broken?"
            )
        if self._clock == "record":
            advice = "the bag's record times repeat: try --set source.stamps=header"
        elif steady:
            advice = "--set source.stamps=auto goes on across the step"
        elif self._has_record:
            advice = "use the bag's record time instead: --set source.stamps=record"
        else:
            advice = "give the input increasing stamps"
        return (
            f"the stamps of the last {n} messages ({i0} to {i1}) are {how} Every further "
            f"scan would be dropped, so the run stops here; {advice}"
        )

    def run(
        self,
        scans: Iterable[Scan | SkippedMessage],
        *,
        on_frame: Callable[[int], None] | None = None,
        max_frames: int | None = None,
        start: int = 0,
        strict: bool = False,
    ) -> RunState:
        """Process ``scans`` until exhausted, ``max_frames``, Ctrl-C or unreadable input.

        ``start``: the index of the first input message used (messages before it are read
        and ignored). The source stamps with the clock ``source.stamps`` picks (bags: header
        stamp or record time, ``slam.io.stamps``); ``source.reorder_window`` scans are held
        and released in stamp order, so that messages recorded a few places out of order are
        kept. A :class:`SkippedMessage` (damaged message, no finite point) and a scan whose
        stamp is still not after the previous one (duplicated, out of order) cost that frame
        only: counted by reason in ``state.skipped_messages``; with ``strict`` the first one
        stops the run like unreadable input, and so do STAMP_RUN_LIMIT of them in a row
        without ``strict`` (a clock gone back: the rest of the input would be dropped).
        Ctrl-C (SIGINT, when Python's default handler is
        in place) stops the loop after the frame in hand, a second one at once; a
        KeyboardInterrupt or an InputError from the source stops the loop; the state so far
        is finalised (``state.stopped_by`` says why). Never loses computed frames.
        """
        st = self.state
        src = self.config.source
        notes = getattr(scans, "notes", None)
        self._notes = notes if isinstance(notes, list) else None
        use_stamps = getattr(scans, "use_stamps", None)  # bags: header or record time
        self._has_record = callable(use_stamps)
        self._clock = src.stamps
        if callable(use_stamps):
            use_stamps(src.stamps, src.reorder_window)
        elif src.stamps == "record":
            raise InputError(
                "source.stamps=record: only bags have a record time; this input's stamps "
                "are its own (use source.stamps auto or header)"
            )
        began = time.perf_counter()
        try:
            with StopRequest() as stop:  # Ctrl-C: stop after the frame in hand
                self._reorder = Reorder(islice(scans, start, None), src.reorder_window)
                for n, item in enumerate(self._reorder, 1):
                    if max_frames is not None and st.frames + len(self._buffer) >= max_frames:
                        break
                    self._consume(item, strict)
                    if on_frame is not None:
                        on_frame(n)  # messages consumed (frames and skipped ones)
                    if stop.requested:
                        break
                if stop.requested:
                    st.stopped_by = "interrupted (Ctrl-C)"
                else:
                    self._settle_held_back()  # out-of-order scans at the very end
                    self._flush()  # a source shorter than the beam-model window
        except KeyboardInterrupt:
            st.stopped_by = "interrupted (Ctrl-C)"
        except SystemError as exc:  # Ctrl-C inside a compiled call (numba loading a kernel)
            if not caused_by_interrupt(exc):
                raise
            st.stopped_by = "interrupted (Ctrl-C)"
        except InputError as exc:
            st.stopped_by = f"bad input: {exc}"
            self._flush_held()
        except BackendError as exc:
            log.error("back end failed at keyframe %d: %s", len(st.keyframes) - 1, exc)
            st.stopped_by = f"back end failed: {exc}"
        finally:
            st.wall_seconds += time.perf_counter() - began
            self.finish()
        return st

    def _flush_held(self) -> None:
        """The scans held (reorder buffer, beam model), processed after the input stopped
        with an error (a truncated bag, stamps gone wrong): read frames are not lost."""
        try:
            for scan in self._reorder.drain() if self._reorder is not None else []:
                scan.stamp = float(scan.stamp) + self._offset
                last = self._last_stamp()
                if last is None or scan.stamp > last:
                    self._feed(scan)
            self._settle_held_back()
            self._flush()
        except KeyboardInterrupt:
            st = self.state
            st.stopped_by = st.stopped_by or "interrupted (Ctrl-C)"
        except BackendError as exc:
            log.error("back end failed at keyframe %d: %s", len(self.state.keyframes) - 1, exc)

    def _flush_factor_sources(self) -> None:
        """Factors a plugin still holds at the end (``flush(graph)``, e.g. loops verified in
        a worker process and due after the last keyframe) go into one last update."""
        st = self.state
        if not st.keyframes:
            return
        factors: list[Any] = []
        loop_closed = False
        for source in self.factor_sources:
            flush = getattr(source.plugin, "flush", None)
            if not callable(flush):
                continue
            t0 = time.perf_counter()
            new = list(flush(self.view))
            st.stage_seconds[f"factor:{source.name}"] += time.perf_counter() - t0
            st.factor_counts[source.name] += len(new)
            if new and source.is_loop:
                loop_closed = True
                st.loops_closed += len(new)
                self._observe_loops(new)
            factors.extend(new)
        if factors:
            t0 = time.perf_counter()
            self._backend_update(factors, {}, loop_closed)
            st.stage_seconds["backend"] += time.perf_counter() - t0
            self._estimate_cache = {}

    def finish(self) -> None:
        """Flush the factor plugins, final optimisation; fills ``state.estimates`` for every
        keyframe."""
        st = self.state
        try:
            if not self._backend_failed:
                self._flush_factor_sources()
        except BackendError as exc:
            log.error("back end failed on the last factors: %s", exc)
            st.stopped_by = st.stopped_by or f"back end failed: {exc}"
        finally:
            for source in self.factor_sources:
                close = getattr(source.plugin, "close", None)
                if callable(close):
                    close()
        if not st.keyframes:
            return
        t0 = time.perf_counter()
        est = self._recovered_estimate() if self._backend_failed else self.backend.finalize()
        st.stage_seconds["backend_final"] += time.perf_counter() - t0
        st.estimates = {k: v.matrix() for k, v in est.items()}
        for kf in st.keyframes:  # a keyframe the back end never saw (stopped mid-update)
            if kf.id not in st.estimates:
                st.estimates[kf.id] = kf.pose_odom
        for obs in self.observers:
            obs.on_optimised(st.estimates)

    def _observe_loops(self, factors: list[Any]) -> None:
        """Tell the observers about the keyframe pairs (a, b) of new loop factors."""
        import gtsam

        for obs in self.observers:
            for f in factors:
                a, b = (gtsam.Symbol(k).index() for k in f.keys()[:2])
                obs.on_loop(int(a), int(b))

    def _observe_optimised(self) -> None:
        """Tell the observers the back end's poses of every keyframe after a loop update."""
        if self.observers:
            poses = {k: v.matrix() for k, v in self.backend.estimate().items()}
            for obs in self.observers:
                obs.on_optimised(poses)


def resolved_config(config: SlamConfig) -> dict[str, Any]:
    """The config with every plugin's defaults filled in (what config.yaml records)."""
    import dataclasses

    def section(group: str, params: dict[str, Any], where: str) -> dict[str, Any]:
        params = dict(params)
        spec = params.pop("plugin", None)
        name = params.get("name", where.split(".")[-1])
        cls = plugins.load(group, spec or name)
        cfg = plugins.plugin_config(cls, {k: v for k, v in params.items() if k != "name"}, where)
        full = dataclasses.asdict(cfg) if cfg is not None else {}
        head = {"name": params["name"]} if "name" in params else {}
        if spec:
            head["plugin"] = spec
        return {**head, **full}

    out = config.to_dict()
    out["frontend"] = section("slam.frontends", config.frontend, "frontend")
    out["backend"] = section("slam.backends", config.backend, "backend")
    out["factors"] = {
        name: section("slam.factors", params, f"factors.{name}")
        for name, params in config.factors.items()
    }
    return _plain(out)


def _plain(obj: Any) -> Any:
    """Tuples -> lists, numpy scalars -> Python, so that YAML stays readable."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def caused_by_interrupt(exc: BaseException) -> bool:
    """True when ``exc`` was caused by a KeyboardInterrupt: a C extension (numba's dispatcher,
    its cache loader) that sees Ctrl-C returns an error CPython reports as a SystemError
    whose cause is the KeyboardInterrupt."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
