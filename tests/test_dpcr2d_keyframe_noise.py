"""The DPCR front end's keyframe information (frontends/dpcr2d.py): the scan-matched chain
claims ``graph_info_scale`` x the planar model only where the scans fit; frames that do not
(a poor fit after the search, a prediction kept) and a re-anchor's jump widen it, so that
the loop edges of the graph can move what such a stretch got wrong; a poor fit that agrees
with the wheels does not."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.dpcr2d import Dpcr2d, Dpcr2dConfig
from slam.mapping.grid2d import compose2d, inverse2d, planar_information
from slam.sim.floorplan2d import simulate2d
from slam.types import Scan

PLANE = [3, 2]  # x translation, heading in the 6x6 information


@pytest.fixture(scope="module")
def lap():
    """1.25 laps of the rooms at 2 m/s with exact wheel odometry."""
    return simulate2d("rooms2d", frames=250, speed=2.0, seed=7)


def _scan(seq, k: int, pts: np.ndarray | None = None) -> Scan:
    pts = seq.points(k) if pts is None else pts
    return Scan(float(seq.stamps[k]), np.column_stack([pts, np.zeros(len(pts))]),
                odom=seq.poses[k].copy())  # fmt: skip


def _sigmas(odo) -> np.ndarray:
    """(sigma_x m, sigma_theta deg) of a keyframe's information."""
    s = 1.0 / np.sqrt(np.diag(odo.info)[PLANE])
    return np.array([s[0], np.degrees(s[1])])


def _model(fe: Dpcr2d, odo) -> np.ndarray:
    info = fe.cfg.graph_info_scale * planar_information(odo.relative)
    s = 1.0 / np.sqrt(np.diag(info)[PLANE])
    return np.array([s[0], np.degrees(s[1])])


def test_frames_that_do_not_fit_widen_their_keyframe(lap):
    """Scans 60-64 replaced by clutter (random returns 1-5 m around the robot): the
    keyframe that holds them claims at least the 5 frames' noise (sqrt 5 x 5 cm, 2 deg: the
    heading bounded by each one's disagreement with the wheels); the
    keyframes before, and those after the clutter has left the submap (20 scans), the
    scaled model exactly."""
    fe = Dpcr2d(Dpcr2dConfig(visit_scans=10, poor_fit_sigma_m=0.05))
    rng = np.random.default_rng(0)
    kfs = []
    for k in range(110):
        clutter = None
        if 60 <= k < 65:
            a, r = rng.uniform(-np.pi, np.pi, 300), rng.uniform(1.0, 5.0, 300)
            clutter = np.column_stack([r * np.cos(a), r * np.sin(a)])
        odo = fe.process(_scan(lap, k, clutter))
        if odo.is_keyframe:
            kfs.append((k, odo))
    for k, odo in kfs:
        if 60 <= k < 70:  # the keyframe whose stretch holds scans 60-64
            cfg = fe.cfg
            assert _sigmas(odo)[0] >= cfg.poor_fit_sigma_m * np.sqrt(5) - 1e-9, _sigmas(odo)
            # the clutter drags each registration 5 - 20 cm and 0.8 - 3 deg off the wheels
            assert _sigmas(odo)[1] >= 2.0, _sigmas(odo)
        elif 10 <= k < 60 or k >= 90:
            assert np.allclose(_sigmas(odo), _model(fe, odo)), (k, _sigmas(odo))


@pytest.mark.parametrize("bound", [True, False])
def test_a_poor_fit_that_agrees_with_the_wheels_keeps_the_chain_tight(lap, bound):
    """Scans 60-64 with 8 cm of point noise: each fits worse than ``poor_fit_rmse`` but
    lands within about 2 cm / 0.2 deg of the exact wheel odometry; with the wheel bound
    their keyframe claims at most 4 cm / 0.4 deg (the model's 0.7 cm / 0.06 deg plus their
    disagreement), without it sqrt 5 x 5 cm, 1 deg."""
    cfg = Dpcr2dConfig(visit_scans=10, poor_fit_sigma_m=0.05, poor_fit_wheel_bound=bound)
    fe = Dpcr2d(cfg)
    rng = np.random.default_rng(0)
    widened = None
    for k in range(75):
        pts = lap.points(k)
        if 60 <= k < 65:
            pts = pts + rng.normal(0.0, 0.08, pts.shape)
        odo = fe.process(_scan(lap, k, pts))
        if 60 <= k < 65:
            assert odo.diagnostics.counts["rmse"] > cfg.poor_fit_rmse
        if odo.is_keyframe and 60 <= k < 70:
            widened = _sigmas(odo)
    assert widened is not None
    if bound:
        assert widened[0] < 0.04 and widened[1] < 0.4, widened
    else:
        assert widened[0] >= cfg.poor_fit_sigma_m * np.sqrt(5) - 1e-9, widened
        assert widened[1] >= cfg.poor_fit_sigma_deg * np.sqrt(5) - 1e-9, widened


def test_a_re_anchor_widens_its_keyframe_by_its_jump(lap):
    """The robot and its submap moved 0.3 m / 12 deg at scan 80 (a drift); the re-anchor
    that puts it back onto the old map is a jump of the reported pose, not a motion: it
    ends the visit, and its keyframe claims at least the jump."""
    fe = Dpcr2d(Dpcr2dConfig(visit_scans=10, poor_fit_rmse=0.0, poor_fit_sigma_m=0.05))
    jumps, widened = [], []
    for k in range(len(lap.stamps)):
        if k == 80:
            about = np.array([*fe.pose[:2], 0.0])
            drift = np.array([0.3, 0.0, np.radians(12.0)])
            fe._move(compose2d(compose2d(about, drift), inverse2d(about)))
        odo = fe.process(_scan(lap, k))
        if odo.diagnostics.counts.get("reanchored"):
            jumps.append(odo.diagnostics.counts["reanchor_jump_m"])
            assert odo.is_keyframe  # the jump ends the visit: no visit cloud spans it
        if odo.is_keyframe and jumps and len(widened) < len(jumps):
            widened.append(_sigmas(odo))
    assert jumps and max(jumps) > 0.2, jumps
    assert widened[0][0] >= jumps[0] - 1e-9 and widened[0][1] >= 11.0, (jumps, widened)
