"""The 2D front ends report typed status and diagnostics (``FrameDiagnostics``) and the
region front end its ``RegionTag``; the run state counts and averages them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from frontends.dpcr2d import Dpcr2d
from frontends.icp2d import Icp2d
from slam.sim.floorplan2d import simulate2d
from slam.state import RunState
from slam.types import FrameDiagnostics, Scan, TrackingStatus

T = TrackingStatus


@pytest.fixture(scope="module")
def rooms():
    return simulate2d("rooms2d", frames=90, speed=1.5, seed=3)


def _scan(seq, k: int, empty: bool = False) -> Scan:
    xy = np.zeros((0, 2)) if empty else seq.points(k)
    return Scan(float(seq.stamps[k]), np.column_stack([xy, np.zeros(len(xy))]), index=k)


def test_icp2d_reports_tracked_lost_recovered_and_predicted(rooms):
    fe = Icp2d()
    outs = [fe.process(_scan(rooms, k)) for k in range(20)]
    assert [o.status for o in outs] == [T.TRACKED] * 20
    assert all(isinstance(o.diagnostics, FrameDiagnostics) for o in outs)
    assert all(o.diagnostics.counts["rmse"] < 0.05 for o in outs[1:])
    assert "rmse" not in outs[0].diagnostics.counts  # nothing to register on yet
    strict = fe.cfg
    fe.cfg = replace(strict, min_matches=10**6)  # every registration now implausible
    lost = [fe.process(_scan(rooms, k)) for k in range(20, 23)]
    assert [o.status for o in lost] == [T.LOST] * 3 and all(o.diagnostics.rejected for o in lost)
    assert lost[0].flat()["rejected"] == 1 and "rejected" not in outs[5].flat()
    fe.cfg = strict
    skipped = fe.process(_scan(rooms, 23, empty=True))
    assert skipped.status is T.PREDICTED and "too few points" in skipped.diagnostics.skipped
    assert fe.process(_scan(rooms, 24)).status is T.RECOVERED  # lost until a trusted one
    assert fe.process(_scan(rooms, 25)).status is T.TRACKED
    st = RunState()
    for o in [*outs, *lost, skipped]:
        st.add_diagnostics(o)
    assert st.skipped_frames == 1 and st.degenerate_frames == 0
    assert st.diagnostic_sums["rejected"] == 3 and st.diagnostic_counts["rejected"] == 3
    # the frames that registered: the rejected ones fit nothing (non-finite, not averaged)
    assert st.diagnostic_counts["rmse"] == 19 and not np.isfinite(
        lost[0].diagnostics.counts["rmse"]
    )


def test_dpcr2d_tags_region_keyframes_and_only_them(rooms):
    fe = Dpcr2d()
    outs = [fe.process(_scan(rooms, k)) for k in range(90)]
    assert outs[0].status is T.TRACKED and all(o.status is T.TRACKED for o in outs[1:])
    kfs = [o for o in outs if o.is_keyframe]
    assert len(kfs) >= 4 and all(o.region is not None and o.region.region >= 0 for o in kfs)
    assert all(o.region is None for o in outs if not o.is_keyframe)
    assert kfs[0].region.left == -1 and all(o.region.left >= 0 for o in kfs[1:])
    assert [o.region.left for o in kfs[2:]] == [o.region.region for o in kfs[1:-1]]
    flat = kfs[1].flat()
    assert flat["region"] == kfs[1].region.region and flat["region_left"] == kfs[1].region.left
    assert "visit" not in flat and flat["iterations"] > 0 and "first_ms" in flat
    assert all(not o.region.visit and o.region.anchor is None for o in kfs)
