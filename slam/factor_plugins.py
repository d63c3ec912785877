"""Built-in factor plugins: prior, odometry and position (GPS-like) fixes.

Each shows one way a measurement enters the graph: the prior fixes the gauge, the
odometry plugin turns the front end's relative motion and information into a
BetweenFactorPose3, the position plugin adds external absolute fixes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from slam.errors import ConfigError, InputError
from slam.factors import (
    FactorConfig,
    GraphView,
    information_noise,
    key,
    pose3,
    robust_noise,
)
from slam.types import Keyframe


def sigma_noise(rotation_sigma: float, translation_sigma: float) -> gtsam.noiseModel.Base:
    """Diagonal Pose3 noise, rotation first (rad), then translation (m)."""
    return gtsam.noiseModel.Diagonal.Sigmas(
        np.array([rotation_sigma] * 3 + [translation_sigma] * 3, dtype=float)
    )


def _check_positive(**values: float) -> None:
    for name, value in values.items():
        if not value > 0:
            raise ConfigError(f"{name} must be > 0, got {value}")


# --------------------------------------------------------------------------- prior


@dataclass
class PriorConfig(FactorConfig):
    """Prior on keyframe 0 at its odometry pose; sigmas in rad and m.

    Tiny by default so that the odometry-only optimum reproduces the front end exactly.
    """

    rotation_sigma: float = 1e-6
    translation_sigma: float = 1e-6

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_positive(
            rotation_sigma=self.rotation_sigma, translation_sigma=self.translation_sigma
        )


class PriorFactorPlugin:
    """PriorFactorPose3 on keyframe 0 (fixes the gauge freedom of the pose graph)."""

    Config = PriorConfig

    def __init__(self, config: PriorConfig | None = None):
        self.config = config or PriorConfig()
        base = sigma_noise(self.config.rotation_sigma, self.config.translation_sigma)
        self._noise = robust_noise(base, self.config.robust, self.config.robust_param)

    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.NonlinearFactor]:
        if not self.config.enabled or kf.id != 0:
            return []
        return [gtsam.PriorFactorPose3(key(kf.id), pose3(kf.pose_odom), self._noise)]


# --------------------------------------------------------------------------- odometry


@dataclass
class OdometryConfig(FactorConfig):
    """Between factors from the front end's relative motion.

    use_frontend_information: noise from the keyframe's 6x6 information; otherwise (and
    for an information matrix that is not finite and positive definite) fixed sigmas
    rotation_sigma (rad) and translation_sigma (m).
    """

    use_frontend_information: bool = True
    rotation_sigma: float = 0.01
    translation_sigma: float = 0.05

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_positive(
            rotation_sigma=self.rotation_sigma, translation_sigma=self.translation_sigma
        )


def _positive_definite(info: np.ndarray) -> bool:
    info = np.asarray(info, dtype=float)
    if info.shape != (6, 6) or not np.all(np.isfinite(info)):
        return False
    return bool(np.linalg.eigvalsh(0.5 * (info + info.T)).min() > 0)


class OdometryFactorPlugin:
    """BetweenFactorPose3(prev keyframe, keyframe, relative); nothing for keyframe 0."""

    Config = OdometryConfig

    def __init__(self, config: OdometryConfig | None = None):
        self.config = config or OdometryConfig()
        self._fixed = sigma_noise(self.config.rotation_sigma, self.config.translation_sigma)
        self.fallbacks = 0  # keyframes whose information was unusable (fixed sigmas used)

    def noise(self, kf: Keyframe) -> gtsam.noiseModel.Base:
        """The (robust-wrapped) noise model of ``kf.relative``."""
        base = self._fixed
        if self.config.use_frontend_information:
            if _positive_definite(kf.info):
                base = information_noise(kf.info)
            else:
                self.fallbacks += 1
        return robust_noise(base, self.config.robust, self.config.robust_param)

    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.NonlinearFactor]:
        if not self.config.enabled or kf.id == 0:
            return []
        return [
            gtsam.BetweenFactorPose3(key(kf.id - 1), key(kf.id), pose3(kf.relative), self.noise(kf))
        ]


# --------------------------------------------------------------------------- position


@dataclass
class PositionConfig(FactorConfig):
    """Absolute position fixes of the sensor in the graph's world frame.

    file: TUM (``stamp x y z qx qy qz qw``, orientation ignored) or CSV ``stamp,x,y,z``
    (an optional header line is skipped). sigma: isotropic std-dev in m. max_dt: a keyframe
    gets the fix nearest in time if it is within max_dt seconds.
    """

    file: str = ""
    sigma: float = 1.0
    max_dt: float = 0.05

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_positive(sigma=self.sigma)
        if self.max_dt < 0:
            raise ConfigError(f"max_dt must be >= 0, got {self.max_dt}")


def load_position_fixes(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Sorted stamps (N,) and positions (N, 3) from a TUM or ``stamp,x,y,z`` CSV file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"position fix file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read position fix file {path}: {exc}") from exc
    lines = [ln.strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    rows = []
    for number, line in enumerate(lines):
        try:
            rows.append([float(v) for v in line.replace(",", " ").split()])
        except ValueError as exc:
            if number == 0:
                continue  # a header such as "stamp,x,y,z"
            raise InputError(f"{path}: not TUM or 'stamp,x,y,z' CSV ({line!r}): {exc}") from exc
    if len({len(r) for r in rows}) > 1:
        raise InputError(f"{path}: lines have different numbers of columns")
    rows = np.array(rows, dtype=float)
    if rows.size == 0:
        raise InputError(f"{path}: no position fixes")
    if rows.ndim != 2 or rows.shape[1] not in (4, 8):
        raise InputError(f"{path}: expected 4 columns (stamp,x,y,z) or 8 (TUM) on every line")
    if not np.all(np.isfinite(rows)):
        raise InputError(f"{path}: non-finite numbers in position fixes")
    order = np.argsort(rows[:, 0], kind="stable")
    return rows[order, 0], rows[order, 1:4]


class PositionFactorPlugin:
    """GPSFactor (position of the Pose3) for each keyframe with a fix within ``max_dt``."""

    Config = PositionConfig

    def __init__(self, config: PositionConfig | None = None):
        self.config = config or PositionConfig()
        self.stamps = np.zeros(0)
        self.positions = np.zeros((0, 3))
        self.used = 0  # fixes added to the graph so far
        if not self.config.enabled:
            return
        if not self.config.file:
            raise ConfigError("factors.position.file is required (TUM or 'stamp,x,y,z' CSV)")
        self.stamps, self.positions = load_position_fixes(self.config.file)
        base = gtsam.noiseModel.Isotropic.Sigma(3, self.config.sigma)
        self._noise = robust_noise(base, self.config.robust, self.config.robust_param)

    def nearest(self, stamp: float) -> int | None:
        """Index of the fix nearest to ``stamp`` if within max_dt, else None."""
        n = len(self.stamps)
        if n == 0:
            return None
        i = int(np.searchsorted(self.stamps, stamp))
        candidates = [j for j in (i - 1, i) if 0 <= j < n]
        best = min(candidates, key=lambda j: abs(self.stamps[j] - stamp))
        return best if abs(self.stamps[best] - stamp) <= self.config.max_dt else None

    def on_keyframe(self, kf: Keyframe, graph: GraphView) -> list[gtsam.NonlinearFactor]:
        if not self.config.enabled:
            return []
        j = self.nearest(kf.stamp)
        if j is None:
            return []
        self.used += 1
        return [gtsam.GPSFactor(key(kf.id), gtsam.Point3(*self.positions[j]), self._noise)]
