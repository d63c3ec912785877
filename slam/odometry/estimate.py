"""What a front end's registration step hands to the frame loop."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np

from slam.registration.gicp import RegistrationResult
from slam.registration.information import Information
from slam.types import RegistrationDiagnostics

MapUpdate = TypeVar("MapUpdate")


@dataclass
class Estimate(Generic[MapUpdate]):
    """The pose T_odom_sensor of one scan and how it was found.

    result: the registration (None: nothing to register against yet, the map is being
    started). pending: what ``_insert`` adds to the map if the pose is trusted (the front
    end's own type). skipped: why the scan could not be registered (too few features), or
    None. filtered: the filtered scan (sensor frame, m) the keyframe cloud is made of (None:
    the cropped, deskewed scan). ground_plane: (4,) [nx, ny, nz, d] in the sensor frame, or
    None. counts: the front end's scalar diagnostics. information: the registration's,
    computed by the frame loop. evidence: (pairs, RMSE m) of the points the front end
    judges a start by, when not the registration's own (``slam.odometry.search``).
    """

    pose: np.ndarray
    result: RegistrationResult | None = None
    pending: MapUpdate | None = None
    skipped: str | None = None
    filtered: np.ndarray | None = None
    ground_plane: np.ndarray | None = None
    counts: dict[str, float] = field(default_factory=dict)
    information: Information | None = None
    evidence: tuple[int, float] | None = None

    @property
    def H(self) -> np.ndarray | None:
        """The registration's Gauss-Newton Hessian (6x6, rotation first), or None."""
        return None if self.result is None else self.result.H

    @property
    def residual_variance(self) -> float:
        """Cost per degree of freedom of the registration (1 without one)."""
        res = self.result
        return 1.0 if res is None else res.cost / max(res.dof, 1)

    @property
    def registration(self) -> RegistrationDiagnostics | None:
        """The registration's diagnostics, or None."""
        res = self.result
        if res is None:
            return None
        return RegistrationDiagnostics(
            res.iterations, res.fitness, res.converged, res.num_inliers, res.inlier_ratio
        )
