"""`slam demo`: odometry only vs loop closed from one run, its table and its report (first
figure: both trajectories over the ground truth), on a short corridor piece."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest

from slam.cli import build_parser, main
from slam.cli.demo import DEMO_FRAMES, DEMO_SCENE, demo_frames
from slam.eval.metrics import evaluate

pytestmark = pytest.mark.usefixtures("evo_home")  # tests/conftest.py


def test_demo_defaults_to_the_city_drive_with_its_revisit():
    args = build_parser().parse_args(["demo"])
    assert (args.scene, args.frames, args.config) == (DEMO_SCENE, None, "improved_floam_loop")
    assert DEMO_SCENE == "urban" and DEMO_FRAMES >= 1200  # reaches the street driven back
    assert demo_frames(args.scene, args.frames) == DEMO_FRAMES  # of its 1669


def test_demo_of_a_shorter_scene_runs_all_of_it_unless_told(tmp_path, capsys):
    args = build_parser().parse_args(["demo", "--scene", "corridor"])
    assert demo_frames(args.scene, args.frames) is None  # all 608: the cached whole sequence
    assert demo_frames("corridor", 300) == 300
    code = main(["demo", "--scene", "corridor", "--frames", "700", "--out", str(tmp_path)])
    assert code == 2
    assert "scene 'corridor' has 608 frames; frames=700 is out of range" in capsys.readouterr().err


@pytest.fixture(scope="module")
def demo(corridor_short, tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    code = main(["demo", "--scene", "corridor", "--frames", "60", "--out", str(out), "--quiet"])
    return code, out, corridor_short


def test_demo_table_rows_are_the_two_trajectories_of_one_run(demo, capsys):
    code, out, seq = demo
    assert code == 0
    lines = (out / "demo.md").read_text().splitlines()
    rows = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[2:-1]] for ln in lines[2:]}
    assert list(rows) == [
        "odometry only",
        "loop closed",
        "% improvement loop closed vs odometry only",
    ]
    run = out / "improved_floam_loop"
    rmse = {
        name: evaluate(run / f, seq.ground_truth).ape_trans["rmse"]
        for name, f in (("odometry only", "odometry.tum"), ("loop closed", "trajectory.tum"))
    }
    for name, value in rmse.items():
        assert float(rows[name][4]) == pytest.approx(value, abs=1e-4)  # RMSE column
    change = (rmse["odometry only"] - rmse["loop closed"]) / rmse["odometry only"] * 100
    assert float(rows["% improvement loop closed vs odometry only"][4]) == pytest.approx(
        change, abs=1e-3
    )
    assert rmse["loop closed"] < 0.05  # a 60-frame corridor piece: centimetres


def test_demo_report_opens_with_the_trajectories_and_shows_the_map(demo):
    _, out, _ = demo
    text = (out / "report.html").read_text()
    srcs = re.findall(r'src="data:image/png;base64,([^"]+)"', text)
    first = base64.b64decode(srcs[0])
    assert first == (out / "plots" / "odometry_vs_loop_closed.png").read_bytes()
    assert base64.b64decode(srcs[1]) == (out / "plots" / "map_birdseye.png").read_bytes()
    assert text.index("<img") < text.index("<h2>APE") < text.index("<h2>Map")
    metrics = json.loads((out / "improved_floam_loop" / "metrics.json").read_text())
    assert metrics["frames"] == 60
    # the run's own folder has its own report, with its map
    run_report = (out / "improved_floam_loop" / "report.html").read_text()
    assert "<h2>Map</h2>" in run_report
    assert np.isfinite(metrics["frames_per_second"])


def test_demo_stopped_before_two_frames_says_so_and_exits_130(tmp_path, capsys, monkeypatch):
    """Ctrl-C during the first frame: nothing to evaluate; the exit code is Ctrl-C's, not bad
    input's, and the run's outputs are kept."""
    import os
    import signal

    from slam.system import SlamSystem

    real = SlamSystem.process

    def process(self, scan):
        if scan.index == 0:
            os.kill(os.getpid(), signal.SIGINT)
        return real(self, scan)

    monkeypatch.setattr(SlamSystem, "process", process)
    code = main(["demo", "--scene", "corridor", "--frames", "60", "--out", str(tmp_path),
                 "--quiet"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 130 and "Traceback" not in err
    assert "the demo stopped before it had two frames to evaluate" in err
    assert "run stopped early: interrupted" in err
    assert (tmp_path / "improved_floam_loop" / "trajectory.tum").is_file()
