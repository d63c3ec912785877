"""The extension interface: factor plugins turn keyframes into GTSAM factors.

A factor plugin is any class with ``on_keyframe(kf, graph) -> list[gtsam.NonlinearFactor]``
and, optionally, a ``Config`` dataclass (validated from the YAML ``factors.<name>``
section; it should extend :class:`FactorConfig` so that ``enabled`` and the robust
kernel settings exist everywhere). Plugins are found by name through the
``slam.factors`` entry-point group or by import path ``package.module:Class``.

Keys: keyframe ``i`` is the GTSAM key ``graph.key(i)`` (symbol ``x<i>``).
Plugins never mutate the graph view; they only return factors.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import gtsam
import numpy as np

from slam.errors import ConfigError
from slam.rigid import kept_rigid
from slam.types import Keyframe

ROBUST_KERNELS = ("none", "huber", "cauchy", "tukey", "gemanmcclure")


def key(kf_id: int) -> int:
    """GTSAM key of keyframe ``kf_id``."""
    return gtsam.symbol("x", kf_id)


@dataclass
class FactorConfig:
    """Settings every factor plugin has: a switch and a robust kernel (param in sigmas)."""

    enabled: bool = True
    robust: str = "none"
    robust_param: float = 1.345

    def __post_init__(self) -> None:
        if self.robust not in ROBUST_KERNELS:
            raise ConfigError(
                f"robust must be one of {', '.join(ROBUST_KERNELS)}, got '{self.robust}'"
            )


class GraphView:
    """Read-only access for plugins: keyframes so far, their clouds and the current pose
    estimates. Plugins keep keyframe ids, not copies of clouds: ``cloud(kf_id)`` is the one
    stored copy (O(1))."""

    def __init__(self, keyframes: Sequence[Keyframe], estimate: Callable[[int], np.ndarray]):
        self._keyframes = keyframes
        self._estimate = estimate

    @property
    def keyframes(self) -> Sequence[Keyframe]:
        return self._keyframes

    def key(self, kf_id: int) -> int:
        return key(kf_id)

    def estimate(self, kf_id: int) -> np.ndarray:
        """Current best T_world_sensor (4x4) of keyframe ``kf_id``."""
        return self._estimate(kf_id)

    def cloud(self, kf_id: int) -> np.ndarray:
        """Keyframe ``kf_id``'s stored cloud: (N, 3) float32 m in its sensor frame,
        voxel-thinned by the front end, read-only (shared, not copied)."""
        return self._keyframes[kf_id].cloud


@runtime_checkable
class FactorPlugin(Protocol):
    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[Any]: ...


def robust_noise(base: gtsam.noiseModel.Base, kernel: str, param: float) -> gtsam.noiseModel.Base:
    """Wrap ``base`` in a robust M-estimator (``kernel`` in ROBUST_KERNELS)."""
    if kernel == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    makers = {
        "huber": est.Huber.Create,
        "cauchy": est.Cauchy.Create,
        "tukey": est.Tukey.Create,
        "gemanmcclure": est.GemanMcClure.Create,
    }
    if kernel not in makers:
        raise ConfigError(f"unknown robust kernel '{kernel}'; valid: {', '.join(ROBUST_KERNELS)}")
    return gtsam.noiseModel.Robust.Create(makers[kernel](param), base)


def information_noise(info: np.ndarray) -> gtsam.noiseModel.Base:
    """Gaussian noise model from a 6x6 information matrix (rotation first), symmetrised."""
    info = 0.5 * (np.asarray(info, dtype=float) + np.asarray(info, dtype=float).T)
    return gtsam.noiseModel.Gaussian.Information(info)


def pose3(T: np.ndarray) -> gtsam.Pose3:
    """gtsam.Pose3 from a 4x4 matrix, its rotation re-orthonormalised when it is off SO(3)
    by more than rounding (gtsam.Pose3 takes the matrix as it is: a scaled "rotation"
    made iSAM2 fail with an indeterminate system)."""
    return gtsam.Pose3(kept_rigid(np.asarray(T, dtype=float)))
