"""Ctrl-C that stops a run between frames, never inside compiled code.

A KeyboardInterrupt raised in the middle of a numba call (a kernel being compiled or loaded
from the cache, an llvmlite callback) does not always arrive as a KeyboardInterrupt: it
can surface as a SystemError or a RuntimeError from the compiler and the run would lose
its outputs. While a run is in progress the first SIGINT only asks it to stop after the
frame in hand; a second one aborts at once (KeyboardInterrupt, as before)."""

from __future__ import annotations

import logging
import signal
import threading

log = logging.getLogger(__name__)


class StopRequest:
    """Context manager: while active in the main thread, the first SIGINT sets
    ``requested`` instead of raising. Leaves SIGINT alone when a caller installed its own
    handler or ignores it (only Python's default handler is replaced, then restored).
    ``message``: the warning the first Ctrl-C logs (what the run does before it stops)."""

    def __init__(self, message: str = "stopping after this frame") -> None:
        self.requested = False
        self.message = message
        self._previous = None

    def __enter__(self) -> StopRequest:
        if (
            threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        ):
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("Ctrl-C: %s (press again to abort at once)", self.message)

    def __exit__(self, *exc) -> bool:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None
        return False


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
