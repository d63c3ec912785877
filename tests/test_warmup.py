"""Warm-up (slam/warmup.py): the synthetic scans are what the front end expects, and one
warm-up in a fresh interpreter loads the kernels of the default recipe's hot stages."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from slam.config import load_config
from slam.plugins import instantiate
from slam.warmup import synthetic_scans, without_start_search

# the kernels of SOR, the range image and the window search a 64-beam frame spends most in
HOT = (
    "slam.preprocess.range_image_kernels:window_knn",
    "slam.preprocess.range_image_kernels:range_image_into",
    "slam.preprocess.range_image_kernels:box_knn",
    "slam.preprocess.sor_kernels:weighted_sor_kernel_simd",
)


def test_synthetic_scans_have_driver_fields_and_register():
    scans = synthetic_scans()
    assert len(scans) == 3
    for s in scans:
        assert s.xyz.dtype == np.float64 and s.xyz.shape == (16 * 600, 3)
        assert s.ring.dtype == np.int16 and s.ring.max() == 15
        assert s.intensity.dtype == np.float32
        assert 0.0 <= s.time.min() and s.time.max() < 0.1
        r = np.linalg.norm(s.xyz, axis=1)
        assert 0.5 < r.min() and r.max() < 30.0  # inside the 24 x 14 x 4 m room
    fe = instantiate("slam.frontends", load_config("improved_floam").frontend, "frontend")
    poses = [fe.process(s).pose for s in scans[:2]]
    step = poses[1][:3, 3] - poses[0][:3, 3]
    assert abs(step[0] - 0.2) < 0.02 and np.abs(step[1:]).max() < 0.02  # 0.2 m along x


def test_warm_up_loads_the_hot_kernels_in_a_fresh_process():
    code = f"""
import importlib, json
from slam.config import load_config
from slam.warmup import warm_up
def loaded():
    return [len(getattr(importlib.import_module(m), f).signatures) > 0
            for m, f in (name.split(":") for name in {HOT!r})]
before = loaded()
seconds = warm_up(load_config("improved_floam").frontend)
print(json.dumps([before, loaded(), seconds]))
"""
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True
    )
    before, after, seconds = json.loads(run.stdout.strip().splitlines()[-1])
    assert before == [False] * len(HOT)
    assert after == [True] * len(HOT)
    assert seconds > 0


def test_warm_up_front_end_skips_the_start_search_only():
    section = load_config("improved_floam").frontend
    quick = without_start_search(section)
    assert quick["start_max_speed"] == 0.0
    assert {k: v for k, v in quick.items() if k != "start_max_speed"} == section
    assert "start_max_speed" not in section  # the caller's section is not changed
    fe = instantiate("slam.frontends", quick, "frontend")
    assert fe.cfg.start_max_speed == 0.0
    # a front end without the search (2D) keeps its section as it is
    assert without_start_search(load_config("dpcr2d").frontend) == load_config("dpcr2d").frontend
