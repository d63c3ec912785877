"""The visit after a re-anchor made a loop edge claims more translation noise
(``frontend.anchor_after_sigma_m``): the front end has just moved its submap onto an old
map, and its motion over the next visit is measured on that move."""

from __future__ import annotations

import numpy as np
import pytest

from slam.config import load_config
from slam.mapping.grid2d import compose2d, inverse2d
from slam.sim.floorplan2d import simulate2d
from slam.system import SlamSystem
from slam.types import Scan

DRIFT = (100, 195)  # frames over which the heading drifts 0.1 deg per frame (9.5 deg)
SIGMA = 0.1  # m
VISIT = 10  # scans per visit


def _keyframes(sigma: float) -> list[tuple[int, bool, float]]:
    """1.25 laps of the rooms (exact wheels), the heading drifting over ``DRIFT`` so that
    the front end re-anchors; per keyframe (frame, anchored, translation sigma m)."""
    lap = simulate2d("rooms2d", frames=250, speed=2.0, seed=7)
    sets = ["frontend.visit_anchor_edges=true", f"frontend.visit_scans={VISIT}",
            f"frontend.anchor_after_sigma_m={sigma}"]  # fmt: skip
    cfg = load_config("dpcr2d", sets)
    system = SlamSystem(cfg)
    fe = system.frontend
    out = []
    for k in range(len(lap.stamps)):
        if DRIFT[0] <= k < DRIFT[1]:
            about = np.array([*fe.pose[:2], 0.0])
            fe._move(compose2d(compose2d(about, np.array([0.0, 0.0, np.radians(0.1)])),
                               inverse2d(about)))  # fmt: skip
        pts = lap.points(k)
        odo = system.process(Scan(float(lap.stamps[k]), np.column_stack([pts, np.zeros(len(pts))]),
                                  odom=lap.poses[k].copy(), index=k))  # fmt: skip
        if odo.is_keyframe:
            anchored = odo.region is not None and odo.region.anchor is not None
            out.append((k, anchored, float(1.0 / np.sqrt(odo.info[3, 3]))))
    system.finish()
    return out


@pytest.fixture(scope="module")
def keyframes():
    return {s: _keyframes(s) for s in (0.0, SIGMA)}


def test_the_visit_after_a_re_anchor_claims_the_extra_noise(keyframes):
    """The front end is the same with and without (the noise changes no pose); the
    keyframe after each anchored one claims sqrt(sigma_before^2 + SIGMA^2 x its frames /
    VISIT), every other keyframe exactly what it claimed before."""
    off, on = keyframes[0.0], keyframes[SIGMA]
    assert [k for k, _, _ in off] == [k for k, _, _ in on]
    anchored = [i for i, (_, a, _) in enumerate(on) if a]
    assert anchored, "the drift makes the front end re-anchor"
    after = {i + 1 for i in anchored if i + 1 < len(on)}
    for i, ((k, _, s_off), (_, _, s_on)) in enumerate(zip(off, on, strict=True)):
        if i in after:
            frames = k - on[i - 1][0]
            assert s_on == pytest.approx(np.hypot(s_off, SIGMA * np.sqrt(frames / VISIT)), rel=1e-6)
            assert s_on > s_off + 0.02
        else:
            assert s_on == pytest.approx(s_off, rel=1e-9), (i, k)
