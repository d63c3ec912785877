"""Frames/s of the front ends on simulated 16-beam scans (~28k points), next to small_gicp's
own scan-to-map odometry (align against a GaussianVoxelMap) measured in the same run.

    .venv/bin/python benchmarks/bench_frontends.py [--scene corridor] [--frames 100]
        [--sensor hdl64] [--configs improved_floam floam]

Prints frames/s, mean per-stage times and the final translation error of each.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import small_gicp

from slam.io.source import open_source
from slam.plugins import instantiate
from slam.sim.cache import ensure_sequence


def small_gicp_odometry(scans, threads: int = 2) -> list[np.ndarray]:
    """The reference: downsample 0.25 m, VGICP against a 1 m GaussianVoxelMap, const. velocity."""
    vmap = small_gicp.GaussianVoxelMap(1.0)
    vmap.set_lru(horizon=100, clear_cycle=10)
    T, motion, poses = np.eye(4), np.eye(4), []
    for k, scan in enumerate(scans):
        pc, _ = small_gicp.preprocess_points(scan.xyz, 0.25, num_threads=threads)
        if k:
            res = small_gicp.align(vmap, pc, T @ motion, num_threads=threads)
            motion = np.linalg.inv(T) @ res.T_target_source
            T = res.T_target_source
        vmap.insert(pc, T)
        poses.append(T.copy())
    return poses


def final_error(poses, scans, gt_stamps, gt) -> float:
    idx = np.clip(np.searchsorted(gt_stamps, [s.stamp for s in scans]), 0, len(gt) - 1)
    G = np.linalg.inv(gt[idx[0]]) @ gt[idx[-1]]
    return float(np.linalg.norm(poses[-1][:3, 3] - G[:3, 3]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="corridor")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--sensor", help="simulated sensor model (default: the scene's 16 beams)")
    ap.add_argument("--configs", nargs="+", default=["improved_floam", "floam"])
    args = ap.parse_args()
    kw = {"sensor": args.sensor} if args.sensor else {}
    sim = ensure_sequence(args.scene, frames=args.frames, **kw)
    scans = list(open_source(sim.bag))
    gt_stamps, gt = sim.read_ground_truth()
    print(f"{args.scene}: {len(scans)} scans, {np.mean([len(s) for s in scans]):.0f} points each")
    rows = []
    for name in args.configs:
        fe = instantiate("slam.frontends", {"name": name}, "frontend")
        for scan in scans[:3]:  # compile / load the numba kernels (registration from frame 1)
            fe.process(scan)
        fe = instantiate("slam.frontends", {"name": name}, "frontend")
        t0 = time.perf_counter()
        outs = [fe.process(s) for s in scans]
        dt = time.perf_counter() - t0
        stages = {
            k: np.mean([o.extras.get(k, 0.0) for o in outs])
            for k in outs[-1].extras
            if k.endswith("_ms")
        }
        err = final_error([o.pose for o in outs], scans, gt_stamps, gt)
        rows.append((name, len(scans) / dt, err, stages))
    t0 = time.perf_counter()
    poses = small_gicp_odometry(scans)
    dt = time.perf_counter() - t0
    rows.append(
        ("small_gicp (reference)", len(scans) / dt, final_error(poses, scans, gt_stamps, gt), {})
    )
    ref = rows[-1][1]
    print(f"{'front end':24s} {'frames/s':>9s} {'x ref':>6s} {'final err m':>12s}  stage ms")
    for name, fps, err, stages in rows:
        st = ", ".join(f"{k[:-3]} {v:.1f}" for k, v in stages.items())
        print(f"{name:24s} {fps:9.1f} {fps / ref:6.3f} {err:12.4f}  {st}")


if __name__ == "__main__":
    main()
