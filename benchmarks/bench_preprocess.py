"""Speed of preprocessing and features on a simulated 28.8k-point 16-beam scan (ms per scan).

Run: .venv/bin/python benchmarks/bench_preprocess.py [--repeat 7]
Baseline: open3d remove_statistical_outlier (C++). Also prints outlier removal / surface kept.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import open3d as o3d

from slam.deskew import deskew
from slam.features.curvature import covariance_curvature
from slam.features.loam import FeatureConfig, extract_features
from slam.preprocess.sor import classic_sor, weighted_sor
from slam.preprocess.voxel import voxel_downsample


def scan(seed=0):
    """16 x 1800 rays in a closed yard (ground + 4 walls, infinite height) -> 28,800 points,
    1 cm range noise, 0.5 % of the points replaced by outliers uniform in the volume."""
    rng = np.random.default_rng(seed)
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    az = np.linspace(-np.pi, np.pi, 1800, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for c, ax in ((-15.0, 0), (25.0, 0), (-10.0, 1), (12.0, 1), (-1.5, 2)):
            tt = c / d[:, ax]
            t = np.where((tt > 0) & (tt < t), tt, t)
    xyz = d * (t + rng.normal(0, 0.01, len(t)))[:, None]
    label = np.zeros(len(xyz), dtype=int)
    out = rng.choice(len(xyz), int(0.005 * len(xyz)), replace=False)
    xyz[out] = rng.uniform([-15, -10, -1.5], [25, 12, 4], (len(out), 3))
    label[out] = 1
    ring = np.repeat(np.arange(16), 1800).astype(np.int16)
    time_s = np.tile(np.arange(1800) / 1800 * 0.1, 16)
    return xyz, label, ring, time_s


def timed(fn, repeat):
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    xyz, label, ring, time_s = scan()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 0.0]
    cfg_cov = FeatureConfig(use_covariance_curvature=True)
    cases = {
        "classic_sor (k=10)": lambda: classic_sor(xyz),
        "weighted_sor (k=10)": lambda: weighted_sor(xyz),
        "open3d remove_statistical_outlier": lambda: pc.remove_statistical_outlier(11, 1.0),
        "covariance_curvature (k=10)": lambda: covariance_curvature(xyz),
        "extract_features": lambda: extract_features(xyz, ring),
        "extract_features + kappa": lambda: extract_features(xyz, ring, cfg_cov),
        "deskew": lambda: deskew(xyz, time_s, T, 0.1),
        "voxel_downsample (0.2 m)": lambda: voxel_downsample(xyz, 0.2),
    }
    print(f"{len(xyz)} points, median of {args.repeat} runs")
    for name, fn in cases.items():
        print(f"  {name:36s} {timed(fn, args.repeat):8.1f} ms")
    for name, keep in (("classic", classic_sor(xyz)), ("weighted", weighted_sor(xyz))):
        print(
            f"  {name:9s} outliers removed {1 - keep[label == 1].mean():6.1%}"
            f"  surface kept {keep[label == 0].mean():6.1%}"
        )


if __name__ == "__main__":
    main()
