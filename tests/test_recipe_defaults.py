"""One source of defaults: the Config dataclasses. A recipe holds only what differs from them
(or from its ``base`` recipe), and the resolved config a run writes lists every field."""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path
from typing import Any

import pytest

from slam import plugins
from slam.config import (
    OutputConfig,
    SourceConfig,
    _locate,
    _read_yaml,
    available_configs,
    from_dict,
    load_config,
    load_raw,
)
from slam.pipeline import resolved_config

RECIPES = available_configs()
SELECTORS = ("name", "plugin")  # a section's choice of plugin, not a setting


def _leaves(d: dict[str, Any], pre: tuple[str, ...] = ()):
    """(key path, value) of every setting; an empty mapping (a factor switched on with its
    defaults) is a selection, not a setting."""
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, pre + (k,))
        else:
            yield pre + (k,), v


def _get(d: Any, path: tuple[str, ...]) -> Any:
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return KeyError
        d = d[p]
    return d


def _pinned(path: Path) -> set[tuple[str, ...]]:
    """Key paths whose line says ``# pinned: why`` (kept although equal to the default)."""
    out, stack = set(), []
    for line in path.read_text().splitlines():
        m = re.match(r"^(\s*)([A-Za-z_][\w]*):", line)
        if not m:
            continue
        indent = len(m.group(1))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        stack.append((indent, m.group(2)))
        if re.search(r"#\s*pinned\b", line):
            out.add(tuple(k for _, k in stack))
    return out


def _reference(own: dict[str, Any]) -> dict[str, Any]:
    """What the recipe's keys are compared with: the resolved base recipe, or the defaults
    of the same plugins."""
    if own.get("base"):
        return resolved_config(from_dict(load_raw(str(own["base"]))))
    skeleton: dict[str, Any] = {}
    for section in ("frontend", "backend"):
        if section in own:
            skeleton[section] = {k: own[section][k] for k in SELECTORS if k in own[section]}
    if "factors" in own:
        skeleton["factors"] = {
            name: {k: v for k, v in (params or {}).items() if k == "plugin"}
            for name, params in own["factors"].items()
        }
    return resolved_config(from_dict(skeleton))


def _plain(v: Any) -> Any:
    return [_plain(x) for x in v] if isinstance(v, (list, tuple)) else v


def repeated_defaults(path: Path) -> list[str]:
    """Keys of the recipe at ``path`` equal to their default and not pinned."""
    own = _read_yaml(path)
    ref, pinned = _reference(own), _pinned(path)
    return [
        ".".join(p)
        for p, v in _leaves({k: v for k, v in own.items() if k != "base"})
        if p[-1] not in SELECTORS and p not in pinned and _plain(_get(ref, p)) == _plain(v)
    ]


@pytest.mark.parametrize("name", RECIPES)
def test_every_recipe_key_differs_from_its_default_or_is_pinned(name):
    same = repeated_defaults(Path(str(_locate(name))))
    assert not same, f"{name}.yaml repeats its defaults (delete them or mark '# pinned'): {same}"


def test_a_repeated_default_is_found(tmp_path):
    """The check can fail: a recipe repeating its base's value and a front-end default."""
    recipe = tmp_path / "mine.yaml"
    text = (
        "base: improved_floam_loop\nfrontend:\n  min_range: 0.5\n  max_range: 60.0\n"
        "factors:\n  loop_closure:\n    enabled: true\n    search:\n      min_keyframe_gap: 3\n"
    )
    recipe.write_text(text)
    assert repeated_defaults(recipe) == [
        "frontend.min_range", "factors.loop_closure.enabled",
        "factors.loop_closure.search.min_keyframe_gap",
    ]  # fmt: skip
    recipe.write_text(text.replace("0.5", "0.5  # pinned: the sensor's blind zone"))
    assert "frontend.min_range" not in repeated_defaults(recipe)


def _missing_fields(cls: type, d: dict[str, Any], where: str) -> list[str]:
    """Fields of dataclass ``cls`` (recursively) absent from ``d``, and keys of ``d`` that
    are no field."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    out = [f"{where}.{k} (not a field)" for k in d if k not in names and k not in SELECTORS]
    for f in names:
        if f not in d:
            out.append(f"{where}.{f}")
        elif dataclasses.is_dataclass(hints[f]):
            out += _missing_fields(hints[f], d[f], f"{where}.{f}")
    return out


def config_lists_every_field(resolved: dict[str, Any], config: Any) -> list[str]:
    """Every field of every section's Config in the resolved config (what config.yaml is)."""
    missing = _missing_fields(SourceConfig, resolved["source"], "source")
    missing += _missing_fields(OutputConfig, resolved["output"], "output")
    sections = [("slam.frontends", "frontend", config.frontend),
                ("slam.backends", "backend", config.backend)]  # fmt: skip
    sections += [("slam.factors", f"factors.{k}", v) for k, v in config.factors.items()]
    for group, where, params in sections:
        name = params.get("plugin", params.get("name", where.split(".")[-1]))
        cls = getattr(plugins.load(group, name), "Config", None)
        if cls is not None:
            missing += _missing_fields(cls, _get(resolved, tuple(where.split("."))), where)
    return missing


@pytest.mark.parametrize("name", RECIPES)
def test_resolved_config_lists_every_field(name):
    config = load_config(name)
    assert config_lists_every_field(resolved_config(config), config) == []


def test_a_missing_field_is_found():
    config = load_config("improved_floam_loop")
    resolved = resolved_config(config)
    del resolved["factors"]["loop_closure"]["verify"]["max_fitness"]
    del resolved["frontend"]["keyframe"]
    resolved["output"]["colour"] = "red"
    assert sorted(config_lists_every_field(resolved, config)) == [
        "factors.loop_closure.verify.max_fitness",
        "frontend.keyframe",
        "output.colour (not a field)",
    ]
