"""slam.bench.lego_table (benchmarks/table_lego.py): the ground-factor row replays the plain
run's front end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from slam.bench.lego_table import jobs_for, run_job
from slam.bench.loop_replay import load_recording, replay

FRAMES = 60  # the whole short corridor: a few keyframes


def test_ground_row_replays_the_recorded_plain_run(corridor_short, tmp_path):
    jobs = jobs_for("corridor", corridor_short, ["lego_lpb"], FRAMES, tmp_path, False,
                    ["lego_lpb"])  # fmt: skip
    assert [j["label"] for j in jobs] == ["lego_lpb", "lego_lpb + ground factor"]
    plain, ground = jobs
    assert ground["replay_of"] == plain["record"]
    assert "factors.ground.enabled=true" in ground["overrides"]

    row = run_job(plain)
    assert "error" not in row, row.get("error")
    assert row["frames_run"] == FRAMES and Path(plain["record"]).is_file()
    # the recording replayed without the factor is the run itself
    rec = load_recording(Path(plain["record"]))
    assert len(rec["stamps"]) == FRAMES
    replay(rec, "lego_lpb", [], tmp_path / "plain_replay", None)
    a = np.loadtxt(Path(plain["out"]) / "trajectory.tum")
    b = np.loadtxt(tmp_path / "plain_replay" / "trajectory.tum")
    assert a.shape == b.shape and np.abs(a - b).max() < 1e-9

    grow = run_job(ground)
    assert "error" not in grow, grow.get("error")
    assert grow["replayed"] == plain["record"] and grow["fps"] == row["fps"]
    assert grow["frames_run"] == FRAMES and grow["keyframes"] == row["keyframes"]
    # the factor acted: z is constrained (flat corridor floor), x/y stay with the odometry
    assert grow["z_rmse"] < 0.1 and grow["ape"]["rmse"] < 0.2
    factors = json.loads((Path(ground["out"]) / "metrics.json").read_text())["factors"]
    assert row["keyframes"] >= 3 and factors["ground"] >= 2  # chain mode: not the anchors


def test_no_replay_runs_the_ground_row_in_full(corridor_short, tmp_path):
    jobs = jobs_for("corridor", corridor_short, ["lego_lpb"], FRAMES, tmp_path, False,
                    ["lego_lpb"], replay_ground=False)  # fmt: skip
    assert all("record" not in j and "replay_of" not in j for j in jobs)
