"""The loop closure's nested config and the flat keys of version 0.1: a recipe written for
0.1 runs unchanged, with one warning naming each key's new place."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import yaml
from test_recipe_defaults import config_lists_every_field

from slam.cli import main
from slam.config import (
    ConfigDeprecationWarning,
    build_dataclass,
    load_config,
    upgrade_keys,
)
from slam.errors import ConfigError
from slam.loop.config import FLAT_KEYS, LoopConfig
from slam.pipeline import resolved_config

# configs/improved_floam_loop.yaml of version 0.1, its keys verbatim (the measurement comment
# left out)
RECIPE_0_1 = """\
# improved FLOAM + Scan Context loop closure (two layers: descriptor proposes, GICP verifies).
# Everything else is inherited from improved_floam.yaml; `slam run --no-loop` with this
# recipe reproduces improved_floam exactly.
base: improved_floam
factors:
  loop_closure:
    enabled: true
    verify_workers: 1
    min_keyframe_gap: 3
"""
FRAMES = 30
# every setting of version 0.1's flat loop Config and its default
DEFAULTS_0_1 = {
    "rings": 20,
    "sectors": 60,
    "max_radius": 0.0,
    "lidar_height": -1.0,
    "auto_keyframes": 10,
    "exclude_recent": 30,
    "exclude_seconds": 0.0,
    "top_k": 10,
    "sc_threshold": 0.25,
    "rebuild_every": 10,
    "shift_window": 0,
    "proximity_radius": 0.0,
    "descriptor": "scan_context",
    "proposer": "descriptor",
    "radius": 7.0,
    "radius_min_seconds": 30.0,
    "cc_threshold": 0.25,
    "ground_clearance": 0.3,
    "cc_rows": 80,
    "cc_cols": 20,
    "cc_lateral": 20.0,
    "cc_longitudinal": 40.0,
    "lateral_shifts": 10,
    "longitudinal_shifts": 5,
    "verify_voxel": 0.25,
    "neighbours": 0,
    "max_correspondence": 1.0,
    "coarse_voxel": 0.5,
    "coarse_max_correspondence": 2.0,
    "global_search": 20.0,
    "try_flip": True,
    "max_offset": 20.0,
    "inlier_distance": 0.3,
    "beam_gap_deg": 2.0,
    "plane_tolerance": 0.1,
    "plane_range_ratio": 0.002,
    "max_fitness": 0.1,
    "min_overlap": 0.4,
    "min_overlap_near": 0.65,
    "overlap_loss_per_m": 0.015,
    "yaw_tolerance_deg": 15.0,
    "max_verify": 1,
    "min_keyframe_gap": 0,
    "consistency_base": 3.0,
    "consistency_ratio": 0.04,
    "consistency_yaw_deg": 45.0,
    "pair_window": 10,
    "pair_base": 0.5,
    "pair_ratio": 0.02,
    "pair_base_deg": 2.0,
    "pair_ratio_deg": 0.5,
    "min_sigma_trans": 0.05,
    "min_sigma_rot_deg": 0.5,
    "min_sigma_tilt_deg": 1.0,
    "max_sigma_ratio": 100.0,
    "coarse_registration": "gicp",
    "coarse_vgicp_resolution": 1.0,
    "ambiguity_ratio": 0.8,
    "free_sigma": 20.0,
    "verify_workers": 0,
    "verify_lag": 2,
}


def _deprecations(record: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, ConfigDeprecationWarning)]


def test_every_flat_key_has_a_nested_place_with_the_same_default():
    """All settings of 0.1's flat Config map onto a field whose default is 0.1's (the
    plugin's own sigma floors are VerifyParams' defaults now)."""
    assert set(FLAT_KEYS) == set(DEFAULTS_0_1)
    cfg = LoopConfig()
    for old, new in FLAT_KEYS.items():
        value = cfg
        for part in new.split("."):
            value = getattr(value, part)  # AttributeError: no such place
        assert value == DEFAULTS_0_1[old], (old, new, value)


def test_flat_keys_build_the_same_config_as_nested_ones_with_one_warning():
    flat = {"sc_threshold": 0.3, "descriptor": "scan_context_pp", "pair_window": 0,
            "free_sigma": 0.0, "verify_workers": 1}  # fmt: skip
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        old = build_dataclass(LoopConfig, flat, "factors.loop_closure")
    nested = build_dataclass(
        LoopConfig,
        {"search": {"threshold": 0.3}, "descriptor": {"kind": "scan_context_pp"},
         "consistency": {"pairwise": {"window": 0}}, "verify": {"free_sigma": 0.0},
         "workers": {"processes": 1}},
        "factors.loop_closure",
    )  # fmt: skip
    assert old == nested
    (message,) = _deprecations(record)
    for key, place in [("sc_threshold", "search.threshold"), ("descriptor", "descriptor.kind"),
                       ("pair_window", "consistency.pairwise.window"),
                       ("verify_workers", "workers.processes")]:  # fmt: skip
        assert f"{key} -> {place}" in message


def test_nested_keys_give_no_warning_and_a_key_given_twice_is_an_error():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_dataclass(LoopConfig, {"search": {"threshold": 0.3}}, "loop")
    with pytest.raises(ConfigError, match="sc_threshold.*search.threshold.*both"):
        upgrade_keys(LoopConfig, {"sc_threshold": 0.3, "search": {"threshold": 0.2}}, "loop")
    with pytest.raises(ConfigError, match="valid keys of 'loop.search'"):
        build_dataclass(LoopConfig, {"search": {"sc_threshold": 0.3}}, "loop")


def test_a_flat_override_reaches_the_nested_field():
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cfg = load_config("improved_floam_loop", ["factors.loop_closure.sc_threshold=0.3"])
    assert cfg.factors["loop_closure"]["search"] == {"min_keyframe_gap": 3, "threshold": 0.3}
    assert len(_deprecations(record)) == 1


@pytest.fixture(scope="module")
def two_runs(corridor_short, tmp_path_factory):
    """The 0.1 recipe and today's improved_floam_loop on the same frames; the warnings."""
    tmp = tmp_path_factory.mktemp("recipe_0_1")
    recipe = tmp / "my_loop.yaml"
    recipe.write_text(RECIPE_0_1)
    outs = {}
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        for name, config in (("old", str(recipe)), ("new", "improved_floam_loop")):
            outs[name] = tmp / name
            args = ["run", str(corridor_short.bag), "--config", config, "--out",
                    str(outs[name]), "--max-frames", str(FRAMES), "--quiet"]  # fmt: skip
            assert main(args) == 0
    return outs, record


def test_recipe_of_version_0_1_runs_unchanged_with_one_warning(two_runs):
    outs, record = two_runs
    (message,) = _deprecations(record)  # the second run, nested, warns nothing
    assert "verify_workers -> workers.processes" in message
    assert "min_keyframe_gap -> search.min_keyframe_gap" in message
    old, new = (np.loadtxt(outs[n] / "trajectory.tum") for n in ("old", "new"))
    assert len(old) == FRAMES
    np.testing.assert_array_equal(old, new)
    resolved = {n: yaml.safe_load((outs[n] / "config.yaml").read_text()) for n in outs}
    resolved["old"]["name"] = resolved["new"]["name"]
    assert resolved["old"] == resolved["new"]
    loop = resolved["old"]["factors"]["loop_closure"]
    assert loop["workers"] == {"processes": 1, "lag": 2}
    assert loop["search"]["min_keyframe_gap"] == 3 and "verify_workers" not in loop


def test_the_run_config_yaml_lists_every_field(two_runs):
    outs, _ = two_runs
    written = yaml.safe_load((outs["new"] / "config.yaml").read_text())
    config = load_config("improved_floam_loop", [f"source.max_frames={FRAMES}"])
    assert config_lists_every_field(written, config) == []
    expected = resolved_config(config)
    expected["name"] = written["name"]
    assert written == expected
