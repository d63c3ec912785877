"""Yaw helpers of 4x4 poses (radians), shared by the descriptors, verification and the gates."""

from __future__ import annotations

import numpy as np


def yaw_of(T: np.ndarray) -> float:
    """Yaw (radians) of a 4x4 pose: rotation about z of its x axis."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def wrap_angle(a: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return float(np.pi - np.mod(np.pi - a, 2.0 * np.pi))


def yaw_matrix(yaw: float, translation: np.ndarray | None = None) -> np.ndarray:
    """4x4 rotation by ``yaw`` radians about z (plus an optional translation)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    if translation is not None:
        T[:3, 3] = translation
    return T
