"""From a registration Hessian to a plausible information matrix, and a degeneracy test.

The one Hessian-to-information conversion of the project: the front ends use it with the
residual variance (absolute scale), loop verification with ``relative=True`` (the best
direction is put at its floor sigma, the Hessian's shape kept).

A scan-to-map Gauss-Newton Hessian H = sum J^T W J counts thousands of correlated residuals
as independent, so H / s^2 (s^2 = residual variance) claims sub-millimetre sigmas. Factor
graphs need a covariance that reflects the real drift of odometry: we scale by the residual
variance, then clamp the eigenvalues of the information (in units of the best-case sigmas)
so no direction is more certain than ``min_sigma_translation`` / ``min_sigma_rotation_deg``.

The degeneracy flag follows LOAM (Zhang and Singh, "On degeneration of optimization-based
state estimation problems"): a direction is degenerate when the smallest eigenvalue of the
(normalised) information falls below a threshold, i.e. its sigma is much larger than the
best case. Ordering is GTSAM's: rotation (rx, ry, rz) first, then translation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.errors import ConfigError


@dataclass
class InformationConfig:
    """Sigma floors (best case) and ceilings (worst case) of a registration's covariance.

    degenerate_factor: a direction whose sigma exceeds this many times its floor is
    degenerate (LOAM-style eigenvalue test on the normalised information).
    """

    min_sigma_translation: float = 0.01
    min_sigma_rotation_deg: float = 0.05
    max_sigma_translation: float = 10.0
    max_sigma_rotation_deg: float = 30.0
    degenerate_factor: float = 5.0

    def __post_init__(self) -> None:
        for kind, unit in (("translation", "m"), ("rotation_deg", "deg")):
            lo, hi = getattr(self, f"min_sigma_{kind}"), getattr(self, f"max_sigma_{kind}")
            if not 0 < lo <= hi:
                raise ConfigError(
                    f"frontend.information: need 0 < min_sigma_{kind} <= max_sigma_{kind} "
                    f"({unit}: the floor and ceiling of a registration's sigma), got {lo} and {hi}"
                )
        if not self.degenerate_factor >= 1:
            raise ConfigError(
                f"frontend.information.degenerate_factor must be >= 1 (a sigma this many times its "
                f"floor is degenerate), got {self.degenerate_factor}"
            )


@dataclass
class Information:
    """info: 6x6 (rotation first). degenerate: flag. min_eigenvalue: smallest eigenvalue of the
    normalised information before clamping (1 = best case; < 1/degenerate_factor^2 flags).
    weak_direction: its eigenvector (6,)."""

    info: np.ndarray
    degenerate: bool
    min_eigenvalue: float
    weak_direction: np.ndarray


def _floors(cfg: InformationConfig) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([np.radians(cfg.min_sigma_rotation_deg)] * 3 + [cfg.min_sigma_translation] * 3)
    hi = np.array([np.radians(cfg.max_sigma_rotation_deg)] * 3 + [cfg.max_sigma_translation] * 3)
    return lo, hi


def information_from_hessian(
    H: np.ndarray,
    residual_variance: float = 1.0,
    cfg: InformationConfig | None = None,
    *,
    relative: bool = False,
) -> Information:
    """Information = H / residual_variance with its eigenvalues clamped to plausible sigmas.

    H: 6x6 Hessian of a least-squares cost (rotation first, as the solvers here produce).
    residual_variance: s^2 of the residuals (cost / dof); the information of a least-squares
    estimate is H / s^2. The normalised information N = D I D (D = diag(best-case sigmas)) has
    eigenvalue 1 where a direction is known to its floor; eigenvalues are clipped to
    [(floor/ceiling)^2, 1] and mapped back, so the result is symmetric positive definite.
    relative: first divide N by its largest eigenvalue, so that the best-determined
    direction has exactly its floor sigma whatever the Hessian's scale (raw GICP Hessians of
    thousands of millimetre-thin covariances are 1e6-1e9); ``min_eigenvalue`` and the
    degeneracy flag are then relative to the best direction as well.
    A non-finite or mis-shaped H gives the weakest information (every sigma at its ceiling).
    """
    cfg = cfg or InformationConfig()
    H = np.asarray(H, dtype=np.float64)
    if H.shape != (6, 6) or not np.all(np.isfinite(H)):
        H = np.zeros((6, 6))
    info = 0.5 * (H + H.T) / max(float(residual_variance), 1e-12)
    lo, hi = _floors(cfg)
    N = lo[:, None] * info * lo[None, :]
    w, V = np.linalg.eigh(N)
    if relative:
        top = float(w[-1])
        w = w / top if top > 0 else np.zeros(6)
    min_eig = float(w[0])
    lower = float(np.max((lo / hi) ** 2))
    w_c = np.clip(w, lower, 1.0)
    N_c = (V * w_c) @ V.T
    out = N_c / lo[:, None] / lo[None, :]
    return Information(
        info=0.5 * (out + out.T),
        degenerate=bool(min_eig < 1.0 / cfg.degenerate_factor**2),
        min_eigenvalue=min_eig,
        weak_direction=V[:, 0].copy(),
    )


def default_information(cfg: InformationConfig | None = None, factor: float = 10.0) -> np.ndarray:
    """A weak diagonal information (sigmas = ``factor`` x the floors) for skipped frames."""
    lo, _ = _floors(cfg or InformationConfig())
    return np.diag(1.0 / (factor * lo) ** 2)
