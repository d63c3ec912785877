"""The recent-scan window of the DPCR front end's refinement
(``slam.mapping.scan_window2d``): scans join only where the robot moved, and move with it."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.dpcr2d import Dpcr2dConfig
from slam.errors import ConfigError
from slam.mapping.scan_window2d import ScanWindow, ScanWindowConfig


def test_a_robot_standing_still_does_not_feed_its_window():
    window = ScanWindow(ScanWindowConfig(scans=3, min_move=0.05, min_turn_deg=2.0))
    wall = np.column_stack([np.linspace(-1.0, 1.0, 50), np.full(50, 2.0)])
    assert window.add(wall, np.zeros(3))
    assert not window.add(wall, np.array([0.01, 0.0, np.radians(0.5)]))
    assert window.add(wall, np.array([0.06, 0.0, 0.0]))
    assert len(window) == 2
    window.move(np.array([1.0, 0.0, 0.0]))
    ref = window.reference()
    assert ref is not None and np.allclose(ref.points[:, 1], 2.0)
    assert ref.points[:, 0].min() == pytest.approx(0.0, abs=0.05)
    # a wall seen along x: every point's local line runs along x
    assert np.all(np.abs(ref.directions[:, 0]) > 0.99)


def test_the_window_keeps_its_newest_scans():
    window = ScanWindow(ScanWindowConfig(scans=2))
    wall = np.column_stack([np.linspace(-1.0, 1.0, 50), np.full(50, 2.0)])
    for x in (0.0, 0.1, 0.2):
        window.add(wall, np.array([x, 0.0, 0.0]))
    assert len(window) == 2 and window.scans[0][1][0] == pytest.approx(0.1)


def test_refinement_settings_are_checked():
    assert Dpcr2dConfig().refine.scans == 0 and Dpcr2dConfig().second_gain == 1.0
    with pytest.raises(ConfigError, match="second_gain"):
        Dpcr2dConfig(second_gain=0.0)
    with pytest.raises(ConfigError, match="submap_lines"):
        Dpcr2dConfig(submap_lines="straight")


def test_a_large_second_correction_is_taken_on_evidence_only():
    """second_evidence: a correction beyond second_max_* is taken when it brings more of the
    submap's cells onto the regional map (a real drift), not when it brings none closer."""
    from frontends.dpcr2d import Dpcr2d
    from slam.registration.local_lines2d import local_line_reference

    # an L of walls: x = 0 (y 0..2 m) and y = 0 (x 0..2 m), as the regional map's lines
    t = np.linspace(0.0, 2.0, 41)
    ref_pts = np.vstack([np.column_stack([np.zeros(41), t]), np.column_stack([t, np.zeros(41)])])
    ref = local_line_reference(ref_pts, Dpcr2dConfig().refine.lines)
    submap = ref_pts + np.array([0.12, 0.0])  # drifted 12 cm along x
    off = Dpcr2d(Dpcr2dConfig(second_max_m=0.1, second_max_deg=2.0))
    on = Dpcr2d(Dpcr2dConfig(second_max_m=0.1, second_max_deg=2.0, second_evidence=0.05))
    back = np.array([-0.12, 0.0, 0.0])
    assert not off._second_evidence(submap, ref, back)  # off: never
    assert on._second_evidence(submap, ref, back)  # half the cells (the x = 0 wall) 12 cm off
    assert not on._second_evidence(ref_pts, ref, back)  # on the map already: it moves them off
    assert Dpcr2dConfig().second_evidence < 0 and Dpcr2dConfig().second_evidence_m == 0.05
