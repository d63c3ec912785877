"""The SLAM system: front end -> factor plugins -> back end, the only place they meet.

``process(scan)`` takes one clean scan (``slam.io.stream``); ``finish()`` flushes the
plugins and optimises a last time. For every frame the system keeps its keyframe and its
pose relative to that keyframe, so that the final trajectory of every frame follows the
optimised keyframes. Algorithms live in the plugins; this is orchestration only.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from slam import plugins
from slam.config import SlamConfig
from slam.errors import BackendError, ConfigError, InputError, SlamError
from slam.factor_sources import FactorSource, build_factor_plugins, loop_pairs
from slam.factors import GraphView, key, pose3
from slam.observer import Observers, RunObserver
from slam.state import MEMORY_REFERENCE_FRAME, RunState, StopReason, peak_memory_mb
from slam.types import Keyframe, Odometry, Scan

log = logging.getLogger(__name__)


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
    """The scalars (numbers, bools, strings) of a flat dict such as ``Odometry.extras``,
    without arrays or private ``_`` entries; for scripts (keyframes keep typed fields)."""
    keep = (bool, int, float, str, np.generic)
    return {k: v for k, v in extras.items() if isinstance(v, keep) and not k.startswith("_")}


class SlamSystem:
    """Front end, factor plugins and back end of one run; ``state`` holds what it computed.

    ``observers`` (``slam.observer.RunObserver``) see every frame, keyframe, loop and
    optimisation; with none nothing is called.
    """

    def __init__(
        self,
        config: SlamConfig,
        *,
        frontend: Any = None,
        backend: Any = None,
        factor_sources: list[FactorSource] | None = None,
        observers: Sequence[RunObserver] = (),
    ):
        self.config = config
        self.frontend = frontend or plugins.instantiate(
            "slam.frontends", config.frontend, "frontend"
        )
        self.backend = backend or plugins.instantiate("slam.backends", config.backend, "backend")
        self.factor_sources = (
            factor_sources if factor_sources is not None else build_factor_plugins(config.factors)
        )
        hook = getattr(self.frontend, "on_factor_plugins", None)
        if callable(hook):  # a front end whose own loop edges need a plugin to take them
            hook([source.plugin for source in self.factor_sources])
        # optional: a front end that can start on the next scan early
        self._look_ahead = getattr(self.frontend, "look_ahead", None)
        self.state = RunState()
        self.timer = self.state.timer
        self.observers = Observers(observers)
        self.view = GraphView(self.state.keyframes, self._estimate)
        self._estimate_cache: dict[int, np.ndarray] = {}  # cleared on every back-end update
        self._pending: tuple[int, np.ndarray] | None = None  # new keyframe: initial guess
        self._backend_failed = False  # an update failed: the run stops, outputs are written
        self._untyped_warned = False  # a front end of an earlier version was named once

    def _estimate(self, kf_id: int) -> np.ndarray:
        """The graph view's pose of a keyframe: the initial guess of the one being added."""
        if self._pending is not None and kf_id == self._pending[0]:
            return self._pending[1]
        cached = self._estimate_cache.get(kf_id)
        if cached is None:
            cached = self._estimate_cache[kf_id] = self.backend.pose(kf_id).matrix()
        return cached

    # ------------------------------------------------------------------ per frame
    def look_ahead(self, scan: Scan) -> None:
        """``scan`` comes after the scans announced before it: the front end may start on it
        (``look_ahead``, optional) while it processes those."""
        if self._look_ahead is not None:
            self._look_ahead(scan)

    def process(self, scan: Scan) -> Odometry:
        """One scan through front end, factor plugins and back end (O(1) per frame:
        nothing here scans the frames or keyframes so far). Raises BackendError when the
        back end cannot take the keyframe (the run stops there, see :meth:`_update`)."""
        st = self.state
        with self.timer.frame():
            with self.timer("frontend"):
                odom = self.frontend.process(scan)
            if odom.diagnostics is None and odom.extras and not self._untyped_warned:
                self._warn_untyped()
            st.add_diagnostics(odom)
            if odom.is_keyframe or not st.keyframes:
                self._add_keyframe(scan, odom)
            self._record_frame(scan, odom)
            if self.observers:
                with self.timer("observers"):
                    self.observers.on_frame(st.frames - 1, scan, odom)
        if st.frames == MEMORY_REFERENCE_FRAME:
            st.memory_reference = (peak_memory_mb(), st.path_length)
        return odom

    def _warn_untyped(self) -> None:
        """One warning for a front end that reports its diagnostics only in the untyped
        ``Odometry.extras`` of earlier versions (the system no longer reads them)."""
        self._untyped_warned = True
        log.warning("front end %s returns Odometry.extras but no Odometry.diagnostics: its "
                    "skipped/degenerate flags and counts are not in metrics.json; fill "
                    "diagnostics (slam.types.FrameDiagnostics) and status instead",
                    type(self.frontend).__name__)  # fmt: skip

    def _record_frame(self, scan: Scan, odom: Odometry) -> None:
        """The frame's stamp, odometry and pose relative to its keyframe."""
        st = self.state
        kf = st.keyframes[-1]
        pose = np.asarray(odom.pose, dtype=float)
        if st.odom_poses:
            st.path_length += float(np.linalg.norm(pose[:3, 3] - st.odom_poses[-1][:3, 3]))
        # appended together so that an interrupt never leaves the per-frame lists ragged
        st.stamps.append(float(scan.stamp))
        st.odom_poses.append(pose)
        st.frame_kf.append(kf.id)
        st.T_kf_frame.append(np.linalg.solve(kf.pose_odom, pose))
        st.frame_spread.append(np.nan if odom.spread is None else float(odom.spread))

    def _add_keyframe(self, scan: Scan, odom: Odometry) -> None:
        """A new keyframe: the factor plugins' factors and its initial guess (the previous
        keyframe's estimate composed with the odometry) go into one back-end update."""
        st = self.state
        kf = Keyframe(
            id=len(st.keyframes),
            stamp=float(scan.stamp),
            frame_index=len(st.stamps),
            pose_odom=np.asarray(odom.pose, dtype=float),
            relative=np.asarray(odom.relative, dtype=float),
            info=np.asarray(odom.info, dtype=float),
            cloud=keyframe_cloud(odom.cloud),
            status=odom.status,
            diagnostics=odom.diagnostics,
            ground_plane=None if odom.ground_plane is None else np.array(odom.ground_plane),
            region=odom.region,
        )
        with self.timer.measure() as guess:  # back-end time too
            initial_T = kf.pose_odom if kf.id == 0 else self._estimate(kf.id - 1) @ kf.relative
        st.keyframes.append(kf)
        self._pending = (kf.id, initial_T)
        if self.observers:
            with self.timer("observers"):
                self.observers.on_keyframe(kf.id, kf.frame_index, kf.pose_odom, kf.cloud)
        factors, loop_closed = self._gather(
            self.factor_sources, lambda plugin: plugin.on_keyframe(kf, self.view)
        )
        with self.timer("backend", plus=guess) as lap:
            self._update(factors, {kf.id: pose3(initial_T)}, loop_closed)
        st.backend_seconds.append(lap.wall)
        self._pending = None
        self._optimised()
        hook = getattr(self.frontend, "on_graph_update", None)
        if callable(hook):  # a front end that keeps maps (dpcr2d) moves them to the graph
            with self.timer("frontend_feedback"):
                hook(self.view)

    def _gather(
        self, sources: list[FactorSource], call: Callable[[Any], Iterable[Any]]
    ) -> tuple[list[Any], bool]:
        """The new factors of ``call(plugin)`` for every source (timed and counted by
        name), and whether a loop plugin gave any."""
        st = self.state
        factors: list[Any] = []
        loop_closed = False
        for source in sources:
            with self.timer(f"factor:{source.name}"):
                new = list(call(source.plugin))
            st.factor_counts[source.name] += len(new)
            if new and source.is_loop:
                loop_closed = True
                st.loops_closed += len(new)
                pairs = loop_pairs(new)
                st.loop_pairs.extend(pairs)
                if self.observers:
                    with self.timer("observers"):
                        for a, b in pairs:
                            self.observers.on_loop(a, b)
            factors.extend(new)
        return factors, loop_closed

    def _update(self, factors: list[Any], initial: dict[int, Any], loop_closed: bool) -> None:
        """``backend.update``. A failure is handled here, once: logged, recorded as the
        run's stop, the last estimate then re-optimised in batch (:meth:`finish`), and a
        BackendError raised so that the run stops with what it has."""
        try:
            self.backend.update(factors, initial, loop_closed=loop_closed)
        except (InputError, ConfigError):
            raise
        except (SlamError, RuntimeError, ValueError) as exc:
            self._backend_failed = True
            message = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            log.error("back end failed at keyframe %d: %s", len(self.state.keyframes) - 1, message)
            self.state.stopped(StopReason.BACKEND_FAILED, message)
            raise BackendError(message) from exc
        self._estimate_cache = {}

    def _optimised(self, poses: dict[int, np.ndarray] | None = None) -> None:
        """Show the observers the optimised keyframes (``poses``, default the back end's)."""
        if self.observers:
            with self.timer("observers"):
                if poses is None:
                    poses = {k: p.matrix() for k, p in self.backend.estimate().items()}
                self.observers.on_optimised(poses)

    # ------------------------------------------------------------------ end of the run
    def finish(self) -> None:
        """Flush the factor plugins, final optimisation; fills ``state.estimates`` for every
        keyframe. Closes the plugins and the observers."""
        st = self.state
        try:
            if not self._backend_failed:
                self._flush_factor_sources()
        except BackendError:
            pass  # recorded by _update: the estimate so far is kept
        finally:
            for source in self.factor_sources:
                close = getattr(source.plugin, "close", None)
                if callable(close):
                    close()
        try:
            if st.keyframes:
                with self.timer("backend_final"):
                    failed = self._backend_failed
                    est = self._recovered_estimate() if failed else self.backend.finalize()
                st.estimates = {k: v.matrix() for k, v in est.items()}
                for kf in st.keyframes:  # a keyframe the back end never saw (stopped mid-update)
                    st.estimates.setdefault(kf.id, kf.pose_odom)
                self._optimised(dict(st.estimates))
        finally:
            self.observers.close()

    def _flush_factor_sources(self) -> None:
        """Factors a plugin still holds at the end (``flush(graph)``, e.g. loops verified in
        a worker process and due after the last keyframe) go into one last update."""
        if not self.state.keyframes:
            return
        sources = [s for s in self.factor_sources if callable(getattr(s.plugin, "flush", None))]
        factors, loop_closed = self._gather(sources, lambda plugin: plugin.flush(self.view))
        if factors:
            with self.timer("backend"):
                self._update(factors, {}, loop_closed)
            self._optimised()

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
