"""Accuracy of our front-end recipes on every real sequence of ``../shared/data``, next to
small_gicp and KISS-ICP run on the same scans in the same process.

    .venv/bin/python benchmarks/bench_real.py [--configs improved_floam floam ...]
        [--sequences kitti04 kitti05 hilti nuscenes] [--set frontend.cloud_voxel=0.2 ...]
        [--variant LABEL:KEY=V[,KEY=V...] ...] [--no-peers] [--no-raw] [--json FILE]
        [--pair-spread] [--stride N] [--reverse]

--stride N keeps every N-th scan at its own stamp (a sensor at 1/N the frame rate: N times
the motion per scan, ~4.4 m on KITTI 04 and up to 31 deg on the hand-held Hilti scans with
--stride 3); --reverse plays the scans backwards (the stamps mirrored): a start in motion
from the first scan.

--set overrides apply to every run of our recipes; each --variant runs every recipe once
more with its overrides (an A/B in one run: same load, same scans), as
``benchmarks/bench_scenes.py`` does.

Sequences with reference poses (APE after SE(3) alignment and RPE over one frame, evo via
``slam.eval.metrics``): the first 10 scans of KITTI odometry 04 (in motion, ~14 m/s) and 05
(from standstill), HDL-64E .bin, poses converted to the LiDAR frame with the ``Tr`` of the
data's PROVENANCE.txt; 30 indoor Hilti scans (Hesai PandarXT-32, a static start and a
dropped frame); 39 nuScenes HDL-32E keyframes at 2 Hz (1-5 m apart). Ours run through
``slam.pipeline.Pipeline`` (beam model inferred from the first scans, as ``slam run``);
small_gicp: VGICP scan-to-map against a 1 m GaussianVoxelMap on 0.25 m downsampled clouds
(``slam.bench.peers``); KISS-ICP: its ``KissICP`` pipeline with its default config
(max range 100 m, voxel 1 m; no deskew: the scans carry no per-point time).

KITTI-raw (22 HDL-64E scans, no ground truth): the map is the judge. ``map blur`` is the
mean distance of each scan's points to the local planes of its neighbours placed with the
poses (cm, lower is sharper; 1 cm of pose noise adds ~0.1 cm). Also the HDL-32E pair against
its reference transform (good to ~1 cm / 0.3 deg: ``--pair-spread`` prints other aligners'
spread around it). Speed: CPU ms per frame (process time), noisy under load: compare within
a run only.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from slam.bench.peers import (
    kiss_icp_default_config,
    kiss_icp_track,
    motion_error,
    small_gicp_odometry,
    small_gicp_pair,
)
from slam.config import load_config
from slam.eval.map_blur import map_blur
from slam.eval.metrics import EvalOptions, evaluate_arrays
from slam.io.folders import FolderSource, read_cloud
from slam.io.kitti import KittiSource
from slam.pipeline import Pipeline
from slam.types import Scan

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RECIPES = ("improved_floam", "floam", "lego_loam", "lego_lpb")
PEERS = ("small_gicp", "kiss_icp")


@dataclass
class Sequence:
    """Real scans and their reference poses (N, 4, 4) in the sensor frame (None: no poses)."""

    name: str
    scans: list[Scan]
    gt: np.ndarray | None


def _kitti_tr() -> np.ndarray:
    """T_cam0_velo of KITTI odometry 04-12, from the shared data's PROVENANCE.txt."""
    rows = []
    for line in (DATA / "kitti_odometry" / "PROVENANCE.txt").read_text().splitlines():
        parts = line.split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            continue
        if len(values) == 4:
            rows.append(values)
    T = np.eye(4)
    T[:3] = np.array(rows[:3])
    return T


def kitti_odometry(seq: str) -> Sequence:
    src = KittiSource(DATA / "kitti_odometry" / seq)
    tr = _kitti_tr()
    gt = np.linalg.inv(tr)[None] @ src.ground_truth() @ tr[None]
    return Sequence(f"kitti{seq}", [s for s in src if isinstance(s, Scan)], gt)


def _folder(path: Path, period: float) -> list[Scan]:
    """The scans of a folder of numbered clouds ``period`` s apart, as ``slam run`` reads
    it with ``--set source.frame_period=PERIOD``."""
    return [s for s in FolderSource(path, frame_period=period) if isinstance(s, Scan)]


def hilti() -> Sequence:
    root = DATA / "hilti_indoor"
    gt = np.loadtxt(root / "poses_4x4_stacked.txt").reshape(-1, 4, 4)
    return Sequence("hilti", _folder(root / "clouds", 0.1), gt)


def nuscenes() -> Sequence:
    root = DATA / "nuscenes_keyframes"
    rows = np.loadtxt(root / "poses_kitti_format.txt").reshape(-1, 3, 4)
    gt = np.tile(np.eye(4), (len(rows), 1, 1))
    gt[:, :3] = rows
    return Sequence("nuscenes", _folder(root / "clouds", 0.5), gt)  # keyframes at 2 Hz


def kitti_raw(tmp: str) -> Sequence:
    with tarfile.open(DATA / "kitti_raw_drive" / "data_1.tar.xz", "r:xz") as tar:
        tar.extractall(tmp, filter="data")
    return Sequence("kitti_raw", _folder(Path(tmp) / "data_1", 0.1), None)


def resample(seq: Sequence, stride: int, reverse: bool) -> Sequence:
    """Every ``stride``-th scan at its own stamp, optionally backwards (stamps mirrored)."""
    idx = list(range(len(seq.scans)))[::stride]
    if reverse:
        idx = idx[::-1]
    if idx == list(range(len(seq.scans))):
        return seq
    t0 = seq.scans[idx[0]].stamp
    scans = [
        Scan(
            abs(seq.scans[i].stamp - t0),
            seq.scans[i].xyz,
            seq.scans[i].intensity,
            seq.scans[i].ring,
            seq.scans[i].time,
            j,
        )
        for j, i in enumerate(idx)
    ]
    tag = f"{seq.name}/{stride}{'r' if reverse else ''}"
    return Sequence(tag, scans, None if seq.gt is None else seq.gt[idx])


LOADERS = {
    "kitti04": lambda: kitti_odometry("04"),
    "kitti05": lambda: kitti_odometry("05"),
    "hilti": hilti,
    "nuscenes": nuscenes,
}


@dataclass
class Run:
    """One system on one sequence: poses (N, 4, 4), CPU s, frames rejected, sensor line."""

    poses: np.ndarray
    cpu_s: float
    rejected: int = 0
    sensor: str = ""


def run_ours(scans: list[Scan], recipe: str, overrides: list[str]) -> Run:
    """The recipe through the pipeline, as ``slam run`` (its loop closure off)."""
    cfg = load_config(recipe, [*overrides])
    pipe = Pipeline(cfg)
    c = time.process_time()
    st = pipe.run([Scan(s.stamp, s.xyz, s.intensity, s.ring, s.time, s.index) for s in scans])
    cpu = time.process_time() - c
    rejected = int(round(st.diagnostic_sums.get("rejected", 0.0)))
    return Run(np.asarray(st.odom_poses), cpu, rejected, st.sensor or "")


def run_small_gicp(scans: list[Scan]) -> Run:
    c = time.process_time()
    poses = small_gicp_odometry(scans)
    return Run(np.asarray(poses), time.process_time() - c)


def has_kiss_icp() -> bool:
    """KISS-ICP is a benchmark-only extra: without it its rows are left out, with one line."""
    if importlib.util.find_spec("kiss_icp") is not None:
        return True
    print("KISS-ICP not installed: its rows are left out (pip install 'pyslam-graph[bench]')")
    return False


def run_kiss_icp(scans: list[Scan]) -> Run:
    cfg = kiss_icp_default_config()
    c = time.process_time()
    poses = [T for _, T in kiss_icp_track(scans, cfg)]
    return Run(np.asarray(poses), time.process_time() - c)


def run_system(name: str, scans: list[Scan], overrides: list[str]) -> Run:
    """``name``: a peer, a recipe, or ``recipe@label`` (a variant: its overrides appended)."""
    if name == "small_gicp":
        return run_small_gicp(scans)
    if name == "kiss_icp":
        return run_kiss_icp(scans)
    recipe, _, label = name.partition("@")
    return run_ours(scans, recipe, [*overrides, *VARIANTS.get(label, [])])


VARIANTS: dict[str, list[str]] = {}  # label -> overrides, from --variant


def accuracy(run: Run, gt: np.ndarray) -> dict:
    """APE (SE(3)-aligned) and RPE over one frame (cm, deg), evo."""
    res = evaluate_arrays(None, run.poses, None, gt, EvalOptions(rpe_delta=1, rpe_unit="frames"))
    return {
        "ape_rmse_cm": 100 * res.ape_trans["rmse"],
        "ape_max_cm": 100 * res.ape_trans["max"],
        "rpe_cm": 100 * res.rpe_trans["mean"],
        "rpe_max_cm": 100 * res.rpe_trans["max"],
        "rpe_deg": res.rpe_rot["mean"],
    }


def delta(T: np.ndarray, T_ref: np.ndarray) -> str:
    """T_ref^-1 T as translation (cm) and rotation vector (deg), both per axis."""
    D = np.linalg.inv(T_ref) @ T
    rot = np.degrees(Rotation.from_matrix(D[:3, :3]).as_rotvec())
    return f"dt {np.round(100 * D[:3, 3], 2)} cm, drot {np.round(rot, 3)} deg"


def pair_rows(systems: list[str], overrides: list[str], spread: bool) -> list[str]:
    """The HDL-32E pair: each system's motion against the reference transform."""
    pair = DATA / "scan_pair"
    T_ref = np.loadtxt(pair / "T_target_source.txt")
    scans = [read_cloud(pair / "target.ply", index=0), read_cloud(pair / "source.ply", index=1)]
    scans[1].stamp = 0.1
    rows = []
    for name in systems:
        P = run_system(name, scans, overrides).poses
        t, r = motion_error(np.linalg.inv(P[0]) @ P[1], T_ref)
        rows.append(f"| {name} | {100 * t:.2f} cm | {r:.3f} deg |")
    if spread:
        for voxel in (0.1, 0.25, 0.5):
            for kind in ("GICP", "PLANE_ICP"):
                d = delta(small_gicp_pair(scans[0].xyz, scans[1].xyz, voxel, kind), T_ref)
                rows.append(f"| small_gicp {kind} s2s {voxel:.2f} m | {d} | |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=list(RECIPES))
    ap.add_argument("--sequences", nargs="+", default=list(LOADERS), choices=list(LOADERS))
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--no-peers", action="store_true", help="skip small_gicp and KISS-ICP")
    ap.add_argument("--no-raw", action="store_true", help="skip KITTI-raw and the pair")
    ap.add_argument("--json", type=Path, help="write every number to this file")
    ap.add_argument("--pair-spread", action="store_true", help="other aligners on the pair")
    ap.add_argument("--variant", nargs="+", default=[], help="LABEL:KEY=V[,KEY=V...]")
    ap.add_argument("--stride", type=int, default=1, help="keep every N-th scan (1/N the rate)")
    ap.add_argument("--reverse", action="store_true", help="play the scans backwards")
    args = ap.parse_args()
    if args.stride < 1:
        ap.error("--stride must be 1 or more")
    for v in args.variant:
        label, _, sets = v.partition(":")
        VARIANTS[label] = [x for x in sets.split(",") if x]
    variants = [f"{c}@{label}" for label in VARIANTS for c in args.configs]
    peers = [] if args.no_peers else [p for p in PEERS if p != "kiss_icp" or has_kiss_icp()]
    systems = [*args.configs, *variants, *peers]
    results: dict = {}
    lines = [
        "| sequence | system | APE RMSE cm | APE max cm | RPE/frame cm | RPE max cm "
        "| RPE/frame deg | rejected | CPU ms/frame |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in args.sequences:
        seq = resample(LOADERS[key](), args.stride, args.reverse)
        for name in systems:
            run = run_system(name, seq.scans, args.overrides)
            acc = accuracy(run, seq.gt)
            ms = 1e3 * run.cpu_s / len(seq.scans)
            results[f"{key}/{name}"] = {**acc, "rejected": run.rejected, "cpu_ms": ms}
            if run.sensor:
                results[f"{key}/sensor"] = run.sensor
            lines.append(
                f"| {key} ({len(seq.scans)}) | {name} | {acc['ape_rmse_cm']:.1f} "
                f"| {acc['ape_max_cm']:.1f} | {acc['rpe_cm']:.2f} | {acc['rpe_max_cm']:.1f} "
                f"| {acc['rpe_deg']:.3f} | {run.rejected} | {ms:.0f} |"
            )
            print(lines[-1], flush=True)
    print("\n" + "\n".join(lines))
    for key in args.sequences:
        if f"{key}/sensor" in results:
            print(f"{key}: sensor {results[f'{key}/sensor']}")
    if not args.no_raw:
        with tempfile.TemporaryDirectory() as tmp:
            raw = kitti_raw(tmp)
            rows = ["| system | map blur cm | CPU ms/frame |", "|---|---|---|"]
            for name in systems:
                run = run_system(name, raw.scans, args.overrides)
                blur = 100 * map_blur(raw.scans, run.poses)
                results[f"kitti_raw/{name}"] = {"map_blur_cm": blur}
                rows.append(f"| {name} | {blur:.3f} | {1e3 * run.cpu_s / len(raw.scans):.0f} |")
        print(f"\nKITTI raw ({len(raw.scans)} HDL-64E scans, no ground truth): map sharpness")
        print("\n".join(rows))
        print("\nHDL-32E pair vs reference T_target_source")
        print("| system | translation | rotation |\n|---|---|---|")
        print("\n".join(pair_rows(systems, args.overrides, args.pair_spread)))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
