"""Bad input the CLI finds before computing anything (exit 2, nothing run), and what the
run summary says about degenerate frames or an empty map."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np

from slam.cli import main
from slam.cli.run import degenerate_warning, print_run_summary
from slam.io.trajectory import read_tum, write_tum


def bad_ground_truth(tmp_path, corridor_short):
    """The corridor's ground truth with a zero quaternion on its 4th pose."""
    stamps, poses = read_tum(corridor_short.ground_truth)
    path = tmp_path / "bad_gt.tum"
    write_tum(path, stamps, poses)
    lines = path.read_text().splitlines()
    lines[4] = " ".join(lines[4].split()[:4] + ["0", "0", "0", "0"])
    path.write_text("\n".join(lines) + "\n")
    return path


def test_run_and_compare_read_the_ground_truth_before_the_scans(tmp_path, corridor_short, capsys):
    gt = bad_ground_truth(tmp_path, corridor_short)
    out = tmp_path / "run"
    assert main(["run", str(corridor_short.bag), "--gt", str(gt), "--out", str(out),
                 "--quiet"]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "bad_gt.tum, line 5: zero quaternion" in err and "Traceback" not in err
    assert not out.exists()  # nothing was processed or written
    out = tmp_path / "cmp"
    assert main(["compare", str(corridor_short.bag), "--gt", str(gt), "--out", str(out),
                 "--configs", "floam", "--quiet"]) == 2  # fmt: skip
    assert "line 5: zero quaternion" in capsys.readouterr().err
    assert not (out / "floam" / "metrics.json").exists()
    same = tmp_path / "same.tum"
    write_tum(same, np.zeros(5), np.tile(np.eye(4), (5, 1, 1)))
    assert main(["run", str(corridor_short.bag), "--gt", str(same), "--out", str(out),
                 "--quiet"]) == 2  # fmt: skip
    assert "same stamp" in capsys.readouterr().err


def test_compare_resolves_every_config_before_the_first_run(tmp_path, corridor_short, capsys):
    out = tmp_path / "cmp"
    args = ["compare", str(corridor_short.bag), "--gt", str(corridor_short.ground_truth)]
    assert main([*args, "--out", str(out), "--configs", "floam", "nosuch", "--quiet"]) == 2
    assert "unknown config 'nosuch'" in capsys.readouterr().err
    assert not (out / "floam").exists()  # floam did not run first
    # the plugin keys of a recipe file are checked before any run too
    bad = tmp_path / "bad_k.yaml"
    bad.write_text("base: improved_floam\nfrontend: {name: improved_floam, sor: {k: abc}}\n")
    assert main([*args, "--out", str(out), "--configs", "floam", str(bad), "--quiet"]) == 2
    assert "frontend.sor.k: expected an integer" in capsys.readouterr().err
    assert not (out / "floam").exists()


def test_sweep_checks_every_grid_value_before_running(tmp_path, corridor_short, capsys):
    out = tmp_path / "sweep"
    args = ["sweep", str(corridor_short.bag), "--gt", str(corridor_short.ground_truth),
            "--out", str(out), "--quiet", "--workers", "1"]  # fmt: skip
    assert main([*args, "--grid", "frontend.sor.k=8,abc"]) == 2
    err = capsys.readouterr().err
    assert "grid point frontend.sor.k=abc: frontend.sor.k: expected an integer" in err
    assert not out.exists()  # k=8 did not run first
    gt = bad_ground_truth(tmp_path, corridor_short)
    args[3] = str(gt)
    assert main([*args, "--grid", "frontend.sor.k=8"]) == 2
    assert "line 5: zero quaternion" in capsys.readouterr().err and not out.exists()


def test_summary_warns_of_degenerate_frames_and_an_empty_map(tmp_path, capsys):
    metrics = {"frames": 40, "keyframes": 3, "degenerate_frames": 12, "map_points": 5000}
    assert degenerate_warning(metrics, {}) == (
        "12 of 40 frames were degenerate (the scans constrain the motion poorly along "
        "some direction: a corridor, an open field)"
    )
    empty = {"frames": 40, "keyframes": 0, "degenerate_frames": 0}
    assert degenerate_warning(empty, {}).startswith("the map is empty")
    assert degenerate_warning({**metrics, "degenerate_frames": 0}, {}) is None
    no_map = SimpleNamespace(config=SimpleNamespace(output=SimpleNamespace(write_map=False)))
    assert degenerate_warning(empty, {"system": no_map}) is None  # no map was asked for
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    print_run_summary({"out": tmp_path, "frames": 40, "keyframes": 3})
    err = capsys.readouterr().err
    assert "warning: 12 of 40 frames were degenerate" in err
    (tmp_path / "metrics.json").write_text(json.dumps({**metrics, "degenerate_frames": 0}))
    print_run_summary({"out": tmp_path, "frames": 40, "keyframes": 3})
    assert "warning" not in capsys.readouterr().err
