"""benchmarks/unseen_sweep.py: its case names and its ran-away rule (APE > 2 % of the path
or a step error > 1 m)."""

import importlib.util
from pathlib import Path

import pytest

_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
_spec = importlib.util.spec_from_file_location("unseen_sweep", _DIR / "unseen_sweep.py")
unseen = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(unseen)


def test_case_names():
    c = unseen.parse_case("urban:1:hdl64", 150)
    assert (c["scene"], c["seed"], c["sensor"], c["strip"], c["frames"]) == (
        "urban",
        1,
        "hdl64",
        False,
        150,
    )
    c = unseen.parse_case("street:0:vlp16:strip@300", 150)
    assert (c["scene"], c["sensor"], c["strip"], c["frames"]) == ("street", "vlp16", True, 300)
    assert unseen.parse_case("kitti", 150)["kind"] == "kitti"
    for bad in ("urban:1", "urban:1:vlp16:nostrip", "urban:x:vlp16"):
        with pytest.raises((SystemExit, ValueError)):
            unseen.parse_case(bad, 150)


def test_ran_away_rule():
    ok = {"path_m": 122.5, "ape_rmse": 0.047, "step_err_max": 0.03}
    assert unseen.ran_away(ok) == ""
    # 2 % of 122.5 m is 2.45 m; a step error of 0.5 m per frame (the robustness sweeps' limit)
    assert "APE 2.1 % of path" in unseen.ran_away({**ok, "ape_rmse": 2.6})
    assert unseen.ran_away({**ok, "ape_rmse": 2.4}) == ""
    assert "step error 0.65 m" in unseen.ran_away({**ok, "step_err_max": 0.65})
    assert unseen.ran_away({**ok, "step_err_max": 0.49}) == ""
    # short paths are judged by the step alone; a crash is a finding
    assert unseen.ran_away({"path_m": 10.0, "ape_rmse": 1.0, "step_err_max": 0.1}) == ""
    assert "boom" in unseen.ran_away({"error": "RuntimeError('boom')"})
