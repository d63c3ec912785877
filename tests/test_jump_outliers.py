"""Range / intensity jump outliers along the rings (slam/preprocess/jump_outliers.py)."""

import numpy as np
import pytest

from slam.errors import ConfigError, InputError
from slam.io.source import open_source
from slam.preprocess.jump_outliers import JumpOutlierConfig, jump_outlier_mask


def _ring_scan(n_rings=4, n_az=720, radius=10.0):
    """A cylinder wall around the sensor: rings at +-5 deg, intensity 100 with a painted strip."""
    az = np.linspace(-np.pi, np.pi, n_az, endpoint=False)
    elev = np.radians(np.linspace(-5, 5, n_rings))
    A, E = np.meshgrid(az, elev)
    d = radius / np.cos(E)
    xyz = np.column_stack(
        [
            (d * np.cos(E) * np.cos(A)).ravel(),
            (d * np.cos(E) * np.sin(A)).ravel(),
            (d * np.sin(E)).ravel(),
        ]
    )
    ring = np.repeat(np.arange(n_rings), n_az).astype(np.int16)
    inten = np.full(len(xyz), 100.0)
    inten[(np.abs(A.ravel()) < 0.3)] = 10.0  # a dark strip: a material boundary, not spikes
    return xyz, inten, ring


def test_single_spikes_go_edges_and_boundaries_stay():
    xyz, inten, ring = _ring_scan()
    xyz[100] *= 1.5  # a range spike
    xyz[1000] *= 0.6
    inten[2000] = 250.0  # an intensity glint on the bright wall
    inten[2500] = 100.0 if inten[2500] < 50 else 0.0
    # a depth edge: a box face 2 m in front over 40 columns of ring 2
    xyz[1500:1540] *= 0.8
    perm = np.random.default_rng(0).permutation(len(xyz))  # any point order works
    keep = jump_outlier_mask(xyz[perm], inten[perm], ring[perm])
    keep = keep[np.argsort(perm)]
    assert not keep[[100, 1000, 2000, 2500]].any()
    assert keep[1500:1540].all() and keep[1460:1500].all() and keep[1540:1580].all()
    assert keep.sum() == len(xyz) - 4  # the strip's boundaries are kept too


def test_without_ring_everything_is_kept_and_bad_input_raises():
    xyz, inten, _ = _ring_scan()
    assert jump_outlier_mask(xyz, inten, None).all()
    with pytest.raises(InputError):
        jump_outlier_mask(xyz[:, :2], inten, None)
    with pytest.raises(InputError):
        jump_outlier_mask(xyz, inten, np.zeros(3, dtype=np.int16))
    with pytest.raises(ConfigError):
        JumpOutlierConfig(window=0)
    with pytest.raises(ConfigError):
        JumpOutlierConfig(min_agree=11)


def _inject(scan, seed):
    """Copy of the scan's xyz / intensity with 1 % range spikes and 1 % intensity spikes."""
    rng = np.random.default_rng(seed)
    n = len(scan)
    xyz = scan.xyz.copy()
    inten = scan.intensity.astype(np.float64).copy()
    spikes = rng.choice(n, n // 50, replace=False)
    r_sp, i_sp = spikes[: len(spikes) // 2], spikes[len(spikes) // 2 :]
    near = rng.random(len(r_sp)) < 0.5  # multipath long / early returns: -25..-70 %, +30..+100 %
    xyz[r_sp] *= np.where(
        near, rng.uniform(0.3, 0.75, len(r_sp)), rng.uniform(1.3, 2.0, len(r_sp))
    )[:, None]
    scale = np.quantile(inten, 0.95)  # glints saturate, weak echoes collapse
    inten[i_sp] = np.where(inten[i_sp] < 0.5 * scale, 1.5 * scale, 0.05 * scale)
    clean = np.ones(n, dtype=bool)
    clean[spikes] = False
    return xyz, inten, r_sp, i_sp, clean


@pytest.mark.parametrize("fixture", ["corridor_short", "plaza_short"])
def test_injected_spikes_are_dropped_on_simulated_scans(fixture, request):
    seq = request.getfixturevalue(fixture)
    rates = []
    for k, scan in enumerate(open_source(seq.bag)):
        if k not in (10, 45):
            continue
        xyz, inten, r_sp, i_sp, clean = _inject(scan, k)
        keep = jump_outlier_mask(xyz, inten, scan.ring)
        # the numba kernel equals the numpy reference, with and without intensity
        assert np.array_equal(keep, jump_outlier_mask(xyz, inten, scan.ring, reference=True))
        assert np.array_equal(
            jump_outlier_mask(xyz, None, scan.ring),
            jump_outlier_mask(xyz, None, scan.ring, reference=True),
        )
        rates.append((keep[clean].mean(), (~keep[r_sp]).mean(), (~keep[i_sp]).mean()))
    clean_kept, range_found, intensity_found = np.min(rates, axis=0)
    print(
        f"{fixture}: clean kept {clean_kept:.4f}, range spikes {range_found:.3f}, "
        f"intensity spikes {intensity_found:.3f}"
    )
    assert clean_kept > 0.99
    assert range_found > 0.9
    assert intensity_found > 0.8
