"""Typed configuration loaded from YAML recipes in ``configs/``.

A recipe is a mapping with the sections ``source``, ``frontend``, ``backend``,
``factors`` and ``output``. ``frontend`` and ``backend`` name a plugin
(``name: improved_floam``) and carry that plugin's own keys, validated against the
plugin's ``Config`` dataclass. ``factors`` maps a factor plugin name (or an import
path ``package.module:Class``) to its keys. A recipe may start from another with
``base: NAME``. Unknown keys anywhere are errors that list the valid ones. Defaults live
in the dataclasses only: a recipe holds what differs from them.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from importlib import resources
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

import yaml

from slam import plugins
from slam.dataclass_build import (  # noqa: F401  (re-exported: recipes' API)
    ConfigDeprecationWarning,
    build_dataclass,
    upgrade_keys,
)
from slam.errors import ConfigError

CONFIG_PACKAGE = "slam.configs"  # the top-level configs/ folder, shipped as package data
DEFAULT_CONFIG = "improved_floam"


LAYOUT_TIME = ("auto", "always", "never")
FRAME_PERIOD_S = 0.1  # a spinning LiDAR's 10 Hz


@dataclass
class SourceConfig:
    """Which messages to read and how to treat damaged ones.

    topic: None = the only point-cloud topic. start: index of the first message used (the
    ones before are read and ignored). max_frames: stop after this many frames. strict: stop
    at the first damaged message or bad stamp (default: skip that frame, count it, go on).
    beam_scans: the first scans the beam table (elevation per ring) is estimated from, so
    that clouds without a ring field get one (slam.sensor); 0 = never.
    layout_time: per-point time for clouds stored beam by beam (KITTI's, an Ouster driver's
    layout) without a time field, from each point's azimuth, so that the front end can
    deskew them. "auto" (default): made up as ``Scan.layout_time``, and the front end
    deskews with it only once registrations at speed show the clouds are not
    motion-compensated (KITTI publishes its scans compensated, also in the bags converted
    from them, and deskewing them again makes them worse; an Ouster driver does not);
    "always": used as the time field; "never": not made up.
    stamps: the clock that stamps a scan (slam.io.stamps). "header": the driver's header
    stamp; "record": the bag's record time (bags only); "auto": the header stamp unless it
    does not increase over the first 10 messages (running backwards, all equal), then the
    record time with one warning; neither increasing stops the run (exit 2) saying so.
    reorder_window: scans held and released in stamp order in front of the pipeline, so
    that messages recorded a few places out of order are kept (0 = off); a stamp still
    out of order after it is skipped and counted.
    frame_period: seconds between scans of a folder (.pcd/.ply, KITTI .bin) whose file
    names are frame numbers (``0.pcd``, ``000001.bin``) or not numbers, and that has no
    ``times.txt``: scan i is stamped i * frame_period (0.1 s = 10 Hz; nuScenes keyframes
    are 0.5 s apart). File names that are stamps, and a KITTI ``times.txt``, are used as
    they are. The front ends' motion prediction and plausibility checks use these stamps.
    """

    topic: str | None = None
    start: int = 0
    max_frames: int | None = None
    strict: bool = False
    beam_scans: int = 3
    layout_time: str = "auto"
    stamps: str = "auto"
    reorder_window: int = 4
    frame_period: float = FRAME_PERIOD_S

    def __post_init__(self) -> None:
        if not (math.isfinite(self.frame_period) and self.frame_period > 0):
            raise ConfigError(
                f"source.frame_period must be > 0 s (0.1 = 10 Hz), got {self.frame_period}"
            )
        if self.stamps not in ("auto", "header", "record"):
            raise ConfigError(
                f"source.stamps must be one of auto, header, record, got {self.stamps!r}"
            )
        if self.reorder_window < 0:
            raise ConfigError(f"source.reorder_window must be >= 0, got {self.reorder_window}")
        if self.layout_time not in LAYOUT_TIME:
            raise ConfigError(
                f"source.layout_time must be one of {', '.join(LAYOUT_TIME)}, "
                f"got {self.layout_time!r}"
            )
        if self.start < 0:
            raise ConfigError(f"source.start must be >= 0, got {self.start}")
        if self.beam_scans < 0:
            raise ConfigError(f"source.beam_scans must be >= 0, got {self.beam_scans}")
        if self.max_frames is not None and self.max_frames < 1:
            raise ConfigError(f"source.max_frames must be >= 1, got {self.max_frames}")


@dataclass
class OutputConfig:
    """What a run writes besides the trajectories. map_voxel in metres."""

    write_map: bool = True
    map_voxel: float = 0.1
    map_format: str = "pcd"


@dataclass
class SlamConfig:
    """A whole run. Plugin sections stay dicts until the plugin's own Config validates them."""

    frontend: dict[str, Any] = field(default_factory=lambda: {"name": "improved_floam"})
    backend: dict[str, Any] = field(default_factory=lambda: {"name": "isam2"})
    factors: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {"prior": {}, "odometry": {}}
    )
    source: SourceConfig = field(default_factory=SourceConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    name: str = "custom"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------- loading


def _builtin_dir() -> Traversable:
    """The installed recipes (works from a wheel, an editable install or a checkout)."""
    return resources.files(CONFIG_PACKAGE)


def available_configs() -> list[str]:
    """Names of the built-in recipes."""
    names = (p.name for p in _builtin_dir().iterdir())
    return sorted(n[: -len(".yaml")] for n in names if n.endswith(".yaml"))


def _read_yaml(path: Path | Traversable) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the config: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config must be a mapping of sections")
    return data


def _locate(name_or_path: str) -> Path | Traversable:
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        return path
    candidate = _builtin_dir() / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    raise ConfigError(
        f"unknown config '{name_or_path}'; built-in configs: {', '.join(available_configs())}"
        " (or give a path to a .yaml file)"
    )


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge; ``over`` wins. A plugin section changing ``name`` replaces it whole."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if (
            isinstance(value, dict)
            and isinstance(out.get(key), dict)
            and not ("name" in value and value.get("name") != out[key].get("name"))
        ):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_raw(name_or_path: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """The merged mapping of a recipe and its ``base:`` chain."""
    path = _locate(name_or_path)
    if str(path) in _seen:
        raise ConfigError(f"config 'base' chain loops through {path}")
    data = _read_yaml(path)
    base = data.pop("base", None)
    data.setdefault("name", path.name.rsplit(".", 1)[0])
    if base:
        merged = deep_merge(load_raw(str(base), _seen + (str(path),)), data)
        merged["name"] = data["name"]
        return merged
    return data


def parse_override(text: str) -> tuple[list[str], Any]:
    """``section.key=value`` -> (["section", "key"], parsed YAML value)."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' must look like section.key=value")
    key, _, value = text.partition("=")
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"override '{text}' has an empty key")
    try:
        parsed = yaml.safe_load(value) if value.strip() else None
    except yaml.YAMLError as exc:
        raise ConfigError(f"override '{text}': value is not valid YAML ({exc})") from exc
    return parts, parsed


def apply_overrides(raw: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    out = copy.deepcopy(raw)
    for text in overrides:
        parts, value = parse_override(text)
        node = out
        for part in parts[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise ConfigError(f"override '{text}': '{part}' is not a section")
            node = child
        node[parts[-1]] = value
    return out


def from_dict(raw: dict[str, Any]) -> SlamConfig:
    """Validate a raw mapping into a SlamConfig (plugin keys are validated by the plugins)."""
    raw = dict(raw)
    for section in ("frontend", "backend"):
        value = raw.get(section)
        if value is not None and (not isinstance(value, dict) or "name" not in value):
            raise ConfigError(f"'{section}' must be a mapping with a 'name' key")
    factors = raw.get("factors")
    if factors is not None:
        if not isinstance(factors, dict):
            raise ConfigError("'factors' must map factor plugin names to their settings")
        raw["factors"] = {
            k: _upgrade_plugin_section("slam.factors", k, dict(v or {}), f"factors.{k}")
            for k, v in factors.items()
        }
    for section, group in (("frontend", "slam.frontends"), ("backend", "slam.backends")):
        if raw.get(section) is not None:
            value = raw[section]
            raw[section] = _upgrade_plugin_section(group, value["name"], value, section)
    return build_dataclass(SlamConfig, raw, "config")


def _upgrade_plugin_section(
    group: str, name: str, params: dict[str, Any], where: str
) -> dict[str, Any]:
    """A plugin section with its moved keys upgraded once, at load time (so that the one
    warning is not repeated each time the section is validated). A plugin that cannot be
    loaded is left to report itself where it is built."""

    try:
        cls = plugins.load(group, params.get("plugin", name))
    except ConfigError:
        return params
    config_cls = getattr(cls, "Config", None)
    if config_cls is None or not dataclasses.is_dataclass(config_cls):
        return params
    rest = {k: v for k, v in params.items() if k not in ("name", "plugin")}
    upgraded = upgrade_keys(config_cls, rest, where)
    if upgraded is rest:
        return params
    head = {k: params[k] for k in ("name", "plugin") if k in params}
    return {**head, **upgraded}


def load_config(name_or_path: str | None = None, overrides: list[str] | None = None) -> SlamConfig:
    """Load a recipe by name (``configs/NAME.yaml``) or path, apply ``--set`` overrides."""
    raw = load_raw(name_or_path or DEFAULT_CONFIG)
    if not overrides:
        return from_dict(raw)
    recipe = from_dict(copy.deepcopy(raw))
    config = from_dict(apply_overrides(raw, overrides))
    if not any(o.split("=", 1)[0].strip() == "name" for o in overrides):
        # another front / back end than the recipe's: the outputs must not carry the
        # recipe's name alone ("improved_floam" that ran floam)
        swapped = [
            str(getattr(config, part).get("name"))
            for part in ("frontend", "backend")
            if getattr(config, part).get("name") != getattr(recipe, part).get("name")
        ]
        if swapped:
            config.name = "+".join([config.name, *swapped])
    return config


def save_config(config: SlamConfig, path: Path, resolved: dict[str, Any] | None = None) -> None:
    """Write the config (or the fully resolved dict, with plugin defaults filled in) as YAML."""
    data = resolved if resolved is not None else config.to_dict()
    path.write_text(yaml.safe_dump(data, sort_keys=False))
