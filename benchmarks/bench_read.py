"""Reading speed: frames/s of BagSource (read + deserialise + decode) relative to raw
rosbags AnyReader iteration without deserialisation (the baseline), same run, same file;
with ``--pcd DIR``: FolderSource (numpy PCD reader) relative to open3d.t.io.read_point_cloud
on the same files (e.g. the real KITTI-raw PCDs of ../shared/data/kitti_raw_drive, extracted).

    .venv/bin/python benchmarks/bench_read.py [--scans 60] [--points 28800] [--fmt ros1]
    .venv/bin/python benchmarks/bench_read.py --pcd /tmp/data_1
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from slam.io.bag_writer import write_pointcloud_bag
from slam.io.bags import BagSource, _bag_dir
from slam.io.folders import FolderSource
from slam.types import Scan


def make_scans(n_scans: int, n_points: int) -> list[Scan]:
    rng = np.random.default_rng(0)
    return [
        Scan(
            stamp=1.0 + 0.1 * i,
            xyz=rng.uniform(-50, 50, (n_points, 3)),
            intensity=rng.uniform(0, 255, n_points).astype(np.float32),
            ring=(np.arange(n_points) % 16).astype(np.int16),
            time=np.linspace(0.0, 0.1, n_points),
        )
        for i in range(n_scans)
    ]


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bench_pcd(folder: Path, repeats: int) -> None:
    """FolderSource vs open3d.t.io on the same PCD files (same run)."""
    import open3d as o3d

    source = FolderSource(folder)
    files = source.files

    def o3d_read() -> None:
        for f in files:
            pc = o3d.t.io.read_point_cloud(str(f))
            pc.point.positions.numpy().astype(np.float64)

    def ours() -> None:
        assert sum(isinstance(s, Scan) for s in source) == len(files)

    t_o3d, t_ours = best_of(o3d_read, repeats), best_of(ours, repeats)
    pts = sum(len(s) for s in source if isinstance(s, Scan)) / len(files)
    print(f"PCD folder {folder}: {len(files)} files, {pts:.0f} points each")
    print(f"  open3d.t.io.read_point_cloud (baseline): {len(files) / t_o3d:8.1f} frames/s")
    print(f"  FolderSource (numpy PCD reader):         {len(files) / t_ours:8.1f} frames/s")
    print(f"  ratio FolderSource / baseline:           {t_o3d / t_ours:8.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=60)
    ap.add_argument("--points", type=int, default=28_800)
    ap.add_argument("--fmt", default="ros1", choices=["ros1", "ros2", "mcap"])
    ap.add_argument("--layout", default="velodyne")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--pcd", type=Path, help="a folder of .pcd files: compare with open3d")
    args = ap.parse_args()
    if args.pcd is not None:
        bench_pcd(args.pcd, args.repeats)
        return

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / ("b.bag" if args.fmt == "ros1" else "b")
        write_pointcloud_bag(
            path, make_scans(args.scans, args.points), fmt=args.fmt, layout=args.layout
        )
        size_mb = sum(p.stat().st_size for p in [path, *path.glob("*")] if p.is_file()) / 1e6

        def raw() -> None:
            store = get_typestore(Stores.ROS1_NOETIC)
            with _bag_dir(path) as bag, AnyReader([bag], default_typestore=store) as reader:
                n = sum(1 for _ in reader.messages())
            assert n == args.scans

        def deser() -> None:
            store = get_typestore(Stores.ROS1_NOETIC)
            with _bag_dir(path) as bag, AnyReader([bag], default_typestore=store) as reader:
                for conn, _, data in reader.messages():
                    reader.deserialize(data, conn.msgtype)

        source = BagSource(path)

        def ours() -> None:
            n = sum(isinstance(scan, Scan) for scan in source)
            assert n == args.scans

        t_raw, t_deser, t_ours = (best_of(f, args.repeats) for f in (raw, deser, ours))
    fps = {k: args.scans / t for k, t in (("raw", t_raw), ("deser", t_deser), ("ours", t_ours))}
    print(
        f"{args.fmt} bag, {args.scans} scans x {args.points} points ({args.layout}), "
        f"{size_mb:.0f} MB"
    )
    print(f"  raw AnyReader iteration (baseline): {fps['raw']:8.1f} frames/s")
    print(f"  + rosbags deserialise:              {fps['deser']:8.1f} frames/s")
    print(f"  BagSource (read+deser+decode):      {fps['ours']:8.1f} frames/s")
    print(f"  ratio BagSource / baseline:         {fps['ours'] / fps['raw']:8.2f}")


if __name__ == "__main__":
    main()
