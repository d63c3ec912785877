"""Lost tracking: a sensor blinded for 2 s costs no more than its own drift.

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
from slam.types import Scan, TrackingStatus

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
    # the typed status says the same as the flat counters
    status = [o.status for o in outs]
    assert [i for i, st in enumerate(status) if st is TrackingStatus.LOST] == list(BLIND)
    assert [i for i, st in enumerate(status) if st is TrackingStatus.RECOVERED] == [BLIND.stop]
    assert all(o.diagnostics.rejected == bool(o.extras["rejected"]) for o in outs)
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


def _urban_errors(outs, stamps, gt_stamps, gt):
    """Position error from the start (no alignment) and per-frame step error (m)."""
    idx = np.searchsorted(gt_stamps, np.asarray(stamps) - 1e-6)
    truth = np.linalg.inv(gt[idx[0]]) @ gt[idx]
    P = np.stack([o.pose for o in outs])
    err = np.linalg.norm(P[:, :3, 3] - truth[:, :3, 3], axis=1)
    rel_e = np.linalg.inv(P[:-1]) @ P[1:]
    rel_g = np.linalg.inv(truth[:-1]) @ truth[1:]
    return err, np.linalg.norm(rel_e[:, :3, 3] - rel_g[:, :3, 3], axis=1)


@pytest.mark.parametrize("name", ["improved_floam", "floam"])
def test_a_stalled_driver_costs_no_frame(urban_short, name):
    """Two seconds of the urban drive missing (scans 30-49: a stalled driver or recorder)
    while the car speeds up from 3 to 6 m/s: 9.3 m between the scans either side. The
    registration starts from every 2 m along the extrapolated motion, +-0.5 a T^2 around it,
    and keeps the one that explains the most of the scan. Before: the prediction stopped
    after 1 s, 7 (FLOAM 1) frames were lost and the odometry ended 5.7 (5.0) m off; now 0
    lost, at most 0.18 (0.10) m off, 0.06 (0.03) m at the end."""
    gt_stamps, gt = urban_short.read_ground_truth()
    scans = [s for s in open_source(urban_short.bag) if isinstance(s, Scan)]
    kept = scans[:30] + scans[50:]
    fe = instantiate("slam.frontends", load_config(name).frontend, "frontend")
    outs = [fe.process(s) for s in kept]
    assert outs[30].extras["gap_hypotheses"] > 1
    assert sum(o.extras["tracking_lost"] for o in outs) == 0
    err, _ = _urban_errors(outs, [s.stamp for s in kept], gt_stamps, gt)
    assert err.max() < 0.3 and err[-1] < 0.1, (err.max(), err[-1])


def test_jittered_header_stamps_keep_tracking(urban_short):
    """Header stamps taken when the driver got the data, +-20 ms off the sweep start: a
    spinning LiDAR's scans are whole turns, so the motion between two scans is a whole number
    of sweep periods, not the stamp gap. Before: the prediction was scaled to 0.6-1.4 of the
    period, 2 of 60 frames were rejected and a written step was 0.30 m off (over 400 frames:
    85 rejected, a step 1.76 m off); now as on the exact stamps (0.045 m, steps < 2 cm)."""
    gt_stamps, gt = urban_short.read_ground_truth()
    scans = [s for s in open_source(urban_short.bag) if isinstance(s, Scan)]
    true = [s.stamp for s in scans]
    rng = np.random.default_rng(0)
    for s in scans:
        s.stamp = float(s.stamp) + float(rng.uniform(-0.02, 0.02))
    fe = instantiate("slam.frontends", load_config("improved_floam").frontend, "frontend")
    outs = [fe.process(s) for s in scans]
    assert sum(o.extras["tracking_lost"] for o in outs) == 0
    err, step = _urban_errors(outs, true, gt_stamps, gt)
    assert step.max() < 0.05, step.max()
    assert err.max() < 0.1, err.max()


def test_driver_without_ring_and_time_is_deskewed(urban_short):
    """A VLP-16 bag without ring and time fields (an ``x y z intensity`` driver, points in
    the Velodyne firing order): the time comes from the azimuth along the order and the
    sweep is deskewed as with the time field (final error 0.041 m against 0.043 m with it;
    before: not deskewed at all, 0.47 m off after 60 frames; urban, 400 frames, APE 0.072
    -> 0.396 m)."""
    gt_stamps, gt = urban_short.read_ground_truth()
    scans = [s for s in open_source(urban_short.bag) if isinstance(s, Scan)]
    for s in scans:
        s.ring, s.time = None, None
    fe = instantiate("slam.frontends", load_config("improved_floam").frontend, "frontend")
    outs = [fe.process(s) for s in scans]
    assert sum(o.extras["tracking_lost"] for o in outs) == 0
    err, _ = _urban_errors(outs, [s.stamp for s in scans], gt_stamps, gt)
    assert err[-1] < 0.1, err[-1]
