"""The factor plugins of a run, each under the name it was configured with."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import gtsam

from slam import plugins
from slam.factors import key


@dataclass
class FactorSource:
    """One enabled factor plugin with the name it was configured under."""

    name: str
    plugin: Any

    @property
    def is_loop(self) -> bool:
        return bool(getattr(self.plugin, "is_loop", False))


def build_factor_plugins(factors: dict[str, dict[str, Any]]) -> list[FactorSource]:
    """Instantiate the enabled factor plugins, in config order.

    A section's name is the plugin name, or give ``plugin: package.module:Class`` to
    load a user's class under any section name.
    """
    out = []
    for name, params in factors.items():
        params = dict(params)
        spec = params.pop("plugin", name)
        cls = plugins.load("slam.factors", spec)
        cfg = plugins.plugin_config(cls, params, f"factors.{name}")
        if cfg is not None and not getattr(cfg, "enabled", True):
            continue
        out.append(FactorSource(name, cls(cfg) if cfg is not None else cls()))
    return out


def loop_pairs(factors: Iterable[Any]) -> list[tuple[int, int]]:
    """(keyframe a, keyframe b) of every factor between two keyframes."""
    pairs = []
    for factor in factors:
        ids = [gtsam.Symbol(k) for k in factor.keys()]
        ids = [int(s.index()) for s in ids if s.key() == key(s.index())]
        if len(ids) == 2:
            pairs.append((ids[0], ids[1]))
    return pairs
