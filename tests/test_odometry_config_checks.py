"""The scan-to-map front ends' settings check themselves: a value with no physical meaning
(a crop that keeps nothing, a negative keyframe distance, a voxel of 0 m) is a ConfigError
naming the key, the value and the rule, and ``slam run`` exits 2 before reading a scan."""

from __future__ import annotations

import pytest

from slam import plugins
from slam.cli import main
from slam.config import available_configs, load_config
from slam.errors import ConfigError
from slam.pipeline import resolved_config

FRONTENDS = ["floam", "improved_floam", "lego_loam", "lego_lpb"]


def frontend_config(name: str, overrides: list[str]):
    """The front end ``name``'s Config built from the built-in recipe of that name and
    ``overrides`` (``--set`` syntax), the way ``slam run`` builds it."""
    config = load_config(name, overrides)
    cls = plugins.load("slam.frontends", config.frontend["name"])
    return plugins.plugin_config(cls, config.frontend, "frontend")


@pytest.mark.parametrize("name", FRONTENDS)
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["frontend.min_range=50", "frontend.max_range=10"],
            r"min_range \(50.0 m\).*max_range \(10.0 m\)",
        ),
        (["frontend.min_range=-1"], r"min_range \(-1.0 m\) must be >= 0"),
        (["frontend.max_range=0", "frontend.min_range=0"], r"max_range \(0.0 m\)"),
        (["frontend.keyframe.translation=-1"], r"keyframe.translation must be > 0 m.*got -1.0"),
        (["frontend.keyframe.rotation_deg=0"], r"keyframe.rotation_deg must be > 0 deg.*got 0.0"),
        (["frontend.cloud_voxel=0"], r"frontend.cloud_voxel must be > 0, got 0.0"),
        (["frontend.plane_voxel=-0.4"], r"frontend.plane_voxel must be > 0, got -0.4"),
        (["frontend.edge_voxel=0"], r"frontend.edge_voxel must be > 0, got 0.0"),
        (["frontend.deskew_smoothing=1"], r"deskew_smoothing must be in \[0, 1\).*got 1.0"),
        (["frontend.min_points=-3"], r"frontend.min_points must be >= 0, got -3"),
        (["frontend.max_lost_seconds=-5"], r"frontend.max_lost_seconds must be >= 0, got -5.0"),
        (["frontend.drift_translation=-0.01"], r"drift_translation must be >= 0, got -0.01"),
        (
            ["frontend.information.max_sigma_translation=0.001"],
            r"min_sigma_translation <= max_sigma_translation.*got 0.01 and 0.001",
        ),
        (["frontend.information.min_sigma_rotation_deg=0"], r"0 < min_sigma_rotation_deg"),
        (["frontend.information.degenerate_factor=0.5"], r"degenerate_factor must be >= 1"),
    ],
)  # fmt: skip
def test_meaningless_frontend_values_are_config_errors(name, overrides, message):
    with pytest.raises(ConfigError, match=message):
        frontend_config(name, overrides)


@pytest.mark.parametrize(
    ("name", "key"),
    [
        ("improved_floam", "covariance_voxel"),
        ("lego_loam", "ground_voxel"),
        ("lego_lpb", "ground_voxel"),
    ],
)
def test_each_frontends_own_voxels_are_checked(name, key):
    with pytest.raises(ConfigError, match=rf"frontend.{key} must be > 0, got 0.0"):
        frontend_config(name, [f"frontend.{key}=0"])


@pytest.mark.parametrize("name", FRONTENDS)
def test_the_edge_values_that_mean_off_stay_valid(name):
    """0 switches several safeguards off (min_range, the map's motion thresholds, the speed
    starts, the lost timeout): still accepted, and read back."""
    cfg = frontend_config(
        name,
        [
            "frontend.min_range=0",
            "frontend.max_range=0.5",
            "frontend.map_min_translation=0",
            "frontend.map_min_rotation_deg=0",
            "frontend.start_max_speed=0",
            "frontend.max_lost_seconds=0",
            "frontend.deskew_smoothing=0",
            "frontend.keyframe.translation=0.01",
        ],
    )
    assert (cfg.min_range, cfg.max_range, cfg.map_min_translation) == (0.0, 0.5, 0.0)
    assert (cfg.start_max_speed, cfg.max_lost_seconds, cfg.keyframe.translation) == (0, 0, 0.01)


@pytest.mark.parametrize("name", available_configs())
def test_every_builtin_recipe_passes_the_checks(name):
    resolved = resolved_config(load_config(name))  # builds every plugin's Config
    assert resolved["frontend"]["name"]


def test_loop_verify_sigma_floors_are_checked():
    """The loop's information comes from these floors: 0 or a ratio below 1 is an error at
    load, not inside the first verification."""
    for bad, message in (
        ("min_sigma_trans=0", "min_sigma_trans must be > 0, got 0"),
        ("max_sigma_ratio=0.5", "max_sigma_ratio must be >= 1, got 0.5"),
    ):
        config = load_config("improved_floam_loop", [f"factors.loop_closure.verify.{bad}"])
        with pytest.raises(ConfigError, match=message):
            resolved_config(config)
    off = load_config("improved_floam_loop", ["factors.loop_closure.verify.min_sigma_tilt_deg=0"])
    assert resolved_config(off)["factors"]["loop_closure"]["verify"]["min_sigma_tilt_deg"] == 0


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["frontend.min_range=50", "frontend.max_range=10"], "frontend.min_range (50.0 m)"),
        (["frontend.keyframe.translation=-1"], "frontend.keyframe.translation must be > 0 m"),
    ],
)
def test_slam_run_exits_2_with_the_message_and_writes_nothing(
    tmp_path, corridor_short, capsys, overrides, fragment
):
    out = tmp_path / "o"
    args = ["run", str(corridor_short.bag), "--out", str(out), "--quiet"]
    for o in overrides:
        args += ["--set", o]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and fragment in err and "Traceback" not in err
    assert not out.exists()
