"""Incremental map (slam/mapping/incremental_map.py) against rebuilding one scipy cKDTree
per scan, as the map grows scan by scan, measured in the same run.

    .venv/bin/python benchmarks/bench_incremental_map.py [--scene plaza] [--frames 60]
        [--window 0] [--k 5] [--merge-ratio R] [--index buckets|merged] [--queries 1]

Each simulated scan (moved into the world with the ground truth, 0.1 m voxels) is inserted;
with --window W > 0 the points farther than W m from the sensor (box) are deleted lazily
(a sliding-window map). Then the next scan's points query their k nearest map points.
Prints per 10 scans: live points, buckets, ms to update (insert + delete) and to query,
for the incremental map and for the rebuilt tree, and the ratio of the totals.
--queries Q: the next scan queries Q times per insert (a front end's matcher associates
~20 times per frame: LM iterations of the two-step solve); --index merged: one KD-tree
over the live points rebuilt at the first query after a change (IncrementalMapConfig.index).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

from slam.io.source import open_source
from slam.mapping.incremental_map import IncrementalMap, IncrementalMapConfig
from slam.preprocess.voxel import voxel_downsample
from slam.sim.cache import ensure_sequence


def world_scans(scene: str, frames: int) -> list[np.ndarray]:
    seq = ensure_sequence(scene, frames=frames)
    _, poses = seq.read_ground_truth()
    out = []
    for k, scan in enumerate(open_source(seq.bag)):
        T = poses[k]
        out.append(scan.xyz[voxel_downsample(scan.xyz, 0.1)] @ T[:3, :3].T + T[:3, 3])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="plaza")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--window", type=float, default=0.0, help="sliding box half-size (m)")
    ap.add_argument("--k", type=int, default=5)
    ap.add_argument("--merge-ratio", type=float, default=IncrementalMapConfig.merge_ratio)
    ap.add_argument("--index", choices=("buckets", "merged"), default="buckets")
    ap.add_argument("--queries", type=int, default=1, help="k-NN queries per insert")
    args = ap.parse_args()
    scans = world_scans(args.scene, args.frames)
    inc = IncrementalMap(IncrementalMapConfig(merge_ratio=args.merge_ratio, index=args.index))
    live: list[np.ndarray] = []  # the baseline's point list
    totals = np.zeros(4)  # inc update, inc query, rebuild, rebuilt query
    print(
        f"{'scan':>5} {'points':>9} {'buckets':>7} | {'inc upd':>8} {'inc qry':>8} | "
        f"{'rebuild':>8} {'reb qry':>8} | ratio (ms, this scan)"
    )
    for k in range(len(scans) - 1):
        pts, nxt = scans[k], scans[k + 1]
        centre = pts.mean(axis=0)
        t0 = time.perf_counter()
        inc.insert(pts)
        if args.window > 0:
            inc.delete(box=(centre - args.window, centre + args.window), outside=True)
        t1 = time.perf_counter()
        for _ in range(args.queries):
            d_inc, _ = inc.knn(nxt, args.k)
        t2 = time.perf_counter()
        live.append(pts)
        allp = np.concatenate(live)
        if args.window > 0:
            allp = allp[np.all(np.abs(allp - centre) <= args.window, axis=1)]
            live = [allp]
        tree = cKDTree(allp)
        t3 = time.perf_counter()
        for _ in range(args.queries):
            d_ref, _ = tree.query(nxt, k=args.k)
        t4 = time.perf_counter()
        assert np.allclose(d_inc, d_ref.reshape(d_inc.shape))  # same answers
        dt = np.array([t1 - t0, t2 - t1, t3 - t2, t4 - t3]) * 1e3
        totals += dt
        if k % 10 == 0 or k == len(scans) - 2:
            ratio = (dt[0] + dt[1]) / (dt[2] + dt[3])
            print(
                f"{k:5d} {len(inc):9d} {inc.n_buckets:7d} | {dt[0]:8.1f} {dt[1]:8.1f} | "
                f"{dt[2]:8.1f} {dt[3]:8.1f} | {ratio:.2f}"
            )
    print(
        f"total ms: incremental update {totals[0]:.0f} + query {totals[1]:.0f} = "
        f"{totals[0] + totals[1]:.0f}; rebuild {totals[2]:.0f} + query {totals[3]:.0f} = "
        f"{totals[2] + totals[3]:.0f}; ratio incremental/rebuild "
        f"{(totals[0] + totals[1]) / (totals[2] + totals[3]):.2f}"
    )


if __name__ == "__main__":
    main()
