"""Loop closure: Scan Context descriptor, ring-key candidate search, GICP verification, plugin."""

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
from slam.loop.search import Candidate, ScanContextDatabase, SearchParams
from slam.loop.verify import VerifyParams, VerifyResult, scaled_information, verify

__all__ = [
    "Candidate",
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
