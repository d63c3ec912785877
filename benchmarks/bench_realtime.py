"""Real-time factor of whole processes: ``slam run`` (start to outputs written) per recipe
and sensor, next to small_gicp's and KISS-ICP's odometry on the same scans, in the same run.

    .venv/bin/python benchmarks/bench_realtime.py [--quick] [--frames 200]
        [--recipes improved_floam_loop floam ...] [--datasets urban16 corridor ...]
        [--peers small_gicp kiss_icp] [--set frontend.sor.mode=banded]
        [--before /path/to/other/checkout/.venv/bin/slam]

Datasets: ``urban16`` (16-beam car-speed city drive, ``slam simulate urban``), ``corridor``
(16-beam indoor), ``urban64`` (simulated HDL-64E, ``--sensor hdl64``), ``kitti-raw`` (the 22
real KITTI-raw HDL-64E scans in ../shared/data/kitti_raw_drive), ``urban128`` (``--sensor
os128``). Every system runs as its own process (``os.wait4``: wall time, CPU time, peak
resident memory of that process); the peers read the scans with our reader, so both sides
pay the same input cost. Columns: frames/s of the whole process, the ratio to small_gicp's
frames/s in the same run, cores used (CPU time / wall time), peak memory (MiB; per km of
path from ``metrics.json`` for ours), the
front end's own per-frame stage means (``metrics.json`` ``frontend_means``, ms) and CPU ms
per frame of the pipeline's stages (``stage_cpu_ms_last100``), APE RMSE against ground truth
when there is one. ``--before SLAM``: every recipe also runs with another checkout's
``slam`` (rows ``recipe (before)``), so before and after are measured in the same run.
Timings on a loaded machine are noisy: read the ratio, not the frames/s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti_raw_drive" / "data_1.tar.xz"
SLAM = Path(sys.executable).parent / "slam"
RECIPES = ("improved_floam_loop", "improved_floam", "floam", "lego_loam", "lego_lpb")
DATASETS = ("urban16", "corridor", "urban64", "kitti-raw", "urban128")
PEERS = ("small_gicp", "kiss_icp")
SIM = {  # dataset -> (scene, sensor)
    "urban16": ("urban", "vlp16"),
    "corridor": ("corridor", "vlp16"),
    "urban64": ("urban", "hdl64"),
    "urban128": ("urban", "os128"),
}
STAGES = ("sor", "features", "covariance", "registration", "map")


@dataclass
class Run:
    """One whole process: wall s, CPU s, peak RSS MiB, frames, metrics.json and APE RMSE."""

    system: str
    wall: float
    cpu: float
    peak_mb: float
    frames: int
    metrics: dict = field(default_factory=dict)
    ape: float | None = None
    error: str = ""

    @property
    def fps(self) -> float:
        return self.frames / self.wall if self.wall > 0 else 0.0


def timed_process(argv: list[str], env: dict | None = None) -> tuple[float, float, float, str]:
    """Run argv to its end; (wall s, CPU s user+sys, peak RSS MiB, stderr tail)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        p = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err, env=env)
        _, status, ru = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        tail = err.read().decode(errors="replace")[-400:] if p.returncode else ""
    return wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024.0, tail


def prepare(name: str, frames: int, tmp: Path) -> tuple[Path, Path | None, int]:
    """(input path, ground truth or None, frames) of a dataset; simulated ones are cached."""
    if name == "kitti-raw":
        if not KITTI.is_file():
            raise SystemExit(f"missing {KITTI}: the shared data folder must sit beside the repo")
        with tarfile.open(KITTI, "r:xz") as tar:
            tar.extractall(tmp, filter="data")
        folder = tmp / "data_1"
        return folder, None, min(frames, len(list(folder.glob("*.pcd"))))
    from slam.sim.cache import ensure_sequence

    scene, sensor = SIM[name]
    sim = ensure_sequence(scene, frames=frames, sensor=sensor)
    return Path(sim.bag), Path(sim.ground_truth), frames


def run_ours(
    recipe: str, bag: Path, gt: Path | None, frames: int, out: Path, sets, slam: Path = SLAM
) -> Run:
    argv = [str(slam), "run", str(bag), "--config", recipe, "--out", str(out), "--quiet"]
    argv += ["--max-frames", str(frames)] + (["--gt", str(gt)] if gt else [])
    for s in sets:
        argv += ["--set", s]
    wall, cpu, peak, err = timed_process(argv)
    if err:
        return Run(recipe, wall, cpu, peak, 0, error=err.strip().splitlines()[-1])
    m = json.loads((out / "metrics.json").read_text())
    ape = None
    if (out / "ape.json").is_file():
        ape = json.loads((out / "ape.json").read_text())["ape_trans"]["rmse"]
    return Run(recipe, wall, cpu, peak, int(m["frames"]), m, ape)


PEER_CODE = """
import itertools, sys
import numpy as np
from slam.bench import peers
from slam.io.source import open_source
from slam.types import Scan
peer, path, frames = sys.argv[1], sys.argv[2], int(sys.argv[3])
scans = itertools.islice((s for s in open_source(path) if isinstance(s, Scan)), frames)
if peer == "small_gicp":
    track = peers.small_gicp_track(scans, threads=2)
else:
    track = peers.kiss_icp_track(scans, peers.kiss_icp_two_thread_config())
stamps, poses = [], []
for stamp, pose in track:
    stamps.append(stamp); poses.append(pose)
np.save(sys.argv[4], np.array(poses)); np.save(sys.argv[4] + ".stamps.npy", np.array(stamps))
"""


def ape_of(poses_file: Path, gt: Path | None) -> float | None:
    """APE RMSE (m) of a peer's poses against the TUM ground truth, SE(3)-aligned (evo)."""
    if gt is None:
        return None
    import numpy as np

    from slam.eval.metrics import evaluate_arrays, read_trajectory

    poses = np.load(poses_file)
    stamps = np.load(str(poses_file) + ".stamps.npy")
    gt_stamps, gt_poses = read_trajectory(gt)
    res = evaluate_arrays(stamps, poses, gt_stamps, gt_poses)
    return float(res.ape_trans["rmse"])


def run_peer(peer: str, bag: Path, gt: Path | None, frames: int, tmp: Path) -> Run:
    poses = tmp / f"{peer}.npy"
    argv = [sys.executable, "-c", PEER_CODE, peer, str(bag), str(frames), str(poses)]
    wall, cpu, peak, err = timed_process(argv)
    if err:
        return Run(peer, wall, cpu, peak, 0, error=err.strip().splitlines()[-1])
    n = len(__import__("numpy").load(poses))
    return Run(peer, wall, cpu, peak, n, ape=ape_of(poses, gt))


def row(dataset: str, r: Run, ref_fps: float | None) -> str:
    if r.error:
        return f"| {dataset} | {r.system} | failed: {r.error[:80]} |" + " |" * 10
    ratio = f"{r.fps / ref_fps:.2f}x" if ref_fps else "-"
    means = r.metrics.get("frontend_means", {})
    stages = " / ".join(f"{means.get(f'{s}_ms', 0.0):.1f}" for s in STAGES)
    cpu = r.metrics.get("stage_cpu_ms_last100", {})
    fe_cpu = f"{cpu['frontend']:.1f}" if "frontend" in cpu else "-"
    cpu_frame = 1e3 * r.cpu / max(r.frames, 1)
    counts = r.metrics.get("frontend_counts", {})
    bad = counts.get("rejected", 0) + counts.get("tracking_lost", 0)
    ape = f"{100 * r.ape:.2f}" if r.ape is not None else "-"
    per_km = r.metrics.get("memory_mb_per_km")
    per_km = f"{per_km:.0f}" if per_km else "-"
    return (
        f"| {dataset} | {r.system} | {r.frames} | {r.fps:.1f} | {ratio} | {cpu_frame:.0f} | "
        f"{r.cpu / r.wall:.2f} | {r.peak_mb:.0f} | {per_km} | {fe_cpu} | "
        f"{stages if means else '-'} | {bad if r.metrics else '-'} | {ape} |"
    )


HEADER = (
    "| data | system | frames | frames/s | x small_gicp | CPU ms/frame | cores | peak MiB | "
    "MiB/km | front end CPU ms/frame | sor / features / cov / reg / map ms | rejected+lost | "
    "APE cm |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--recipes", nargs="+", default=list(RECIPES))
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=DATASETS)
    ap.add_argument("--peers", nargs="*", default=list(PEERS), choices=PEERS)
    ap.add_argument("--set", action="append", default=[], help="override for our runs")
    ap.add_argument("--before", type=Path, help="another checkout's slam, run next to ours")
    ap.add_argument("--quick", action="store_true", help="40 frames, 3 datasets, 2 recipes")
    a = ap.parse_args(argv)
    if a.quick:
        a.frames = min(a.frames, 40)
        a.datasets = [d for d in a.datasets if d in ("urban16", "corridor", "kitti-raw")]
        a.recipes = a.recipes[:2]
    print(f"load average at start {os.getloadavg()[0]:.1f} (2 cores: read the ratios)\n")
    print(HEADER, flush=True)
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for ds in a.datasets:
            bag, gt, n = prepare(ds, a.frames, tmp)
            peers = {p: run_peer(p, bag, gt, n, tmp) for p in a.peers}
            ref = peers.get("small_gicp")
            ref_fps = ref.fps if ref is not None and not ref.error else None
            slams = [("", SLAM)] + ([(" (before)", a.before)] if a.before else [])
            for recipe in a.recipes:
                for tag, slam in slams:
                    sets = a.set if not tag else []
                    if ds == a.datasets[0]:  # numba's cache filled before the timed run
                        run_ours(recipe, bag, gt, 3, tmp / f"warm-{recipe}{tag}", sets, slam)
                    r = run_ours(recipe, bag, gt, n, tmp / f"{ds}-{recipe}{tag}", sets, slam)
                    r.system += tag
                    print(row(ds, r, ref_fps), flush=True)
            for r in peers.values():
                print(row(ds, r, ref_fps), flush=True)


if __name__ == "__main__":
    main()
