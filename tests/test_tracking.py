"""Lost tracking (issue 10.4): a sensor blinded for 2 s costs no more than its own drift.

Frames 60-79 of the park (realistic sensor, 150 frames) are blinded: every ray returns from
a bumpy surface 0.8-1.45 m away that moves with the sensor (a truck alongside, a bush
brushing past), keeping the points that were already closer than 1.5 m and the rings and
per-point times. Before the plausibility gate, GICP registered those close points against
the map with a normal-looking fitness, the blinding surface went into the map, the sensor
"stood still" in it for 2 s and the run ended 3.8 m off (FLOAM: 6.1 m).
"""

import numpy as np
import pytest

from slam.config import load_config
from slam.io.source import open_source
from slam.plugins import instantiate
from slam.sim import ensure_sequence
from slam.types import Scan

FRAMES = 150
BLIND = range(60, 80)


def blinded(scans: list[Scan], frames: range, radius: float = 1.5, seed: int = 0) -> list[Scan]:
    """``scans`` with every return of the scans in ``frames`` within ``radius`` metres."""
    rng = np.random.default_rng(seed)
    out = []
    for s in scans:
        if s.index in frames:
            r = np.linalg.norm(s.xyz, axis=1)
            d = s.xyz / r[:, None]
            az, el = np.arctan2(d[:, 1], d[:, 0]), np.arcsin(d[:, 2])
            surface = 1.12 + 0.2 * np.sin(3 * az) * np.cos(5 * el) + rng.normal(0, 0.03, len(r))
            close = d * np.clip(surface, 0.8, radius - 0.05)[:, None]
            xyz = np.where((r < radius)[:, None], s.xyz, close)
            s = Scan(s.stamp, xyz, s.intensity, s.ring, s.time, s.index)
        out.append(s)
    return out


@pytest.fixture(scope="module")
def park():
    sim = ensure_sequence("park", frames=FRAMES)
    scans = [s for s in open_source(sim.bag) if isinstance(s, Scan)]
    return scans, *sim.read_ground_truth()


@pytest.mark.parametrize(
    ("name", "max_after", "max_final"),
    # improved FLOAM ends where its clean run ends (0.10 m); FLOAM drifts 0.86 m on the clean
    # park over these 150 frames, so it is held to that (before the gate: 6.1 m)
    [("improved_floam", 0.5, 0.25), ("floam", 1.0, 1.0)],
)
def test_blinded_stretch_is_flagged_and_recovered(park, name, max_after, max_final):
    scans, gt_stamps, gt = park
    assert len(scans) == FRAMES
    seq = blinded(scans, BLIND)
    assert max(np.linalg.norm(seq[i].xyz, axis=1).max() for i in BLIND) < 1.5
    fe = instantiate("slam.frontends", load_config(name).frontend, "frontend")
    outs = [fe.process(s) for s in seq]
    idx = np.clip(np.searchsorted(gt_stamps, [o.stamp for o in outs]), 0, len(gt) - 1)
    G = np.linalg.inv(gt[idx[0]]) @ gt[idx]
    err = np.linalg.norm(np.array([o.pose for o in outs])[:, :3, 3] - G[:, :3, 3], axis=1)
    lost = [i for i, o in enumerate(outs) if "lost" in o.extras]
    assert lost == list(BLIND), lost  # every blinded frame, and only those
    assert sum(o.extras["rejected"] for o in outs) == len(BLIND)
    assert [i for i, o in enumerate(outs) if o.extras["recovered"]] == [BLIND.stop]
    assert not any(outs[i].is_keyframe for i in BLIND)
    # the blinded stretch costs its own drift (constant velocity over 2 s), nothing more
    assert err[BLIND.stop :].max() < max_after, err[BLIND.stop :].max()
    assert err[-1] < max_final, err[-1]


@pytest.mark.parametrize("name", ["improved_floam", "floam"])
def test_dropped_scans_at_car_speed_keep_tracking(name):
    """Every 7th scan of the urban drive (12 m/s) missing, as in a lossy bag: the prediction
    spans the gap, so no registration is rejected (before: 7 of 55 frames lost and 2.1 m
    off with improved FLOAM: the unscaled prediction fell 1.2 m short at every gap)."""
    sim = ensure_sequence("urban", frames=60)
    gt_stamps, gt = sim.read_ground_truth()
    scans = [s for s in open_source(sim.bag) if isinstance(s, Scan)]
    kept = [s for i, s in enumerate(scans) if i < 20 or i % 7 != 6]
    fe = instantiate("slam.frontends", load_config(name).frontend, "frontend")
    outs = [fe.process(s) for s in kept]
    assert sum(o.extras["tracking_lost"] for o in outs) == 0
    idx = np.searchsorted(gt_stamps, [s.stamp for s in kept])
    truth = np.linalg.inv(gt[idx[0]]) @ gt[idx]  # the odometry starts at the first scan
    err = np.linalg.norm(np.stack([o.pose[:3, 3] for o in outs]) - truth[:, :3, 3], axis=1)
    assert err.max() < 0.3  # drift from the start, no alignment
