from dataclasses import dataclass

import gtsam
import numpy as np

from slam.factors import FactorConfig


class PlanarMotion:
    """Ground robot: keep every keyframe near z = 0 with level roll and pitch."""

    @dataclass
    class Config(FactorConfig):
        sigma_z: float = 0.05  # metres
        sigma_tilt_deg: float = 1.0

    def __init__(self, config: Config):
        self.config = config

    def on_keyframe(self, kf, graph):
        T = graph.estimate(kf.id)  # current guess of this keyframe's pose (4x4, world)
        yaw = np.arctan2(T[1, 0], T[0, 0])
        level = gtsam.Pose3(gtsam.Rot3.Yaw(yaw), gtsam.Point3(T[0, 3], T[1, 3], 0.0))
        tilt = np.radians(self.config.sigma_tilt_deg)
        free = 1e3  # x, y and yaw are left to the other factors
        sigmas = np.array([tilt, tilt, free, free, free, self.config.sigma_z])
        noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
        return [gtsam.PriorFactorPose3(graph.key(kf.id), level, noise)]
