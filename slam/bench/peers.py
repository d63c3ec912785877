"""The systems our recipes are measured against, run on the same scans: small_gicp's
scan-to-map VGICP odometry and scan-to-scan registration, KISS-ICP, and one of our front
ends alone (no back end)."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

import numpy as np

from slam.types import Scan


def small_gicp_track(scans: Iterable[Scan], threads: int = 2) -> Iterator[tuple[float, np.ndarray]]:
    """(stamp, pose) per scan of small_gicp's odometry: downsample 0.25 m, VGICP against a
    1 m GaussianVoxelMap (LRU horizon 100), constant-velocity prediction. Streams."""
    import small_gicp

    vmap = small_gicp.GaussianVoxelMap(1.0)
    vmap.set_lru(horizon=100, clear_cycle=10)
    T, motion = np.eye(4), np.eye(4)
    for k, scan in enumerate(scans):
        pc, _ = small_gicp.preprocess_points(scan.xyz, 0.25, num_threads=threads)
        if k:
            res = small_gicp.align(vmap, pc, T @ motion, num_threads=threads)
            motion = np.linalg.inv(T) @ res.T_target_source
            T = res.T_target_source
        vmap.insert(pc, T)
        yield scan.stamp, T.copy()


def small_gicp_odometry(scans: Iterable[Scan], threads: int = 2) -> list[np.ndarray]:
    """The poses (4, 4) of :func:`small_gicp_track`, one per scan."""
    return [T for _, T in small_gicp_track(scans, threads)]


def small_gicp_pair(
    target: np.ndarray, source: np.ndarray, voxel: float = 0.25, kind: str = "GICP"
) -> np.ndarray:
    """small_gicp's scan-to-scan ``kind`` registration: T_target_source from the identity."""
    import small_gicp

    tgt, tree = small_gicp.preprocess_points(target, voxel, num_threads=2)
    src, _ = small_gicp.preprocess_points(source, voxel, num_threads=2)
    res = small_gicp.align(tgt, src, tree, np.eye(4), registration_type=kind, num_threads=2)
    return res.T_target_source


def kiss_icp_default_config():
    """KISS-ICP's own default config (max range 100 m, voxel 1 m), deskew off: our scans
    carry no per-point time."""
    from kiss_icp.config import load_config

    cfg = load_config(None)
    cfg.data.deskew = False
    return cfg


def kiss_icp_two_thread_config():
    """KISS-ICP's defaults with deskew off, voxel max_range / 100 and two threads (the
    whole-process timings of bench_realtime.py, on a 2-core machine)."""
    from kiss_icp.config import KISSConfig

    cfg = KISSConfig()
    cfg.data.deskew = False
    cfg.mapping.voxel_size = cfg.data.max_range / 100.0
    cfg.registration.max_num_threads = 2
    return cfg


def kiss_icp_track(scans: Iterable[Scan], cfg) -> Iterator[tuple[float, np.ndarray]]:
    """(stamp, pose) per scan of KISS-ICP's ``KissICP`` pipeline with ``cfg``. Streams."""
    from kiss_icp.kiss_icp import KissICP

    odom = KissICP(cfg)
    for scan in scans:
        odom.register_frame(np.asarray(scan.xyz, dtype=np.float64), np.zeros(0))
        yield scan.stamp, odom.last_pose.copy()


def motion_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) of A^-1 B."""
    D = np.linalg.inv(A) @ B
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(np.arccos(cos)))


def run_frontend(scans: list[Scan], config: str, overrides: list[str]) -> tuple[list, float]:
    """The recipe's front end alone over ``scans`` (rings filled from the beam model of the
    first three): its Odometry of every scan and the wall time (s)."""
    from slam.config import load_config
    from slam.plugins import instantiate
    from slam.sensor import estimate_beams

    fe = instantiate("slam.frontends", load_config(config, overrides).frontend, "frontend")
    model = estimate_beams([s.xyz for s in scans[:3]])
    for s in scans:
        if s.ring is None:
            s.ring = model.ring_of(s.xyz)
    t = time.perf_counter()
    outs = [fe.process(s) for s in scans]
    return outs, time.perf_counter() - t
