"""Beam model estimated from the data (slam/sensor/): 16-128 beams, three point layouts."""

from __future__ import annotations

import numpy as np
import pytest

from slam.errors import InputError
from slam.sensor.beam_model import BeamModel
from slam.sensor.beam_table import beams_from_rings, estimate_beams
from slam.sensor.layout import layout_rings

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


# ---------------------------------------------------------------- compiled kernels


def _layout_clouds() -> list[np.ndarray]:
    """Clouds of every layout the kernels meet: beam by beam (bottom up, top down, with
    sky gaps), firing order and shuffled (not layouts), 16-128 beams."""
    clouds = []
    for elev in SENSORS.values():
        for order in ("ring", "firing", "shuffled"):
            clouds.append(spin(elev, 600, order, seed=len(elev))[0])
    xyz, ring = spin(SENSORS["OS-128"], 512, "ring")
    clouds.append(xyz[np.argsort(-ring, kind="stable")])
    xyz, ring = spin(SENSORS["HDL-64E"], 900, "ring", seed=2)
    az = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0])) % 360
    clouds.append(xyz[~((ring >= 48) & (az > 60) & (az < 270))])
    return clouds


def test_forward_kernel_equals_numpy_reference() -> None:
    from slam.sensor.layout import forward_azimuth, forward_from_azimuth

    n_layouts = 0
    for xyz in _layout_clouds():
        ref = forward_azimuth(xyz)
        polar = np.arctan2(xyz[:, 1], xyz[:, 0]), np.hypot(xyz[:, 0], xyz[:, 1])
        got = forward_from_azimuth(*polar)
        assert (ref is None) == (got is None)
        if ref is not None:
            n_layouts += 1
            assert np.array_equal(ref[0], got[0]) and ref[1] == got[1]
    assert n_layouts >= 6  # beam-by-beam clouds of every sensor


def test_group_medians_kernel_equals_numpy_reference() -> None:
    from slam.sensor.layout import group_medians
    from slam.sensor.layout_kernels import group_medians_kernel

    rng = np.random.default_rng(4)
    for n, groups in ((1, 1), (10, 3), (5001, 64), (20000, 130)):
        values = np.round(rng.normal(0.0, 5.0, n), 2)  # ties included
        group = rng.integers(0, groups, n)
        group[: min(n, groups)] = np.arange(min(n, groups))  # no group empty but the last
        ref = group_medians(values, group, groups + 1)
        got = group_medians_kernel(values, group, np.ones(n, np.bool_), groups + 1)
        assert np.array_equal(ref, got, equal_nan=True) and np.isnan(got[-1])


def test_layout_rings_kernel_equals_numpy_reference() -> None:
    from slam.sensor.layout import layout_rings_reference

    n_layouts = 0
    for xyz in _layout_clouds():
        ref, got = layout_rings_reference(xyz), layout_rings(xyz)
        assert (ref is None) == (got is None)
        if ref is not None:
            n_layouts += 1
            assert got.dtype == np.int16 and np.array_equal(ref, got)
    assert n_layouts >= 6


def test_fill_equals_ring_of_and_time_of() -> None:
    for order in ("ring", "firing"):
        xyz, ring = spin(SENSORS["HDL-64E"], 900, order, seed=1)
        model = estimate_beams([xyz])
        r, t = model.fill(xyz, 0.1)
        assert np.array_equal(r, ring) and np.array_equal(r, model.ring_of(xyz))
        t_ref = model.time_of(xyz, 0.1)
        assert (t is None) == (t_ref is None) == (order == "firing")
        if t is not None:
            assert np.array_equal(t, t_ref) and 0.0 <= t.min() and t.max() <= 0.1
        assert model.fill(xyz, 0.1, ring=False, time=False) == (None, None)


def test_points_at_the_origin_keep_the_layout() -> None:
    """Drivers write (0, 0, 0) for a missing return (real KITTI scans hold one): such a point
    has no azimuth, and one of them used to break the layout and send every ring to the
    nearest-elevation table (overlapping HDL-64E beams then mix)."""
    xyz, ring = spin(SENSORS["HDL-64E"], 900, "ring", seed=3)
    model = estimate_beams([xyz])
    holes = xyz.copy()
    holes[[10, 30000, 40000]] = 0.0
    holes[20000] = np.nan
    assert layout_rings(holes, model.seam_rad) is None  # the raw order is broken by them
    r, t = model.fill(holes, 0.1)
    ok = np.ones(len(xyz), bool)
    ok[[10, 20000, 30000, 40000]] = False
    assert np.array_equal(r[ok], ring[ok]) and r.dtype == np.int16
    assert 0 <= r.min() and r.max() < 64
    assert np.array_equal(t[ok], model.time_of(xyz, 0.1)[ok])


def test_real_hdl64_layout_holds_on_every_scan(tmp_path) -> None:
    """Real KITTI-raw HDL-64E scans (stored beam by beam, one (0, 0, 0) point each): every
    scan keeps its layout rings, equal to the numpy reference on the points with an azimuth,
    and the fused fill equals ring_of / time_of."""
    import tarfile

    from shared_data import shared_path

    from slam.io.folders import read_cloud
    from slam.sensor.layout import layout_rings_reference

    with tarfile.open(shared_path("kitti_raw_drive", "data_1.tar.xz"), "r:xz") as tar:
        members = [m for m in tar if m.name.endswith(".pcd")][:4]
        tar.extractall(tmp_path, members=members, filter="data")
    scans = [read_cloud(tmp_path / m.name, index=i, stamp=0.1 * i) for i, m in enumerate(members)]
    model = estimate_beams([s.xyz for s in scans[:3]])
    assert model.layout and model.n_beams == 64
    for s in scans:
        ok = np.einsum("ij,ij->i", s.xyz, s.xyz) > 1e-6
        ref = layout_rings_reference(s.xyz[ok], model.seam_rad)
        ring, t = model.fill(s.xyz, 0.1)
        assert ref is not None and np.array_equal(ring[ok], ref)
        assert np.array_equal(ring, model.ring_of(s.xyz))
        assert np.array_equal(t, model.time_of(s.xyz, 0.1))
        assert np.bincount(ring, minlength=64).min() > 500


def test_near_points_stepping_back_keep_the_layout() -> None:
    """Motion compensation moves a near point's azimuth (KITTI odometry at 10 m/s: 6-11 deg
    back at 1.2-1.9 m): such a back step is not a ~350 deg forward gap (a new turn)."""
    xyz, ring = spin(SENSORS["HDL-64E"], 900, "ring", seed=6)
    glitched = xyz.copy()
    for k in (5000, 30000, 50000):  # three beams: a point 1.5 m away, 12 deg behind
        az = np.arctan2(xyz[k - 1, 1], xyz[k - 1, 0]) - np.radians(12.0)
        el = np.arctan2(xyz[k, 2], np.hypot(xyz[k, 0], xyz[k, 1]))
        glitched[k] = 1.5 * np.array([np.cos(az), np.sin(az), np.tan(el)])
    model = estimate_beams([glitched, xyz])
    assert model.n_beams == 64 and model.layout
    assert np.array_equal(model.ring_of(glitched), ring)
    # the same step 12 deg back at 30 m is a forward gap: each such beam's turn splits in two
    far = glitched.copy()
    far[[5000, 30000, 50000]] *= 20.0
    assert int(layout_rings(far, model.seam_rad).max()) + 1 == 67


def test_a_sweep_stretched_past_the_seam_keeps_its_beams() -> None:
    """Motion compensation to the sweep start stretches a moving scan past one turn: the
    last beam's final near points lie beyond the seam (the simulated HDL-64E at 9 m/s: 251
    points of the lowest beam, 48 deg past it, read as a 65th beam). They are that beam."""
    elev = SENSORS["HDL-64E"]
    xyz, ring = spin(elev, 900, "ring", seed=7)
    az = np.radians(np.arange(1, 61) * 0.4)  # 60 more points of the last beam, 24 deg on
    el = np.radians(elev[-1])
    tail = 5.0 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) + 0 * az])
    for xyz_, ring_ in ((xyz, ring), (xyz[::-1], ring[::-1])):  # spill after / before
        order = [xyz_, tail.T] if xyz_ is xyz else [tail.T[::-1], xyz_]
        cloud = np.concatenate(order)
        model = estimate_beams([cloud])
        assert model.n_beams == 64 and model.layout
        want = np.concatenate([ring_, np.full(60, 63)] if xyz_ is xyz else [np.full(60, 63), ring_])
        assert np.array_equal(model.ring_of(cloud), want)
        assert np.array_equal(layout_rings(cloud), want)


def test_a_recipe_and_the_beam_table_load_without_scipy_ndimage_signal_or_fft():
    """Start-up: scipy.ndimage / scipy.signal (the beam histogram of a driver without rings)
    and scipy.fft (loop verification) are imported where used, not by loading a recipe."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from slam.config import load_config\n"
        "load_config('improved_floam_loop')\n"
        "import slam.sensor.beam_table, slam.loop.plugin, slam.loop.bev\n"
        "print([m for m in ('scipy.ndimage', 'scipy.signal', 'scipy.fft') if m in sys.modules])\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True
    )
    assert run.stdout.strip().splitlines()[-1] == "[]"


def test_a_planar_scanner_is_described_as_one() -> None:
    angles = np.radians(np.arange(-90.0, 90.0, 1.0))
    xyz = np.column_stack([5 * np.cos(angles), 5 * np.sin(angles), np.zeros_like(angles)])
    model = beams_from_rings([xyz], [np.zeros(len(xyz), dtype=np.int16)])
    assert model.n_beams == 1
    assert model.describe() == "planar scanner (one beam), 99 % of returns within 5 m"
