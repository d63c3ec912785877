"""The README's "Add your own factor" example, loaded by import path and by entry point."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from test_pipeline import ScriptedFrontend, circle_odometry, scans

from slam import plugins
from slam.config import from_dict
from slam.pipeline import Pipeline

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = Path(__file__).parent / "example_plugin" / "planar_motion.py"


def drifting_odometry():
    """Circle whose odometry climbs 1 cm per frame and tilts: what a planar factor fixes."""
    poses = circle_odometry(n=60, wobble=False)
    poses[:, 2, 3] = 0.01 * np.arange(len(poses))
    return poses


def run_with(factors):
    config = from_dict({"factors": factors})
    pipe = Pipeline(config, frontend=ScriptedFrontend(drifting_odometry()))
    return pipe.run(scans(60)).trajectory()


def test_readme_shows_the_tested_example():
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, flags=re.S)
    assert EXAMPLE.read_text().strip() in [b.strip() for b in blocks]


def test_example_by_import_path_flattens_the_trajectory():
    base = run_with({"prior": {}, "odometry": {}})
    planar = run_with(
        {
            "prior": {},
            "odometry": {},
            "planar": {"plugin": "example_plugin.planar_motion:PlanarMotion", "sigma_z": 0.01},
        }
    )
    z_base, z_planar = np.abs(base[:, 2, 3]).max(), np.abs(planar[:, 2, 3]).max()
    assert z_base > 0.5
    assert z_planar < 0.25 * z_base


def test_example_by_entry_point(tmp_path, monkeypatch):
    dist = tmp_path / "planar_example-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: planar-example\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(
        "[slam.factors]\nplanar = example_plugin.planar_motion:PlanarMotion\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "planar" in plugins.available("slam.factors")
    cls = plugins.load("slam.factors", "planar")
    assert cls.__name__ == "PlanarMotion"
    traj = run_with({"prior": {}, "odometry": {}, "planar": {"sigma_z": 0.01}})
    assert np.abs(traj[:, 2, 3]).max() < 0.15
