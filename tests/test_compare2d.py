"""`slam compare` on a 2D laser log: DPCR-SLAM against its baseline in one command, with
the APE table and the map_server map of every 2D run (written by run_one, so compare and
sweep get it too, not only `slam run`)."""

from __future__ import annotations

import numpy as np

from slam.cli import main
from slam.io.grid_map import read_pgm


def test_compare_dpcr_against_icp2d_writes_table_and_maps(tmp_path):
    assert main(["simulate", "office2d", str(tmp_path / "sim"), "--frames", "60"]) == 0
    log, gt = tmp_path / "sim" / "office2d.clf", tmp_path / "sim" / "ground_truth.tum"
    out = tmp_path / "cmp"
    assert main(["compare", str(log), "--gt", str(gt), "--configs", "dpcr2d", "icp2d",
                 "--out", str(out), "--quiet"]) == 0  # fmt: skip
    table = (out / "compare.csv").read_text()
    assert "dpcr2d" in table and "icp2d" in table
    for name in ("dpcr2d", "icp2d"):
        traj = np.loadtxt(out / name / "trajectory.tum")
        assert len(traj) == 60
    img = read_pgm(out / "dpcr2d" / "map.pgm")
    occupied = (img < 50).mean()  # walls are a small share of a 5 cm office map
    assert 0.001 < occupied < 0.2
    assert "image: map.pgm" in (out / "dpcr2d" / "map.yaml").read_text()
