"""Loop closure: Scan Context and Scan Context++ descriptors, KD-tree candidate search,
GICP verification, the factor plugin and its nested config."""

from slam.loop.config import LoopConfig
from slam.loop.scan_context import (
    ScanContextParams,
    column_shift_distance,
    ring_key,
    scan_context,
    sector_key,
    sector_key_shift,
    shift_to_yaw,
    yaw_to_shift,
)
from slam.loop.scan_context_pp import (
    CartesianIndex,
    ScanContextPPParams,
    cartesian_context,
    polar_context,
)
from slam.loop.search import Candidate, ScanContextDatabase, SearchParams
from slam.loop.verify import VerifyParams, VerifyResult, scaled_information, verify

__all__ = [
    "Candidate",
    "CartesianIndex",
    "LoopConfig",
    "ScanContextPPParams",
    "cartesian_context",
    "polar_context",
    "ScanContextDatabase",
    "ScanContextParams",
    "SearchParams",
    "VerifyParams",
    "VerifyResult",
    "column_shift_distance",
    "ring_key",
    "scaled_information",
    "scan_context",
    "sector_key",
    "sector_key_shift",
    "shift_to_yaw",
    "verify",
    "yaw_to_shift",
]
