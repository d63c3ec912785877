"""Recordings that start at speed: the simulated motorway (``slam.sim.highway``) cut at a
frame where the car already moves (9-25 m/s), each front end's per-frame step error over the
first frames against the ground truth, next to small_gicp's scan-to-map odometry on the same
scans in the same run.

    .venv/bin/python benchmarks/motorway_starts.py [--cases 3:200:vlp16 2:200:vlp16:fields ...]
        [--configs improved_floam ...] [--frames 30] [--peer] [--set KEY=V ...]

Cases ``SEED:FRAME:SENSOR[:fields][:quiet]``: the motorway of that seed from that frame, as
the sensor's bag has it (x y z intensity, motion-compensated, no ring or time) or, with
``fields``, as the simulated driver publishes it (ring and time); ``quiet`` leaves the traffic
out. One row per case x system: the largest and the mean step error (m, translation of the
per-frame relative pose against the truth's) and the frames rejected. docs/robustness.md
("A start at speed off the open road", "A young map pairs within 0.3 m") has the tables.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slam.bench.peers import run_frontend, small_gicp_odometry
from slam.bench.robustness import step_errors
from slam.sim.highway import highway
from slam.sim.sensors import get_sensor
from slam.sim.simulate import STAMP0, effective_model, frame_stamps, published_scan
from slam.types import Scan

CASES = (  # the starts of docs/robustness.md
    "0:150:vlp16",
    "1:150:vlp16:quiet",
    "2:150:vlp16",
    "0:150:hdl32",
    "0:250:vlp16",
    "0:70:vlp16",
    "1:150:hdl32",
    "2:250:hdl32",
    "2:200:vlp16:fields",
    "2:200:vlp16",
    "3:200:vlp16",
    "4:200:vlp16:fields",
    "5:180:vlp16",
    "6:200:vlp16:fields",
    "3:200:hdl32:fields",
    "4:120:vlp16:fields",
    "1:220:hdl32",
    "5:200:hdl64:fields",
)


def start_scans(case: str, frames: int) -> tuple[list[Scan], np.ndarray]:
    """The scans of ``case`` (see the module doc) and their true poses (N, 4, 4)."""
    parts = case.split(":")
    if len(parts) < 3 or not set(parts[3:]) <= {"fields", "quiet"}:
        raise SystemExit(f"case {case!r}: expected SEED:FRAME:SENSOR[:fields][:quiet]")
    seed, first, sensor = int(parts[0]), int(parts[1]), parts[2]
    scene = highway(seed, pedestrians="quiet" not in parts[3:])
    spec, model = get_sensor(sensor), effective_model(scene, None, sensor)
    rng = np.random.default_rng([first, 7])
    scans, poses = [], []
    for i, stamp in enumerate(frame_stamps(first + frames, model)[first:]):
        scan, _ = published_scan(scene, float(stamp), model, spec, rng)
        scan.index = i
        if "fields" not in parts[3:]:
            scan.ring, scan.time = None, None
        scans.append(scan)
        poses.append(scene.pose_at(np.array([float(stamp) - STAMP0]))[0])
    return scans, np.asarray(poses)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    ap.add_argument("--configs", nargs="+", default=["improved_floam"])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--peer", action="store_true", help="also small_gicp on the same scans")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=V")
    args = ap.parse_args()
    print("| start | system | worst step error (m) | mean (m) | rejected | s |")
    print("|---|---|---|---|---|---|")
    for case in args.cases:
        scans, gt = start_scans(case, args.frames)
        systems = [*args.configs, *(["small_gicp"] if args.peer else [])]
        for name in systems:
            t = time.perf_counter()
            if name == "small_gicp":
                est, rejected = np.array(small_gicp_odometry(scans)), 0
            else:
                outs, _ = run_frontend(scans, name, list(args.set))
                est = np.array([o.pose for o in outs])
                rejected = sum(bool(o.diagnostics.rejected) for o in outs)
            err = step_errors(est, gt)
            dt = time.perf_counter() - t
            print(
                f"| {case} | {name} | {err.max():.3f} | {err.mean():.3f} | {rejected} | {dt:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
