"""Accuracy, speed and memory of the front ends on simulated scenes and sensors, next to
small_gicp's own scan-to-map odometry run on the same scans in the same run.

    .venv/bin/python benchmarks/bench_scenes.py --scene urban --sensor vlp16 hdl64 \\
        --configs improved_floam floam improved_floam_loop [--frames N] \\
        [--set frontend.plane_voxel=0.3 ...] \\
        [--variant off:frontend.max_scan_points=0 60k:frontend.max_scan_points=60000 ...]

--calibration-seed N [N ...]: the scene's sensor with other draws of its per-beam calibration
errors (``LidarModel.calibration_seed``; "ideal" = none), one sequence per draw (cached like
the others). One draw is one sensor unit: on the urban drive (HDL-32E, 150 frames) improved
FLOAM's APE was 3.7 cm without calibration errors and 31 / 67 / 33 cm with draws 0 / 1 / 2
(FLOAM 8.5 / 15 / 55 / 37 cm), so compare front ends over several draws.

--set overrides apply to every run; each --variant LABEL:KEY=V[,KEY=V...] runs every config
once more with its overrides (an A/B in one run: same load, same scans).

One row per scene x sensor x config: APE RMSE / mean / max (SE(3)-aligned, m), KITTI drift
(%/10 m... the devkit's t_rel over its segment lengths, scaled ones on short runs), the
largest per-frame step error (m: |relative translation - ground truth's| between consecutive
frames), frames/s, peak memory (MiB, each run in its own process), degenerate / lost frames
and loops. Markdown table on stdout; JSON rows with --json FILE.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tempfile
import time
from pathlib import Path

import numpy as np


def step_error(est_poses: np.ndarray, gt_poses: np.ndarray) -> float:
    """Largest per-frame translation error (m) of consecutive relative motions."""
    if len(est_poses) < 2:
        return 0.0
    rel_e = np.linalg.inv(est_poses[:-1]) @ est_poses[1:]
    rel_g = np.linalg.inv(gt_poses[:-1]) @ gt_poses[1:]
    return float(np.linalg.norm(rel_e[:, :3, 3] - rel_g[:, :3, 3], axis=1).max())


def _run(job: dict) -> dict:
    """One config on one sequence (in a fresh process, so that peak memory is its own)."""
    from slam.config import load_config
    from slam.eval.metrics import evaluate
    from slam.run import run_one

    config = load_config(job["config"], job.get("overrides") or [])
    if job["frames"]:
        config.source.max_frames = job["frames"]
    out = Path(job["out"])
    summary = run_one(Path(job["bag"]), config, out, quiet=True)
    m = json.loads((out / "metrics.json").read_text())
    res = evaluate(out / "trajectory.tum", Path(job["gt"]))
    kitti = res.kitti or {}
    return {
        "scene": job["scene"],
        "sensor": job["sensor"],
        "config": job["config"] + (f" [{job['variant']}]" if job.get("variant") else ""),
        "frames": summary["frames"],
        "path_m": round(res.path_length, 1),
        "ape_rmse": res.ape_trans["rmse"],
        "ape_mean": res.ape_trans["mean"],
        "ape_max": res.ape_trans["max"],
        "drift_pct": kitti.get("t_rel_pct"),
        "step_err_max": step_error(res.est_poses, res.gt_poses),
        "fps": m.get("frames_per_second"),
        "peak_mb": m.get("peak_memory_mb"),
        "degenerate": m.get("degenerate_frames"),
        "lost": (m.get("frontend_counts") or {}).get("tracking_lost"),
        "loops": m.get("loops_closed"),
        "sensor_model": m.get("sensor"),
    }


def _small_gicp(job: dict) -> dict:
    """small_gicp's scan-to-map odometry (``slam.bench.peers``) on the same scans."""
    from slam.bench.peers import small_gicp_odometry
    from slam.eval.metrics import EvalOptions, evaluate_arrays
    from slam.io.source import open_source
    from slam.io.trajectory import read_tum
    from slam.outputs import peak_memory_mb

    scans = []
    for s in open_source(job["bag"]):
        if hasattr(s, "xyz"):
            scans.append(s)
        if job["frames"] and len(scans) >= job["frames"]:
            break
    t0 = time.perf_counter()
    poses = np.stack(small_gicp_odometry(scans))
    fps = len(scans) / (time.perf_counter() - t0)
    gs, gp = read_tum(job["gt"])
    res = evaluate_arrays(np.array([s.stamp for s in scans]), poses, gs, gp, EvalOptions())
    return {
        "scene": job["scene"],
        "sensor": job["sensor"],
        "config": "small_gicp (reference)",
        "frames": len(scans),
        "path_m": round(res.path_length, 1),
        "ape_rmse": res.ape_trans["rmse"],
        "ape_mean": res.ape_trans["mean"],
        "ape_max": res.ape_trans["max"],
        "drift_pct": (res.kitti or {}).get("t_rel_pct"),
        "step_err_max": step_error(res.est_poses, res.gt_poses),
        "fps": round(fps, 2),
        "peak_mb": round(peak_memory_mb(), 1),
        "degenerate": None,
        "lost": None,
        "loops": None,
        "sensor_model": None,
    }


def calibrated(scene: str, sensor: str, draw: str | None):
    """The LiDAR model of ``scene`` with ``sensor`` and another draw of its per-beam
    calibration errors: None = the scene's own model (the default sequence), "ideal" = no
    calibration errors (everything else as the scene has it), an int = that
    ``calibration_seed``."""
    if draw is None:
        return None
    from dataclasses import replace

    from slam.sim.simulate import effective_model

    model = effective_model(scene, sensor=sensor)
    if draw == "ideal":
        return replace(model, calib_elevation_deg=0.0, calib_azimuth_deg=0.0, calib_range_m=0.0)
    return replace(model, calibration_seed=int(draw))


def _fmt(v, unit=""):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3f}{unit}" if abs(v) < 100 else f"{v:.0f}{unit}"
    return f"{v}{unit}"


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", nargs="+", default=["plaza"])
    ap.add_argument("--sensor", nargs="+", default=["vlp16"])
    ap.add_argument("--configs", nargs="+", default=["improved_floam", "floam"])
    ap.add_argument("--frames", type=int, help="first N frames only")
    ap.add_argument("--no-reference", action="store_true", help="skip small_gicp")
    ap.add_argument("--json", help="also write the rows here")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="KEY=V")
    ap.add_argument("--variant", nargs="+", default=[], help="LABEL:KEY=V[,KEY=V...]")
    ap.add_argument(
        "--calibration-seed",
        nargs="+",
        default=[],
        help="per-beam calibration draws of the sensor (int, or 'ideal' for none)",
    )
    return ap.parse_args()


def parse_variants(specs: list[str]) -> list[tuple[str, list[str]]]:
    """(label, overrides) of each ``LABEL:KEY=V[,KEY=V...]``; one unlabelled without any."""
    if not specs:
        return [("", [])]
    variants = []
    for v in specs:
        label, _, sets = v.partition(":")
        variants.append((label, [x for x in sets.split(",") if x]))
    return variants


def sequence_rows(scene: str, sensor: str, draw, args, variants, ctx, tmp: str) -> list[dict]:
    """Every config x variant (and small_gicp) on one simulated sequence, each in a fresh
    process; the rows print as they come."""
    from slam.sim.cache import ensure_sequence

    seq = ensure_sequence(
        scene, sensor=sensor, frames=args.frames, model=calibrated(scene, sensor, draw)
    )
    label = sensor if draw is None else f"{sensor} cal {draw}"
    base = {
        "scene": scene,
        "sensor": label,
        "bag": str(seq.bag),
        "gt": str(seq.ground_truth),
        "frames": args.frames,
    }
    jobs = [
        {
            **base,
            "config": c,
            "variant": vlabel,
            "overrides": args.overrides + sets,
            "out": f"{tmp}/{scene}-{sensor}-{draw}-{c}-{vlabel}",
        }
        for c in args.configs
        for vlabel, sets in variants
    ]
    rows = []
    for job in jobs:
        with ctx.Pool(1) as pool:
            rows.append(pool.apply(_run, (job,)))
        print(json.dumps(rows[-1]), flush=True)
    if not args.no_reference:
        with ctx.Pool(1) as pool:
            rows.append(pool.apply(_small_gicp, (base,)))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def print_table(rows: list[dict]) -> None:
    print(
        "| scene | sensor | front end | frames | APE RMSE / mean / max (m) | drift % "
        "| max step err (m) | frames/s | peak MiB | degenerate / lost | loops |"
    )
    print("|" + "---|" * 11)
    for r in rows:
        print(
            f"| {r['scene']} | {r['sensor']} | {r['config']} | {r['frames']} | "
            f"{_fmt(r['ape_rmse'])} / {_fmt(r['ape_mean'])} / {_fmt(r['ape_max'])} | "
            f"{_fmt(r['drift_pct'])} | {_fmt(r['step_err_max'])} | {_fmt(r['fps'])} | "
            f"{_fmt(r['peak_mb'])} | {_fmt(r['degenerate'])} / {_fmt(r['lost'])} | "
            f"{_fmt(r['loops'])} |"
        )


def main() -> None:
    args = parse_args()
    variants = parse_variants(args.variant)
    draws = list(args.calibration_seed) or [None]
    ctx = mp.get_context("spawn")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_scenes_") as tmp:
        for scene in args.scene:
            for sensor, draw in ((s, d) for s in args.sensor for d in draws):
                rows += sequence_rows(scene, sensor, draw, args, variants, ctx, tmp)
    print_table(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
