"""The system counts and averages the front end's typed diagnostics (metrics.json), and
keyframes keep the typed fields of their frame; a front end that still reports only the
untyped ``Odometry.extras`` is named once."""

from __future__ import annotations

import logging

import numpy as np

from slam.config import SlamConfig
from slam.outputs import metrics
from slam.system import SlamSystem
from slam.types import FrameDiagnostics, Odometry, RegionTag, Scan, TrackingStatus


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


class TypedFrontend:
    """1 m per frame, a keyframe every other frame; frame 2 skipped, 3 degenerate, 4
    rejected, each frame counts ``n`` = its index."""

    def process(self, scan: Scan) -> Odometry:
        i = scan.index
        d = FrameDiagnostics(counts={"n": float(i)}, timings_ms={"total_ms": 1.0})
        d.skipped = "too few points (0)" if i == 2 else None
        d.degenerate, d.rejected = i == 3, i == 4
        rel = np.eye(4) if i % 2 == 0 else _pose(1.0)
        status = TrackingStatus.LOST if d.rejected else TrackingStatus.TRACKED
        cloud = np.random.default_rng(i).normal(size=(30, 3))
        region = RegionTag(region=i, left=i - 2) if i % 2 == 0 else None
        return Odometry(scan.stamp, _pose(float(i)), i % 2 == 0, rel, np.eye(6) * 1e4, cloud,
                        status=status, diagnostics=d, region=region)  # fmt: skip


class UntypedFrontend(TypedFrontend):
    def process(self, scan: Scan) -> Odometry:
        odom = super().process(scan)
        odom.extras, odom.diagnostics = {"skipped": "old style", "n": 1}, None
        return odom


def _run(frontend, n: int = 8) -> SlamSystem:
    system = SlamSystem(SlamConfig(), frontend=frontend)
    for i in range(n):
        system.process(Scan(stamp=1.0 + 0.1 * i, xyz=np.zeros((1, 3)), index=i))
    system.finish()
    return system


def test_metrics_count_and_average_the_typed_diagnostics():
    system = _run(TypedFrontend())
    st, m = system.state, metrics(system)
    assert st.skipped_frames == m["skipped_frames"] == 1 and m["degenerate_frames"] == 1
    assert m["frontend_counts"] == {"rejected": 1, "tracking_lost": 0, "recovered": 0,
                                    "reinitialised": 0}  # fmt: skip
    # n averaged over all 8 frames, rejected over the one frame that reports it
    assert m["frontend_means"] == {"n": 3.5, "region": 3.0, "region_left": 1.0,
                                   "rejected": 1.0, "total_ms": 1.0}  # fmt: skip
    kfs = st.keyframes
    assert [k.frame_index for k in kfs] == [0, 2, 4, 6]
    assert [k.region.left for k in kfs] == [-2, 0, 2, 4]
    assert kfs[2].status is TrackingStatus.LOST and kfs[2].diagnostics.rejected
    assert kfs[1].diagnostics.skipped == "too few points (0)" and kfs[0].ground_plane is None


def test_a_front_end_with_only_untyped_extras_is_named_once(caplog):
    with caplog.at_level(logging.WARNING, logger="slam.system"):
        system = _run(UntypedFrontend())
    named = [r for r in caplog.records if "Odometry.extras" in r.getMessage()]
    assert len(named) == 1 and "UntypedFrontend" in named[0].getMessage()
    assert system.state.skipped_frames == 0 and "n" not in system.state.diagnostic_means()
    assert system.state.diagnostic_means()["region"] == 3.0  # the typed tag still counts
