"""One job at a time on a worker thread, waited for before its result is needed.

A front end hands the map update of scan n to the worker and filters scan n+1 on the
calling thread meanwhile; it waits before it reads the map again. The job's inputs are
not touched until then and its outputs are read only after ``wait``, so the results are
the same as running it inline, whatever the threads' timing (tests/test_same_run_twice.py).
The overlap is real where the job spends its time in numba kernels compiled ``nogil``
and in numpy, which release the GIL.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager

import numba


class Deferred:
    """Runs ``submit``-ted jobs one after another on one worker thread (``threaded=False``:
    inline, at ``submit``). ``wait`` blocks until the last job is done, re-raises its error,
    and returns the seconds spent waiting."""

    def __init__(self, threaded: bool = True, name: str = "deferred"):
        self.threaded = threaded
        self._name = name
        self._pool: ThreadPoolExecutor | None = None
        self._future: Future | None = None

    def submit(self, job: Callable[[], None]) -> None:
        """Run ``job`` after the previous one (the previous one is waited for first)."""
        self.wait()
        if not self.threaded:
            job()
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=self._name)
        self._future = self._pool.submit(job)

    def wait(self) -> float:
        """Block until the submitted job finished; its exception is raised here."""
        future, self._future = self._future, None
        if future is None:
            return 0.0
        t = time.perf_counter()
        future.result()
        return time.perf_counter() - t

    @property
    def pending(self) -> bool:
        return self._future is not None

    def close(self) -> None:
        """Wait for the last job and stop the worker thread."""
        try:
            self.wait()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
                self._pool = None

    def __del__(self) -> None:  # a front end dropped mid-run: do not leave a thread behind
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)


@contextmanager
def numba_threads(n: int | None) -> Iterator[None]:
    """Parallel numba kernels called by this thread use ``n`` threads inside the block
    (None: unchanged). A thread whose partner core is busy with a ``Deferred`` job runs
    its kernels on one thread: two threads there would contend for that core (urban
    VLP-16: 1.19x the frames/s with one)."""
    if n is None:
        yield
        return
    before = numba.get_num_threads()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(before)
