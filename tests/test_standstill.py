"""A standing sensor neither fills the map nor teaches the gate (slam/odometry).

The urban drive starts with 1 s at a standstill (frames 0-10 at the same pose), then the car
pulls away. Before, every standing scan went into the map: the k neighbours of a map point
became repeated samples of one ray, and the gate's running normal learned a fitness no
moving scan has. On the street scene with a 64-beam sensor that cost 98 of 200 frames and
41 m APE; now only scans 1 cm / 0.2 deg apart enter the map and the normal.
"""

from itertools import islice

import numpy as np
import pytest

from slam.config import load_config
from slam.io.source import open_source
from slam.odometry import CommonConfig, ScanToMapFrontend
from slam.plugins import instantiate
from slam.types import Scan

FRAMES = 16


@pytest.fixture(scope="module")
def departure(urban_short):
    scans = list(islice((s for s in open_source(urban_short.bag) if isinstance(s, Scan)), FRAMES))
    assert len(scans) == FRAMES
    _, poses = urban_short.read_ground_truth()
    return scans, poses[:FRAMES]


def _run(name: str, scans, overrides=()):
    fe = instantiate("slam.frontends", load_config(name, list(overrides)).frontend, "frontend")
    outs = [fe.process(s) for s in scans]
    return fe, outs


@pytest.mark.parametrize("name", ["improved_floam", "floam"])
def test_standing_scans_stay_out_of_map_and_normal(departure, name):
    scans, gt = departure
    moved = np.linalg.norm(gt[:, :3, 3] - gt[0, :3, 3], axis=1)
    standing = np.flatnonzero(moved < 1e-4)
    assert standing.max() >= 9  # the drive's own standstill: frames 0..>=9
    fe, outs = _run(name, scans)
    assert sum(o.extras["rejected"] for o in outs) == 0
    sizes = np.array([o.extras["map_points"] for o in outs])
    skipped = np.array([o.extras["map_skipped"] for o in outs])
    # every standing scan after the first is registered but not inserted ...
    assert skipped[standing[1:]].all() and skipped[0] == 0
    assert (sizes[standing] == sizes[0]).all()
    # ... and once the car moves the scans go in again: every frame that moved 3 cm
    first_in = int(np.argmax((moved >= 0.01) & (skipped == 0)))
    assert first_in > standing.max() and sizes[-1] > sizes[first_in - 1]
    step = np.r_[0.0, np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)]
    assert (step >= 0.03).sum() >= 3 and skipped[step >= 0.03].sum() == 0
    # the gate learned only the moving scans
    assert len(fe.gate.normal) == int((skipped[1:] == 0).sum())
    # the poses are still the standstill's
    pos = np.array([o.pose[:3, 3] for o in outs])
    assert np.linalg.norm(pos[standing], axis=1).max() < 0.01


def test_the_old_behaviour_filled_the_map_while_standing(departure):
    """The same frames with every trusted scan inserted (the setting that restores the old
    behaviour): the map grows while the car stands, so the test above can fail."""
    scans, _ = departure
    old = ("frontend.map_min_translation=0", "frontend.map_min_rotation_deg=0")
    fe, outs = _run("improved_floam", scans[:6], old)
    sizes = [o.extras["map_points"] for o in outs]
    assert sizes[5] > 1.5 * sizes[0]
    # every trusted registration but the first (no prediction tested it) teaches the gate
    assert len(fe.gate.normal) == 4


def test_moved_since_insert_thresholds():
    fe = ScanToMapFrontend(CommonConfig(map_min_translation=0.05, map_min_rotation_deg=0.5))
    assert fe.map_policy.wants(np.eye(4))  # nothing inserted yet
    fe.map_policy.T_inserted = np.eye(4)
    T = np.eye(4)
    T[0, 3] = 0.049
    assert not fe.map_policy.wants(T)
    T[0, 3] = 0.051
    assert fe.map_policy.wants(T)
    for deg, expected in ((0.4, False), (0.6, True)):
        a = np.radians(deg)
        R = np.eye(4)
        R[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        assert fe.map_policy.wants(R) is expected
