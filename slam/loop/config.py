"""The loop closure's settings, nested by stage: descriptor, search, verify, consistency,
workers (``factors.loop_closure`` in a recipe).

The flat keys of version 0.1 (``sc_threshold``, ``verify_workers``, ...) are still read, with
one warning naming each key's new place (:data:`FLAT_KEYS`); they go in the next version.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from slam.factors import FactorConfig
from slam.loop.consistency import ConsistencyParams, OdometryGateParams
from slam.loop.scan_context_pp import ScanContextPPParams
from slam.loop.search import SearchParams
from slam.loop.verify import VerifyParams

DESCRIPTORS = ("scan_context", "scan_context_pp")
PROPOSERS = ("descriptor", "radius")
_PP = ScanContextPPParams()  # the SC++ grid's defaults


@dataclass(frozen=True)
class DescriptorConfig:
    """kind: scan_context (Kim & Kim 2018, all points) or scan_context_pp (SC++, Kim et al.
    2022: polar context of the non-ground points plus the augmented Cartesian context).
    max_radius (m, 0 = auto) and lidar_height (m, < 0 = auto) come from the first
    auto_keyframes keyframes when on auto (:func:`slam.loop.describe.auto_descriptor_params`).
    The SC++ fields are those of :class:`slam.loop.scan_context_pp.ScanContextPPParams`."""

    kind: str = "scan_context"
    rings: int = 20
    sectors: int = 60
    max_radius: float = 0.0
    lidar_height: float = -1.0
    auto_keyframes: int = 10
    ground_clearance: float = _PP.ground_clearance
    cc_rows: int = _PP.cc_rows
    cc_cols: int = _PP.cc_cols
    cc_lateral: float = _PP.cc_lateral
    cc_longitudinal: float = _PP.cc_longitudinal
    lateral_shifts: int = _PP.lateral_shifts
    longitudinal_shifts: int = _PP.longitudinal_shifts

    def __post_init__(self) -> None:
        if self.kind not in DESCRIPTORS:
            raise ValueError(f"unknown descriptor '{self.kind}'; valid: {', '.join(DESCRIPTORS)}")
        for name in ("rings", "sectors", "auto_keyframes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_radius < 0:
            raise ValueError(f"max_radius must be > 0 m (or 0 = auto), got {self.max_radius}")


@dataclass(frozen=True)
class SearchConfig(SearchParams):
    """The KD-tree search of :class:`slam.loop.search.SearchParams` plus who proposes.

    threshold / cc_threshold: Scan Context / SC++ Cartesian distance a candidate must stay
    below. proposer: descriptor (the KD-tree search) or radius (LeGO-LOAM: the nearest
    keyframe within ``radius`` m of the estimate and at least radius_min_seconds older).
    proximity_radius (m, 0 = off): keyframes that near the estimate are candidates too.
    max_verify: candidates verified per keyframe. min_keyframe_gap: keyframes after an
    accepted loop during which nothing is verified (one revisit needs few loops)."""

    cc_threshold: float = 0.25
    proposer: str = "descriptor"
    radius: float = 7.0
    radius_min_seconds: float = 30.0
    proximity_radius: float = 0.0
    max_verify: int = 1
    min_keyframe_gap: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.threshold > 0:
            raise ValueError(f"threshold must be > 0, got {self.threshold}")
        if self.max_verify < 1:
            raise ValueError(f"max_verify must be >= 1, got {self.max_verify}")
        if self.proposer not in PROPOSERS:
            raise ValueError(f"unknown proposer '{self.proposer}'; valid: {', '.join(PROPOSERS)}")
        if self.proposer == "radius" and not self.radius > 0:
            raise ValueError(f"radius must be > 0 m for proposer radius, got {self.radius}")


@dataclass(frozen=True)
class ConsistencyConfig:
    """odometry: the gate of each registered loop against the estimate (ratio < 0: off);
    pairwise: a loop enters the graph once a nearby loop agrees with it (window 0: off)."""

    odometry: OdometryGateParams = field(default_factory=OdometryGateParams)
    pairwise: ConsistencyParams = field(default_factory=ConsistencyParams)


@dataclass(frozen=True)
class WorkersConfig:
    """processes: 0 verifies at the keyframe itself; n > 0 in n worker processes, and the
    loop enters the graph ``lag`` keyframes later (waited for there: results never depend
    on timing, but the estimates later candidates are judged from do change with the lag)."""

    processes: int = 0
    lag: int = 2

    def __post_init__(self) -> None:
        if self.processes < 0 or self.lag < 1:
            raise ValueError(
                f"workers.processes must be >= 0 and workers.lag >= 1 (keyframes), got "
                f"{self.processes} and {self.lag}"
            )


def _flat_keys() -> dict[str, str]:
    """Version 0.1's flat key -> its nested place."""
    out = {"descriptor": "descriptor.kind", "sc_threshold": "search.threshold"}
    out |= {"verify_voxel": "verify.voxel", "verify_workers": "workers.processes"}
    out |= {"verify_lag": "workers.lag"}
    for name in ("rings", "sectors", "max_radius", "lidar_height", "auto_keyframes",
                 "ground_clearance", "cc_rows", "cc_cols", "cc_lateral", "cc_longitudinal",
                 "lateral_shifts", "longitudinal_shifts"):  # fmt: skip
        out[name] = f"descriptor.{name}"
    for name in ("exclude_recent", "exclude_seconds", "top_k", "rebuild_every", "shift_window",
                 "cc_threshold", "proposer", "radius", "radius_min_seconds", "proximity_radius",
                 "max_verify", "min_keyframe_gap"):  # fmt: skip
        out[name] = f"search.{name}"
    for name in ("neighbours", "max_correspondence", "coarse_voxel", "coarse_max_correspondence",
                 "global_search", "try_flip", "max_offset", "inlier_distance", "beam_gap_deg",
                 "plane_tolerance", "plane_range_ratio", "max_fitness", "min_overlap",
                 "min_overlap_near", "overlap_loss_per_m", "yaw_tolerance_deg",
                 "min_sigma_trans", "min_sigma_rot_deg", "min_sigma_tilt_deg", "max_sigma_ratio",
                 "coarse_registration", "coarse_vgicp_resolution", "ambiguity_ratio",
                 "free_sigma"):  # fmt: skip
        out[name] = f"verify.{name}"
    for name in ("base", "ratio", "yaw_deg"):
        out[f"consistency_{name}"] = f"consistency.odometry.{name}"
    for name in ("window", "base", "ratio", "base_deg", "ratio_deg"):
        out[f"pair_{name}"] = f"consistency.pairwise.{name}"
    return out


FLAT_KEYS = _flat_keys()


@dataclass
class LoopConfig(FactorConfig):
    """Scan Context proposes, GICP verifies, the consistency checks admit (see the sections).

    robust: Huber, not Cauchy(1): a verified loop's residual at the drifted linearisation
    point is large, and Cauchy(1) weights it so little that the loop never pulls; false
    loops are stopped upstream by verification and the consistency checks."""

    deprecated_keys: ClassVar[dict[str, str]] = FLAT_KEYS

    robust: str = "huber"
    descriptor: DescriptorConfig = field(default_factory=DescriptorConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    verify: VerifyParams = field(default_factory=VerifyParams)
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    workers: WorkersConfig = field(default_factory=WorkersConfig)
