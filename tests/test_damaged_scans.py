"""Damaged clouds between normal ones, end to end: garbage coordinates (3e38 m), a stray
return far from every other point, ring values beyond the sensor's beams and a cloud that is
mostly garbage cost at most their own frame."""

from __future__ import annotations

import json
from itertools import islice

import numpy as np
import pytest

from slam.cli import main
from slam.io.bag_writer import write_pointcloud_bag
from slam.io.source import open_source
from slam.io.trajectory import read_tum

FRAMES = 12


def damaged(scans):
    """The corridor's scans with scan 4 damaged in every way a frame can survive (150 points
    at 3e38 m, a stray return 58 m from every other point: all its SOR weights underflow,
    rings 30000 and 200 of a 16-beam sensor) and scan 7 mostly garbage (skipped)."""
    s = scans[4]
    s.xyz[1000:1150, 2] = 3.0e38
    s.xyz[5000] = (0.0, 0.0, 60.0)
    s.ring[::5] = 30000
    s.ring[1::7] = 200
    scans[7].xyz[: int(0.8 * len(scans[7])), 0] = -3.0e38
    return scans


@pytest.mark.parametrize("recipe", ["improved_floam", "lego_loam"])
def test_damaged_clouds_cost_at_most_their_frame(tmp_path, corridor_short, recipe, capsys):
    scans = damaged(list(islice(open_source(corridor_short.bag), FRAMES)))
    bag = write_pointcloud_bag(tmp_path / "damaged.bag", scans)
    out = tmp_path / "o"
    assert main(["run", str(bag), "--config", recipe, "--out", str(out), "--quiet"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    stamps, traj = read_tum(out / "trajectory.tum")
    np.testing.assert_allclose(stamps, [s.stamp for i, s in enumerate(scans) if i != 7])
    assert np.isfinite(traj).all()
    m = json.loads((out / "metrics.json").read_text())
    assert m["skipped_messages"] == {"absurd coordinates": 1}
    # the damaged frame did not throw the odometry: 0.27 m driven, within 3 cm
    gt = np.array([p[:3, 3] for p in corridor_short.read_ground_truth()[1][:FRAMES]])
    assert np.linalg.norm(traj[-1][:3, 3]) == pytest.approx(
        np.linalg.norm(gt[-1] - gt[0]), abs=0.03
    )
