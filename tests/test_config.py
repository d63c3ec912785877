"""Typed config loading: recipes, base chains, overrides and the errors users see."""

from dataclasses import dataclass, field

import pytest

from slam.config import (
    apply_overrides,
    available_configs,
    build_dataclass,
    deep_merge,
    from_dict,
    load_config,
    parse_override,
)
from slam.errors import ConfigError


@dataclass
class Inner:
    k: int = 10
    alpha: float = 1.0


@dataclass
class Outer:
    inner: Inner = field(default_factory=Inner)
    name: str = "x"
    flag: bool = False
    topic: str | None = None


def test_build_nested_with_coercion():
    cfg = build_dataclass(Outer, {"inner": {"k": 8, "alpha": 2}, "flag": True}, "frontend")
    assert cfg.inner.k == 8 and cfg.inner.alpha == 2.0 and isinstance(cfg.inner.alpha, float)
    assert cfg.flag is True and cfg.topic is None


def test_exponent_without_dot_is_a_number():
    """YAML 1.1 leaves 1e-3 a string; a float field still reads it as 0.001."""
    cfg = build_dataclass(Outer, {"inner": {"alpha": "1e-3"}}, "x")
    assert cfg.inner.alpha == pytest.approx(0.001)
    assert build_dataclass(Outer, {"inner": {"alpha": "-2.5E2"}}, "x").inner.alpha == -250.0


def test_unknown_key_lists_valid_keys():
    with pytest.raises(ConfigError) as err:
        build_dataclass(Outer, {"inner": {"kk": 3}}, "frontend")
    msg = str(err.value)
    assert "frontend.inner.kk" in msg and "k, alpha" in msg


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"inner": {"k": 1.5}}, "expected an integer"),
        ({"flag": "yes"}, "true/false"),
        ({"name": 3}, "expected a string"),
        ({"inner": 5}, "expected a mapping"),
        ({"inner": {"alpha": "1e"}}, "expected a number"),
    ],
)
def test_bad_types_are_errors(data, fragment):
    with pytest.raises(ConfigError, match=fragment):
        build_dataclass(Outer, data, "x")


def test_override_parsing_and_application():
    assert parse_override("frontend.sor.k=8") == (["frontend", "sor", "k"], 8)
    assert parse_override("source.topic=/points")[1] == "/points"
    raw = apply_overrides({"frontend": {"name": "a", "sor": {"k": 10}}}, ["frontend.sor.k=5"])
    assert raw["frontend"]["sor"]["k"] == 5
    with pytest.raises(ConfigError, match="section.key=value"):
        parse_override("nokey")


def test_deep_merge_replaces_plugin_section_when_name_changes():
    base = {"frontend": {"name": "a", "x": 1}, "factors": {"prior": {}}}
    merged = deep_merge(base, {"frontend": {"name": "b"}, "factors": {"loop": {"enabled": True}}})
    assert merged["frontend"] == {"name": "b"}
    assert set(merged["factors"]) == {"prior", "loop"}
    assert deep_merge(base, {"frontend": {"x": 2}})["frontend"] == {"name": "a", "x": 2}


def test_unknown_top_level_section_and_unknown_config_name():
    with pytest.raises(ConfigError, match="valid keys"):
        from_dict({"frontendd": {"name": "x"}})
    with pytest.raises(ConfigError, match="built-in configs"):
        load_config("no_such_recipe")


def test_builtin_recipes_load_and_loop_recipe_inherits():
    names = available_configs()
    assert {"floam", "floam_loop", "improved_floam", "improved_floam_loop"} <= set(names)
    base = load_config("improved_floam")
    loop = load_config("improved_floam_loop")
    assert loop.name == "improved_floam_loop"
    assert loop.frontend == base.frontend
    assert loop.factors["loop_closure"]["enabled"] is True
    assert base.factors.get("loop_closure", {}).get("enabled", False) is False
    floam, floam_loop = load_config("floam"), load_config("floam_loop")
    assert floam_loop.frontend == floam.frontend and floam_loop.frontend["name"] == "floam"
    assert floam_loop.factors["loop_closure"]["enabled"] is True


def test_a_swapped_front_or_back_end_is_in_the_run_name():
    """--set frontend.name=floam on improved_floam ran floam under improved_floam's name."""
    from slam.config import load_config

    assert load_config("improved_floam", ["frontend.name=floam"]).name == "improved_floam+floam"
    assert load_config("dpcr2d", ["backend.name=isam2"]).name == "dpcr2d+isam2"
    assert load_config("improved_floam", ["frontend.name=improved_floam"]).name == "improved_floam"
    assert load_config("improved_floam_loop", ["backend.name=isam2"]).name == "improved_floam_loop"
    assert load_config("improved_floam", ["frontend.name=floam", "name=mine"]).name == "mine"
    assert load_config("improved_floam", ["frontend.sor.k=8"]).name == "improved_floam"
