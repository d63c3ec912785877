"""benchmarks/bench_scenes.py: the calibration draws it simulates a sensor with."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from slam.sim.simulate import effective_model


def _bench():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_scenes.py"
    spec = importlib.util.spec_from_file_location("bench_scenes", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_calibration_draws_change_only_the_per_beam_errors():
    bench = _bench()
    own = effective_model("urban", sensor="hdl32")
    assert own.has_calibration_error  # the urban drive's sensors are the realistic ones
    assert bench.calibrated("urban", "hdl32", None) is None  # the default sequence
    ideal = bench.calibrated("urban", "hdl32", "ideal")
    assert not ideal.has_calibration_error
    assert ideal.range_sigma == own.range_sigma and ideal.mixed_pixel_prob == own.mixed_pixel_prob
    other = bench.calibrated("urban", "hdl32", "1")
    assert other.calibration_seed == 1 and other.beams == own.beams == 32
    e0, a0, r0 = own.calibration()
    e1, a1, r1 = other.calibration()
    # another unit with the same spread (0.1 deg): different per-beam angles
    assert not np.allclose(e0, e1) and not np.allclose(a0, a1)
    assert 0.05 < np.degrees(np.std(e1)) < 0.2
