"""Loop verification as self-contained jobs, run in the pipeline's process or in a worker.

A :class:`KeyframeJob` holds everything verifying one keyframe's candidates needs (the
clouds, the initial guesses and the odometry-gate data snapshotted when it was made), so
:func:`run_job` is a pure function: the same job gives the same results in this process
or in a worker process. :class:`VerifyPool` runs jobs in worker processes (spawned:
small_gicp's registration holds the GIL, so a thread would not run beside the front end;
a script without an ``if __name__ == "__main__":`` guard is not run again in them)
and hands each result back at the job's ``due`` keyframe, waiting for it there if needed:
which loop enters the graph at which keyframe never depends on timing, so runs are
reproducible.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import signal
import sys
import time
import types
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

import numpy as np

from slam.loop.search import Candidate
from slam.loop.verify import VerifyParams, VerifyResult, verify, wrap_angle, yaw_of

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OdometryGate:
    """The odometry-consistency gate of one candidate, from the estimates when it was
    proposed: T_est (4x4, T_candidate_current of the estimates), allowed (m: base + ratio x
    travelled), travelled (m), max_yaw_deg; ``enabled`` False lets every result through."""

    T_est: np.ndarray
    allowed: float
    travelled: float
    max_yaw_deg: float
    enabled: bool = True


def odometry_inconsistency(gate: OdometryGate, T_cand_cur: np.ndarray) -> str:
    """Why a registered loop contradicts the odometry (empty string when it does not): it may
    move the current keyframe at most ``allowed`` m from the estimate relative to the
    candidate and turn it at most ``max_yaw_deg``."""
    if not gate.enabled:
        return ""
    jump = float(np.linalg.norm(gate.T_est[:3, 3] - T_cand_cur[:3, 3]))
    if jump > gate.allowed:
        return (
            f"inconsistent with odometry: moves {jump:.1f} m from the estimate "
            f"(allowed {gate.allowed:.1f} m after {gate.travelled:.0f} m)"
        )
    turn = abs(np.degrees(wrap_angle(yaw_of(T_cand_cur) - yaw_of(gate.T_est))))
    if turn > gate.max_yaw_deg:
        return (
            f"inconsistent with odometry: turns {turn:.0f} deg from the estimate "
            f"(allowed {gate.max_yaw_deg:.0f} deg)"
        )
    return ""


@dataclass
class CandidateJob:
    """One candidate: its search result, the initial T_candidate_current, the target cloud
    (None when ``skip`` says why no registration could pass the gates) and its gate."""

    cand: Candidate
    init: np.ndarray
    gate: OdometryGate
    target: np.ndarray | None = None
    skip: str = ""
    T_odom: np.ndarray | None = None  # the candidate's front-end pose (pairwise check)
    travel: float = 0.0  # its odometric distance from the start (m)


@dataclass
class KeyframeJob:
    """A keyframe's candidates to verify, best first, against its ``source`` cloud (None when
    every candidate is skipped); ``due``: the keyframe id whose update receives the result."""

    kf_id: int
    stamp: float
    candidates: list[CandidateJob]
    source: np.ndarray | None
    due: int
    future: Future | None = field(default=None, repr=False, compare=False)
    T_odom: np.ndarray | None = None  # the keyframe's front-end pose (pairwise check)
    travel: float = 0.0  # its odometric distance from the start (m)

    def payload(self) -> KeyframeJob:
        """The job without its future (what is sent to a worker)."""
        return KeyframeJob(
            self.kf_id, self.stamp, self.candidates, self.source, self.due, None,
            self.T_odom, self.travel,
        )  # fmt: skip


def run_job(job: KeyframeJob, params: VerifyParams) -> list[tuple[VerifyResult, float]]:
    """Verify the candidates in order until one passes both the registration's and the
    odometry gates; returns (result, registration ms or -1 when skipped) per candidate
    tried. Pure: the same job gives the same results in any process."""
    out: list[tuple[VerifyResult, float]] = []
    for cj in job.candidates:
        if cj.skip:
            res = VerifyResult(
                False, cj.init, np.inf, 0.0, np.degrees(cj.cand.yaw), np.zeros((6, 6)), cj.skip
            )
            out.append((res, -1.0))
            continue
        t0 = time.perf_counter()
        res = verify(cj.target, job.source, cj.init, params)
        ms = 1e3 * (time.perf_counter() - t0)
        if res.accepted:
            res.reason = odometry_inconsistency(cj.gate, res.T_target_source)
            res.accepted = not res.reason
        out.append((res, ms))
        if res.accepted:
            break
    return out


@contextlib.contextmanager
def _main_hidden():
    """``__main__`` is a blank module while workers spawn. A job needs nothing of the main
    module (run_job and the job classes are imported by name), but a spawned worker runs the
    main script again unless the script guards its body with ``if __name__ == "__main__":``;
    a script that drives the pipeline without that guard would run its whole pipeline once
    more inside the worker, and every job would wait for it."""
    main = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")  # no __file__, no __spec__
    try:
        yield
    finally:
        if main is not None:
            sys.modules["__main__"] = main


@contextlib.contextmanager
def _spawning():
    """Around any call that may start a worker: ``__main__`` hidden (:func:`_main_hidden`)
    and SIGINT blocked in this thread, so that a worker starts with SIGINT blocked (a new
    process inherits the signal mask) until :func:`_worker_init` ignores it. Ctrl-C reaches
    the whole process group: a worker that took it while importing or verifying would die
    or hand a KeyboardInterrupt back as its result; the parent alone decides when to stop.
    A SIGINT meanwhile is not lost: another thread of this process takes it, or it waits
    until the block ends."""
    mask = getattr(signal, "pthread_sigmask", None)  # absent on Windows
    blocked = mask is not None and signal.SIGINT not in mask(signal.SIG_BLOCK, ())
    if blocked:
        mask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        with _main_hidden():
            yield
    finally:
        if blocked:
            mask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _worker_init() -> None:
    """A worker ignores SIGINT (the parent stops the run and collects the jobs), verifies
    with one thread and logs nothing of its own."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # discards a SIGINT pending since the spawn
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    logging.getLogger().setLevel(logging.WARNING)


class VerifyPool:
    """Worker processes that run :func:`run_job`; results are taken at the due keyframe.

    The pool starts on the first job. A worker that dies (BrokenProcessPool) costs no loop:
    its jobs are run here instead, with the same result.
    """

    def __init__(self, workers: int, params: VerifyParams):
        self.workers, self.params = workers, params
        self._pool: ProcessPoolExecutor | None = None
        self._unavailable = False  # no worker could start: jobs run in-process
        self.wait_ms = 0.0  # time the pipeline waited for due results (ms)

    def start(self) -> None:
        """Start the workers now (a spawned worker imports numpy, scipy and small_gicp for a
        second or more: started at the first keyframe, it is ready by the first candidate)."""
        if self._pool is not None or self._unavailable:
            return
        try:
            self._pool = ProcessPoolExecutor(
                self.workers, mp_context=multiprocessing.get_context("spawn"),
                initializer=_worker_init,
            )  # fmt: skip
            with _spawning():
                for _ in range(self.workers):
                    self._pool.submit(_worker_init)  # processes start on the first submit
            log.info("loop verification: %d worker process(es) started", self.workers)
        except (BrokenProcessPool, RuntimeError, AssertionError, OSError) as exc:
            log.warning("loop verification worker unavailable (%s): verifying in-process", exc)
            self._unavailable = True

    def submit(self, job: KeyframeJob) -> None:
        """Start the job in a worker; where no worker can start (e.g. inside a daemonic
        process), it runs in-process at its due keyframe instead (same result)."""
        job.future = None
        self.start()
        if self._unavailable:
            return
        try:
            with _spawning():  # the executor may start a process on any submit
                job.future = self._pool.submit(run_job, job.payload(), self.params)
        except (BrokenProcessPool, RuntimeError) as exc:
            log.warning("loop verification worker unavailable (%s): verifying in-process", exc)
            self._unavailable = True

    def result(self, job: KeyframeJob) -> list[tuple[VerifyResult, float]]:
        """The job's results, waiting for the worker if it is not done yet."""
        if job.future is not None:
            t0 = time.perf_counter()
            try:
                return job.future.result()
            except BrokenProcessPool as exc:
                log.warning("loop verification worker died (%s): verifying in-process", exc)
            finally:
                self.wait_ms += 1e3 * (time.perf_counter() - t0)
                job.future = None
        return run_job(job, self.params)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=False)
            self._pool = None
