"""The front-end contract and the keyframe policy shared by front ends."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from slam.errors import ConfigError
from slam.types import Odometry, Scan


@runtime_checkable
class Frontend(Protocol):
    """Turns scans into odometry. Never imports gtsam.

    Optional: ``on_graph_update(view)`` (``slam.factors.GraphView``), called by the
    pipeline after each back-end update of a new keyframe; a front end that keeps its own
    maps moves them to the optimised poses there. Without it nothing is called.
    """

    def process(self, scan: Scan) -> Odometry: ...


@dataclass
class KeyframeConfig:
    """A new keyframe after this much motion since the last one (metres, degrees)."""

    translation: float = 1.0
    rotation_deg: float = 10.0

    def __post_init__(self) -> None:
        for name, unit in (("translation", "m"), ("rotation_deg", "deg")):
            value = getattr(self, name)
            if not value > 0:
                raise ConfigError(
                    f"frontend.keyframe.{name} must be > 0 {unit} (a keyframe after this "
                    f"much motion), got {value}"
                )


def is_new_keyframe(T_prevkf_current: np.ndarray, cfg: KeyframeConfig) -> bool:
    """True when the motion since the previous keyframe passes either threshold."""
    t = float(np.linalg.norm(T_prevkf_current[:3, 3]))
    cos = (np.trace(T_prevkf_current[:3, :3]) - 1.0) / 2.0
    angle = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return t >= cfg.translation or angle >= cfg.rotation_deg
