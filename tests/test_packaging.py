"""The wheel carries every package and the built-in recipes (issue: a non-editable install
found no configs). The full install check is scripts/wheel_check.sh, run by CI."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from slam.config import available_configs, load_config
from slam.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_dir_is_listed_in_pyproject():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    listed = set(pyproject["tool"]["setuptools"]["packages"])
    found = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for top in ("slam", "frontends", "backends")
        for p in (ROOT / top).rglob("__init__.py")
    }
    found.add("slam.configs")
    assert found == listed


def test_builtin_recipes_load_from_the_package():
    names = available_configs()
    assert {"improved_floam", "floam", "improved_floam_loop", "floam_loop"} <= set(names)
    assert len(names) == len(list((ROOT / "configs").glob("*.yaml")))
    cfg = load_config("improved_floam_loop")
    assert cfg.name == "improved_floam_loop"
    assert cfg.frontend["name"] == "improved_floam"  # inherited through base:
    assert cfg.factors["loop_closure"]["enabled"] is True


def test_unknown_recipe_lists_the_builtin_ones():
    listed = "built-in configs: .*floam, floam_loop, .*improved_floam, "
    with pytest.raises(ConfigError, match=listed):
        load_config("no_such_recipe")
