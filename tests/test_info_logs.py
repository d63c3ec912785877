"""`slam info` on a CARMEN log: the log's own stamps give its start, duration and rate."""

from __future__ import annotations

from shared_data import shared_path

from slam.io.info import describe


def test_a_carmen_log_reports_its_start_duration_and_rate():
    out = describe(shared_path("laser2d") / "mit-csail.clf.bz2")
    assert out["message_count"] == 1988
    assert abs(out["start"] - 1134864629.895) < 1e-3
    assert 420.0 < out["duration"] < 428.0  # 1988 scans at ~4.7 Hz
    assert 4.5 < out["rate_hz"] < 4.9
    assert out["first_scan"]["points"] > 200
