"""Scan registration: GICP (paper 000), FLOAM point-to-edge/plane ICP, information matrices."""

from slam.registration.feature_icp import FeatureIcpConfig, FeatureTarget, feature_icp_align
from slam.registration.gicp import (
    GicpConfig,
    GicpTarget,
    RegistrationError,
    RegistrationResult,
    estimate_covariances,
    gicp_align,
    se3_exp,
)
from slam.registration.information import (
    Information,
    InformationConfig,
    information_from_hessian,
)

__all__ = [
    "FeatureIcpConfig",
    "FeatureTarget",
    "GicpConfig",
    "GicpTarget",
    "Information",
    "InformationConfig",
    "RegistrationError",
    "RegistrationResult",
    "estimate_covariances",
    "feature_icp_align",
    "gicp_align",
    "information_from_hessian",
    "se3_exp",
]
