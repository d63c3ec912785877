"""Feature extraction: LOAM edges/planes and the covariance curvature correction."""

from slam.features.curvature import covariance_curvature
from slam.features.loam import FeatureConfig, Features, extract_features, ring_from_elevation

__all__ = [
    "FeatureConfig",
    "Features",
    "covariance_curvature",
    "extract_features",
    "ring_from_elevation",
]
