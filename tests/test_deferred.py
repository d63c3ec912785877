"""slam.deferred: jobs run in order on one worker, their errors surface at wait, and the
numba thread count is scoped to the block."""

import threading

import numba
import pytest

from slam.deferred import Deferred, numba_threads


@pytest.mark.parametrize("threaded", [True, False])
def test_jobs_run_in_order_and_wait_sees_their_results(threaded):
    out: list[int] = []
    job = Deferred(threaded)
    for i in range(5):
        job.submit(lambda i=i: out.append(i))
    job.wait()
    assert out == [0, 1, 2, 3, 4]
    assert not job.pending
    job.close()


def test_a_job_runs_off_the_calling_thread_and_its_error_is_raised_at_wait():
    seen = []
    job = Deferred(True)
    job.submit(lambda: seen.append(threading.current_thread() is threading.main_thread()))
    job.wait()
    assert seen == [False]

    def fail():
        raise ValueError("broken map")

    job.submit(fail)
    with pytest.raises(ValueError, match="broken map"):
        job.wait()
    assert job.wait() == 0.0  # raised once, then nothing is pending
    job.close()


def test_numba_threads_is_scoped_to_the_block():
    before = numba.get_num_threads()
    with numba_threads(1):
        assert numba.get_num_threads() == 1
    assert numba.get_num_threads() == before
    with numba_threads(None):
        assert numba.get_num_threads() == before
