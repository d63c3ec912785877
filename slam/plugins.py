"""Finding plugins by name (entry points) or import path (``package.module:Class``)."""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from slam.dataclass_build import build_dataclass
from slam.errors import PluginError

GROUPS = ("slam.frontends", "slam.backends", "slam.factors")


def available(group: str) -> list[str]:
    """Names registered under an entry-point group."""
    return sorted({ep.name for ep in entry_points(group=group)})


def _import_path(spec: str) -> Any:
    module_name, _, attr = spec.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise PluginError(f"cannot import plugin module '{module_name}': {exc}") from exc
    try:
        obj = module
        for part in attr.split("."):
            obj = getattr(obj, part)
    except AttributeError as exc:
        raise PluginError(f"module '{module_name}' has no attribute '{attr}'") from exc
    return obj


def load(group: str, name: str) -> Any:
    """The plugin class for ``name`` in ``group``; ``name`` may be ``package.module:Class``."""
    if ":" in name:
        return _import_path(name)
    matches = [ep for ep in entry_points(group=group) if ep.name == name]
    if not matches:
        raise PluginError(
            f"unknown {group.split('.')[-1][:-1]} plugin '{name}'; available: "
            f"{', '.join(available(group)) or '(none installed)'}"
            " (or give an import path package.module:Class)"
        )
    try:
        return matches[0].load()
    except Exception as exc:  # noqa: BLE001 - any import failure of a plugin is a config problem
        raise PluginError(f"plugin '{name}' failed to load: {exc}") from exc


def plugin_config(cls: Any, params: dict[str, Any], where: str) -> Any:
    """Validate ``params`` against ``cls.Config`` (a dataclass); plugins without one take none."""
    params = {k: v for k, v in params.items() if k != "name"}
    config_cls = getattr(cls, "Config", None)
    if config_cls is None:
        if params:
            raise PluginError(f"'{where}' takes no settings, got: {', '.join(params)}")
        return None
    return build_dataclass(config_cls, params, where)


def instantiate(group: str, params: dict[str, Any], where: str, name: str | None = None) -> Any:
    """Load plugin ``name`` (default ``params['name']``) and build it from its validated Config."""
    name = name or params.get("name")
    if not name:
        raise PluginError(f"'{where}' needs a 'name'")
    cls = load(group, name)
    cfg = plugin_config(cls, params, where)
    return cls(cfg) if cfg is not None else cls()
