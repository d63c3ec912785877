"""The stage timer (slam/timing.py): totals, slowest calls and per-frame series."""

from __future__ import annotations

import time

import pytest

from slam.timing import StageTimer


def test_stages_in_frames_are_aligned_series_and_outside_only_totals():
    timer = StageTimer()
    for i in range(3):
        with timer.frame():
            with timer("a"):
                time.sleep(0.002)
            if i == 1:  # a stage first seen on frame 1 is 0 on frame 0
                with timer("b"):
                    time.sleep(0.004)
                with timer("b"):  # twice in one frame: summed there, max per call
                    time.sleep(0.001)
    with timer("final"):  # outside a frame: the total only
        time.sleep(0.001)
    assert len(timer.frame_seconds) == len(timer.frame_cpu_seconds) == 3
    assert {k: len(v) for k, v in timer.stage_frame_seconds.items()} == {"a": 3, "b": 3}
    b = list(timer.stage_frame_seconds["b"])
    assert b[0] == b[2] == 0.0 and b[1] >= 0.005
    assert timer.seconds["b"] == pytest.approx(b[1])
    assert 0.004 <= timer.max_seconds["b"] < b[1]
    assert timer.seconds["final"] >= 0.001 and "final" not in timer.max_seconds
    assert "final" not in timer.stage_frame_seconds
    for i in range(3):  # stages fit in their frame
        assert timer.stage_frame_seconds["a"][i] + b[i] <= timer.frame_seconds[i]


def test_a_block_that_raises_is_not_booked_and_measure_books_nothing():
    timer = StageTimer()
    with pytest.raises(ValueError), timer.frame(), timer("a"):
        raise ValueError("boom")
    assert not timer.seconds and len(timer.frame_seconds) == 0
    with timer.frame():
        with timer.measure() as guess:
            time.sleep(0.002)
        with timer("backend", plus=guess) as lap:
            time.sleep(0.001)
    assert lap.wall >= 0.003 and timer.seconds["backend"] == lap.wall
    assert set(timer.seconds) == {"backend"}  # the failed frame left nothing behind
    assert list(timer.stage_frame_seconds) == ["backend"]
