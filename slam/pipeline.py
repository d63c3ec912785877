"""Running a SLAM system over a scan stream: the run loop, its early stops and Ctrl-C.

``run_stream(system, stream)`` feeds the stream's clean scans (``slam.io.stream``) to the
system (``slam.system``) and always finishes it, whatever stopped the loop. ``Pipeline``
is the two in one object, for scripts and tests: a SlamSystem with ``run(scans)``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from slam import plugins
from slam.config import SlamConfig
from slam.errors import BackendError, InputError
from slam.factor_sources import FactorSource, build_factor_plugins
from slam.interrupts import StopRequest, caused_by_interrupt
from slam.io.stream import STAMP_RUN_LIMIT, ScanStream
from slam.state import MEMORY_REFERENCE_FRAME, RunState, Stop, StopReason
from slam.system import SlamSystem, keyframe_cloud, scalar_extras
from slam.types import Scan, SkippedMessage

__all__ = [
    "MEMORY_REFERENCE_FRAME",
    "STAMP_RUN_LIMIT",
    "FactorSource",
    "Pipeline",
    "RunState",
    "Stop",
    "StopReason",
    "build_factor_plugins",
    "caused_by_interrupt",
    "keyframe_cloud",
    "resolved_config",
    "run_stream",
    "scalar_extras",
]


def run_stream(
    system: SlamSystem, stream: ScanStream, *, on_message: Callable[[int], None] | None = None
) -> RunState:
    """Process ``stream`` until exhausted, Ctrl-C, unreadable input or a back-end failure;
    then ``system.finish()``. Returns ``system.state`` (``stop`` says why it ended early).

    Ctrl-C (SIGINT, when Python's default handler is in place) stops the loop after the
    message in hand, a second one at once (during ``finish`` the first one waits for it);
    bad input (an InputError of the source, the stream or a plugin) first processes the
    scans the stream still holds. Never loses computed frames. ``on_message(n)``: input
    messages consumed so far (progress).
    """
    st = system.state
    began = time.perf_counter()
    held = _Held(system)
    try:
        with StopRequest() as stop:  # Ctrl-C: stop after the message in hand
            for item in stream.items(stop=lambda: stop.requested, on_message=on_message):
                if isinstance(item, Scan):
                    held.push(item)
            if stop.requested:  # the scan read ahead is dropped like the reorder buffer
                st.stopped(StopReason.INTERRUPTED)
            else:
                held.flush()
    except KeyboardInterrupt:
        st.stopped(StopReason.INTERRUPTED)
    except SystemError as exc:  # Ctrl-C inside a compiled call (numba loading a kernel)
        if not caused_by_interrupt(exc):
            raise
        st.stopped(StopReason.INTERRUPTED)
    except InputError as exc:
        st.stopped(StopReason.BAD_INPUT, str(exc))
        _drain(system, stream, held)
    except BackendError:
        pass  # recorded by the system where it failed
    finally:
        st.wall_seconds += time.perf_counter() - began
        with StopRequest("finishing the run first (the final optimisation)") as late:
            system.finish()
        if late.requested and st.stop is None:
            st.stopped(StopReason.INTERRUPTED)
    return st


class _Held:
    """One scan held back: each scan is announced to the system (``look_ahead``) when it
    is read and processed after the next one is read, so the front end can start on the
    next scan while it processes this one."""

    def __init__(self, system: SlamSystem):
        self._system = system
        self._scan: Scan | None = None

    def push(self, scan: Scan) -> None:
        self._system.look_ahead(scan)
        held, self._scan = self._scan, scan
        if held is not None:
            self._system.process(held)

    def flush(self) -> None:
        held, self._scan = self._scan, None
        if held is not None:
            self._system.process(held)


def _drain(system: SlamSystem, stream: ScanStream, held: _Held) -> None:
    """The scan held back and the scans the stream holds, processed after the input
    stopped with an error."""
    try:
        held.flush()
        for item in stream.drain():
            if isinstance(item, Scan):
                system.process(item)
    except KeyboardInterrupt:
        system.state.stopped(StopReason.INTERRUPTED)
    except BackendError:
        pass  # recorded by the system where it failed


class Pipeline(SlamSystem):
    """A SLAM system that runs a whole scan source: ``Pipeline(config).run(scans)``."""

    stream: ScanStream | None = None

    def run(
        self,
        scans: Iterable[Scan | SkippedMessage],
        *,
        on_frame: Callable[[int], None] | None = None,
        max_frames: int | None = None,
        start: int = 0,
        strict: bool = False,
    ) -> RunState:
        """Process ``scans`` until exhausted, ``max_frames``, Ctrl-C or unreadable input
        (:func:`run_stream`); the stream (``slam.io.stream.ScanStream``) stamps, orders,
        skips and fills them per the config's ``source`` section, starting at message
        ``start``; ``strict``: the first skipped message or bad stamp stops the run as bad
        input. ``on_frame(n)``: input messages consumed so far."""
        self.stream = ScanStream(
            scans,
            self.config.source,
            start=start,
            max_frames=max_frames,
            strict=strict,
            stats=self.state.input,
        )
        return run_stream(self, self.stream, on_message=on_frame)

    @property
    def beams(self) -> Any:
        """The stream's beam model (None before a run, False when none could be made)."""
        return None if self.stream is None else self.stream.beams


def resolved_config(config: SlamConfig) -> dict[str, Any]:
    """The config with every plugin's defaults filled in (what config.yaml records)."""

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
