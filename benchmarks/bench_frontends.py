"""Frames/s of the front ends on simulated 16-beam scans (~28k points), next to small_gicp's
own scan-to-map odometry (align against a GaussianVoxelMap) measured in the same run.

    .venv/bin/python benchmarks/bench_frontends.py [--scene corridor] [--frames 100]
        [--sensor hdl64] [--configs improved_floam floam]
    .venv/bin/python benchmarks/bench_frontends.py --first-frame [--cold] [--sensor hdl64]

Prints frames/s, mean per-stage times and the final translation error of each.
--first-frame: the first frames of the default recipe's pipeline in fresh processes, without
and with ``slam.warmup.warm_up`` before the first frame (wall and CPU ms per frame, the
warm-up's seconds); --cold runs them with an empty numba cache (NUMBA_CACHE_DIR in a
temporary folder: the first run's compile time).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from slam.bench.peers import small_gicp_odometry
from slam.io.source import open_source
from slam.plugins import instantiate
from slam.sim.cache import ensure_sequence


def final_error(poses, scans, gt_stamps, gt) -> float:
    idx = np.clip(np.searchsorted(gt_stamps, [s.stamp for s in scans]), 0, len(gt) - 1)
    G = np.linalg.inv(gt[idx[0]]) @ gt[idx[-1]]
    return float(np.linalg.norm(poses[-1][:3, 3] - G[:3, 3]))


FIRST_FRAME = """
import json, sys, time
t0 = time.perf_counter()
from slam.config import load_config
from slam.io.source import open_source
from slam.pipeline import Pipeline
from slam.sim.cache import ensure_sequence
from slam.types import Scan
imported = time.perf_counter() - t0
scene, frames, sensor, warm = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4] == "1"
sim = ensure_sequence(scene, frames=frames, **({"sensor": sensor} if sensor else {}))
scans = [s for s in open_source(sim.bag) if isinstance(s, Scan)][:5]
pipe = Pipeline(load_config("improved_floam"))
wall = cpu = 0.0
if warm:
    from slam.warmup import warm_up
    c, w = time.process_time(), time.perf_counter()
    warm_up(pipe.config.frontend)
    wall, cpu = time.perf_counter() - w, time.process_time() - c
pipe.run(scans)
st = pipe.state
print(json.dumps(dict(imported=imported, warm_wall=wall, warm_cpu=cpu,
                      wall=[1e3 * x for x in st.frame_seconds],
                      cpu=[1e3 * x for x in st.frame_cpu_seconds])))
"""


def first_frame(scene: str, frames: int, sensor: str | None, cold: bool) -> None:
    """First frames of the default pipeline in fresh processes, without / with the warm-up."""
    print(f"{scene} {sensor or ''}: fresh process each, numba cache {'empty' if cold else 'warm'}")
    print(f"  load average {os.getloadavg()[0]:.1f}; ms per frame, wall (CPU)")
    for warm in (False, True):
        env = dict(os.environ)
        with tempfile.TemporaryDirectory() as tmp:
            if cold:
                env["NUMBA_CACHE_DIR"] = tmp
            argv = [sys.executable, "-c", FIRST_FRAME, scene, str(frames), sensor or ""]
            out = subprocess.run(
                [*argv, str(int(warm))], env=env, capture_output=True, text=True, check=True
            ).stdout
        r = json.loads(out.strip().splitlines()[-1])
        pairs = zip(r["wall"], r["cpu"], strict=True)
        frames_txt = " ".join(f"{w:.0f} ({c:.0f})" for w, c in pairs)
        warm_txt = f"warm-up {r['warm_wall']:.2f} s ({r['warm_cpu']:.2f} s CPU), " if warm else ""
        print(f"  {'with' if warm else 'without'} warm-up: {warm_txt}frames {frames_txt}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="corridor")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--sensor", help="simulated sensor model (default: the scene's 16 beams)")
    ap.add_argument("--configs", nargs="+", default=["improved_floam", "floam"])
    ap.add_argument("--first-frame", action="store_true", help="first frames, fresh processes")
    ap.add_argument("--cold", action="store_true", help="--first-frame with an empty numba cache")
    args = ap.parse_args()
    if args.first_frame:
        first_frame(args.scene, args.frames, args.sensor, args.cold)
        return
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
