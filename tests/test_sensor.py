"""Beam model estimated from the data (slam/sensor.py): 16-128 beams, three point layouts."""

from __future__ import annotations

import numpy as np
import pytest

from slam.errors import InputError
from slam.sensor import BeamModel, beams_from_rings, estimate_beams, layout_rings

HDL64 = np.r_[np.linspace(-24.33, -8.83, 32), np.linspace(-8.33, 2.0, 32)]  # 1/2, 1/3 deg
SENSORS = {
    "VLP-16": np.linspace(-15.0, 15.0, 16),
    "HDL-32E": np.linspace(-30.67, 10.67, 32),
    "HDL-64E": HDL64,
    "OS-128": np.linspace(-22.5, 22.5, 128),
}


def spin(elev_deg: np.ndarray, columns: int, order: str, seed: int = 0) -> np.ndarray:
    """A sweep of a spinning lidar in a room of walls 4-40 m away: one return per beam and
    column, elevation noise 0.01 deg. order: 'ring' (beam by beam), 'firing' (column by
    column, as Velodyne drivers publish), 'shuffled'."""
    rng = np.random.default_rng(seed)
    b, c = np.meshgrid(np.arange(len(elev_deg)), np.arange(columns), indexing="ij")
    az = np.radians(c * 360.0 / columns + 0.01 * b)  # lasers fire slightly staggered
    el = np.radians(elev_deg[b] + rng.normal(0, 0.01, b.shape))
    r = rng.uniform(4.0, 40.0, b.shape)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
    xyz = xyz.reshape(3, -1).T  # beam-major
    ring = b.ravel()
    if order == "firing":
        perm = np.argsort(c.ravel() * len(elev_deg) + b.ravel(), kind="stable")
    elif order == "shuffled":
        perm = rng.permutation(len(ring))
    else:
        perm = np.arange(len(ring))
    return xyz[perm], ring[perm]


@pytest.mark.parametrize("name", sorted(SENSORS))
@pytest.mark.parametrize("order", ["ring", "firing", "shuffled"])
def test_beams_found_for_every_sensor_and_layout(name: str, order: str) -> None:
    elev = SENSORS[name]
    scans = [spin(elev, 900, order, seed)[0] for seed in range(2)]
    model = estimate_beams(scans)
    assert model.n_beams == len(elev)
    assert np.abs(model.elevations_deg - elev).max() < 0.05
    assert model.layout == (order == "ring")
    xyz, ring = spin(elev, 900, order, seed=5)
    assert np.array_equal(model.ring_of(xyz), ring)
    assert model.ring_of(xyz).dtype == np.int16
    assert abs(model.vertical_resolution_deg - np.median(np.diff(elev))) < 0.02


def test_describe_and_range() -> None:
    xyz, _ = spin(HDL64, 900, "ring")
    model = estimate_beams([xyz])
    line = model.describe()
    assert line.startswith("inferred 64 beams, +2.0..-24.3 deg")
    assert "point layout" in line
    assert 38.0 < model.max_range <= 40.0 * 1.0001  # ranges uniform in 4-40 m


def test_firing_order_is_not_taken_for_a_layout() -> None:
    xyz, _ = spin(SENSORS["VLP-16"], 900, "firing")
    assert layout_rings(xyz) is None
    xyz, ring = spin(SENSORS["VLP-16"], 900, "ring")
    assert np.array_equal(layout_rings(xyz), ring)


def test_layout_model_falls_back_to_elevation_on_other_scans() -> None:
    elev = SENSORS["HDL-32E"]
    model = estimate_beams([spin(elev, 900, "ring")[0]])
    xyz, ring = spin(elev, 900, "shuffled", seed=3)
    assert np.array_equal(model.ring_of(xyz), ring)


def test_beams_from_ring_field() -> None:
    xyz, ring = spin(SENSORS["OS-128"], 600, "firing")
    model = beams_from_rings([xyz], [ring])
    assert model.n_beams == 128 and model.source == "ring field"
    assert model.describe().startswith("read 128 beams, +22.5..-22.5 deg")


def test_bad_input() -> None:
    with pytest.raises(InputError):
        estimate_beams([np.zeros((5, 2))])
    with pytest.raises(InputError):
        estimate_beams([])
    with pytest.raises(InputError):
        BeamModel(np.array([0.0])).ring_of(np.zeros(3))


def test_layout_with_wide_gaps_in_upper_beams() -> None:
    """Upper beams that see sky over half the turn (a gap > 180 deg) keep their layout."""
    elev = SENSORS["HDL-64E"]
    xyz, ring = spin(elev, 900, "ring")
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])) % 360
    keep = ~((ring >= 48) & (az > 60) & (az < 270))  # 210 deg without returns
    model = estimate_beams([xyz[keep]])
    assert model.n_beams == 64 and model.layout
    assert np.array_equal(model.ring_of(xyz[keep]), ring[keep])


def test_layout_top_beam_first_is_numbered_from_the_bottom() -> None:
    elev = SENSORS["OS-128"]
    xyz, ring = spin(elev, 512, "ring")
    flip = np.argsort(-ring, kind="stable")  # beams stored from the top down
    assert np.array_equal(layout_rings(xyz[flip]), ring[flip])


def test_layout_seam_when_the_first_beam_begins_late() -> None:
    """The first stored beam sees sky over its first 40 deg: the cloud's first point is not
    where the turns begin, the seam is found from the data (an Ouster row after sky)."""
    elev = SENSORS["OS-128"]
    xyz, ring = spin(elev, 1024, "ring")
    flip = np.argsort(-ring, kind="stable")  # top beam first, as Ouster stores rows
    xyz, ring = xyz[flip], ring[flip]
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])) % 360
    keep = ~((ring >= 126) & (az < 40))
    model = estimate_beams([xyz[keep]])
    assert model.layout and model.n_beams == 128
    assert abs((np.degrees(model.seam_rad) + 180.0) % 360.0 - 180.0) < 1.0
    assert np.array_equal(model.ring_of(xyz[keep]), ring[keep])


def test_beams_from_rings_bad_input() -> None:
    with pytest.raises(InputError):
        beams_from_rings([np.zeros((0, 3))], [np.zeros(0)])
    with pytest.raises(InputError):
        beams_from_rings([np.ones((20, 3))], [np.zeros(19)])
    xyz, ring = spin(SENSORS["VLP-16"], 300, "firing")
    xyz[:10] = np.nan  # invalid returns are ignored
    assert beams_from_rings([xyz], [ring]).n_beams == 16


def test_time_of_a_layout_cloud() -> None:
    """Beam-by-beam cloud stored in firing order from a seam at +pi, turning clockwise (as
    the simulator's KITTI-style HDL-64E): time = azimuth advanced from the seam."""
    columns = 900
    elev = SENSORS["HDL-64E"]
    b, c = np.meshgrid(np.arange(64), np.arange(columns), indexing="ij")
    az = np.pi - 2 * np.pi * c / columns  # clockwise from +pi, column c fires at c/columns
    el = np.radians(elev[b])
    xyz = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    xyz = (xyz * 10.0).reshape(-1, 3)
    t_true = (c * 0.1 / columns).ravel()
    model = estimate_beams([xyz])
    assert model.layout
    t = model.time_of(xyz, 0.1)
    assert np.abs(t - t_true).max() < 1e-9 + 0.1 / columns
    assert estimate_beams([spin(elev, 900, "firing")[0]]).time_of(xyz, 0.1) is None
