"""Loop detection cost per keyframe at 1000 keyframes (target <= 10 ms without verification).

Synthetic clouds: 5-10k points on the faces of random boxes around the sensor (up to 80 m),
a new random place per keyframe with one in ten revisiting an older place (rotated, noisy)
so the search has real candidates. Reports descriptor, search (ring-key tree + column
distance on the top-k), the plugin's whole detection step (also voxelising the cloud it keeps
for verification) and, separately, GICP verification.

    .venv/bin/python benchmarks/bench_loop.py [--keyframes 1000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slam.factors import GraphView
from slam.loop.plugin import LoopClosurePlugin
from slam.loop.scan_context import scan_context
from slam.loop.verify import verify, yaw_matrix
from slam.types import Keyframe


def box_cloud(rng: np.random.Generator, n_points: int) -> np.ndarray:
    """Points on the side faces of 40 random boxes (1-15 m wide, 2-20 m tall) plus ground."""
    centres = rng.uniform(-70, 70, (40, 2))
    half = rng.uniform(0.5, 7.5, (40, 2))
    height = rng.uniform(2, 20, 40)
    b = rng.integers(0, 40, n_points)
    face = rng.integers(0, 4, n_points)
    u = rng.uniform(-1, 1, n_points)
    axis = face % 2  # faces 0/1: constant x, 2/3: constant y
    sign = np.where(face < 2, 1.0, -1.0)
    xy = np.empty((n_points, 2))
    xy[:, 0] = np.where(axis == 0, sign * half[b, 0], u * half[b, 0])
    xy[:, 1] = np.where(axis == 1, sign * half[b, 1], u * half[b, 1])
    xy += centres[b]
    z = rng.uniform(0, 1, n_points) * height[b] - 1.8
    ground = rng.random(n_points) < 0.3
    xy[ground] = rng.uniform(-30, 30, (ground.sum(), 2))
    z[ground] = -1.8
    return np.column_stack([xy, z])


def rotate(points: np.ndarray, yaw: float, rng: np.random.Generator) -> np.ndarray:
    T = yaw_matrix(yaw)
    return points @ T[:3, :3].T + rng.normal(0, 0.02, points.shape)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=1000)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.keyframes
    places: list[np.ndarray] = []
    clouds = []
    for i in range(n):
        if i > 100 and rng.random() < 0.1:
            clouds.append(rotate(places[rng.integers(0, i - 50)], rng.uniform(-np.pi, np.pi), rng))
        else:
            clouds.append(box_cloud(rng, int(rng.integers(5000, 10001))))
        places.append(clouds[-1])

    t = time.perf_counter()
    for c in clouds[:200]:
        scan_context(c)
    desc_ms = 1e3 * (time.perf_counter() - t) / 200

    # detection only: a huge min_keyframe_gap skips verification; search is timed again
    # on its own (the second query per keyframe)
    cfg = LoopClosurePlugin.Config(min_keyframe_gap=10**9, consistency_ratio=-1.0)
    plugin = LoopClosurePlugin(cfg)
    kfs: list[Keyframe] = []
    view = GraphView(kfs, lambda i: np.eye(4))
    search_ms = []
    hits = 0
    for i, c in enumerate(clouds):
        kf = Keyframe(i, 0.1 * i, i, np.eye(4), np.eye(4), np.eye(6), c)
        kfs.append(kf)
        plugin.on_keyframe(kf, view)
        d = scan_context(c)
        t = time.perf_counter()
        found = plugin.db.detect(d, kf.stamp)
        search_ms.append(1e3 * (time.perf_counter() - t))
        hits += found is not None
    det = np.array(plugin.detect_ms)

    ver_ms = []
    for _ in range(10):
        a = box_cloud(rng, 8000)
        yaw = rng.uniform(-np.pi, np.pi)
        b = rotate(a, -yaw, rng)
        t = time.perf_counter()
        verify(a, b, yaw_matrix(yaw + np.radians(4)))
        ver_ms.append(1e3 * (time.perf_counter() - t))

    print(f"keyframes: {n}, points per cloud: 5000-10000, candidates under threshold: {hits}")
    print(f"descriptor                 {desc_ms:7.2f} ms/keyframe")
    print(
        f"search (tree + top-k SC)   {np.mean(search_ms):7.2f} ms/keyframe (last 100: "
        f"{np.mean(search_ms[-100:]):.2f}), tree builds: {plugin.db.tree_builds}"
    )
    print(
        f"plugin detection step      {det.mean():7.2f} ms/keyframe (last 100: "
        f"{det[-100:].mean():.2f}; incl. voxelising the stored cloud)"
    )
    print(f"verification (GICP)        {np.mean(ver_ms):7.2f} ms/candidate")


if __name__ == "__main__":
    main()
