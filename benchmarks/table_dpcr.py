"""Paper 003's tables: (1) the region-width study (Table 1) and (2) DPCR-SLAM vs a baseline
2D pipeline (Table 2; the paper's baseline is Cartographer, ours is ``frontends.icp2d``:
scan-to-submap ICP with an iSAM2 pose graph of every 5th scan).

(1) On a simulated multi-room scene with ground truth (rooms2d, 2 laps at 1 m/s, a poor
wheel odometry: 3 % slip, 0.5 deg/sqrt(m) heading walk), ``dpcr2d_regions`` (the paper's
region graph; ``dpcr2d`` has the visit graph as back end) for each region width
S: number of regions, map storage (bytes of the stored grids: regional maps), processing
time per scan (ms, the front end's ``total_ms``), graph optimisation time (ms per
optimisation, the region graph's ``stats()``), LocErr_ave (eq. 17: the mean of the
largest 10 % of the aligned position errors) and the APE RMSE.

(2) DPCR (S = 4 m) and the baseline on the same scene and on the first ``--real-frames``
scans of the real FR079 and Intel logs (no ground truth there): storage, time per scan,
graph time, and the map consistency: the wall thickness (``slam.eval.map2d``) of a grid
fused from every 2nd scan at the final trajectory. Speeds are a ratio to the baseline
measured in the same run (the machine is shared; absolute ms are noisy).

    .venv/bin/python benchmarks/table_dpcr.py --out runs/table_dpcr [--real-frames 1500]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from slam.config import load_config
from slam.eval.map2d import (
    fuse_scans,
    map_server_grid,
    view_directions,
    wall_thickness,
    windowed_floor,
)
from slam.eval.metrics import read_trajectory
from slam.io.carmen import CarmenSource
from slam.run import run_one
from slam.sim.floorplan2d import simulate2d, wheel_odometry, write_sequence

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "laser2d"
WIDTHS = (3.0, 4.0, 5.0, 6.0, 8.0, 10.0)


def loc_err_ave(errors: np.ndarray, share: float = 0.1) -> float:
    """LocErr_ave (paper 003, eq. 17): mean of the largest ``share`` of the position
    errors (m)."""
    e = np.sort(np.asarray(errors, dtype=np.float64))[::-1]
    return float(e[: max(1, int(np.ceil(share * len(e))))].mean())


def scene(out: Path, plan: str = "rooms2d", laps: float = 2.0) -> tuple[Path, Path]:
    seq = simulate2d(plan, speed=1.0, laps=laps, seed=1)
    odo = wheel_odometry(seq.poses, slip=0.03, yaw_slip=0.05, heading_deg_per_sqrt_m=0.5)
    return write_sequence(seq, out / plan, odo)


def map_consistency(
    log: Path, run_dir: Path, max_frames: int | None, every: int = 2, first: int | None = None
) -> dict:
    """Wall thickness of all (every ``every``-th) scans fused at ``trajectory.tum``;
    ``first``: only the first scans (the floor: sensor noise and clutter, no revisits)."""
    stamps, T = read_trajectory(run_dir / "trajectory.tum")
    by_stamp = {round(float(s), 4): k for k, s in enumerate(stamps)}
    poses, scans = [], []
    for n, scan in enumerate(CarmenSource(log)):
        if (max_frames is not None and n >= max_frames) or (first is not None and n >= first):
            break
        k = by_stamp.get(round(float(scan.stamp), 4))
        if k is None or n % every:
            continue
        xy = np.asarray(scan.xyz[:, :2], dtype=np.float64)
        r = np.linalg.norm(xy, axis=1)
        scans.append(xy[(r > 0.05) & (r < 30.0)])
        poses.append([T[k][0, 3], T[k][1, 3], np.arctan2(T[k][1, 0], T[k][0, 0])])
    poses = np.array(poses)
    grid = fuse_scans(poses, scans)
    w = wall_thickness(grid)
    side = wall_thickness(grid, views=view_directions(grid, poses, scans))  # one face at a time
    carved = wall_thickness(map_server_grid(poses, scans))  # the map as map_server reads it
    out = {"wall_median_m": w.median, "wall_p90_m": w.p90, "wall_doubled": w.doubled,
           "wall_face_median_m": side.median, "wall_face_p90_m": side.p90,
           "wall_face_doubled": side.doubled, "wall_carved_median_m": carved.median,
           "wall_carved_p90_m": carved.p90, "wall_carved_doubled": carved.doubled}  # fmt: skip
    if first is None and len(poses) >= 50:  # every window of 100 scans (50 fused) alone
        floor = windowed_floor(poses, scans, window=50, every=1)
        out.update(wall_window_floor_m=floor.median, wall_window_floor_p90_m=floor.p90)
        floor = windowed_floor(poses, scans, window=50, every=1, carve=True)
        out.update(wall_window_floor_carved_m=floor.median)
    return out


def run(
    config: str,
    log: Path,
    out: Path,
    sets: list[str],
    gt: Path | None = None,
    max_frames: int | None = None,
    consistency: bool = False,
) -> dict:
    cfg = load_config(config, sets)
    if max_frames is not None:
        cfg.source.max_frames = max_frames
    t0 = time.perf_counter()
    summary = run_one(log, cfg, out, gt=gt, quiet=True)
    wall = time.perf_counter() - t0
    pipe = summary["pipeline"]
    metrics = json.loads((out / "metrics.json").read_text())
    means = metrics["frontend_means"]
    storage = pipe.frontend.storage_bytes()
    stats_of = getattr(pipe.backend, "stats", None)
    backend_ms = np.asarray(pipe.state.backend_seconds) * 1e3
    row: dict = {
        "frames": summary["frames"],
        "keyframes": summary["keyframes"],
        "ms_per_scan": means.get("total_ms", float("nan")),
        "wall_s": wall,
        "storage_bytes": storage.get("regional_maps", storage.get("keyframe_clouds", 0))
        + storage.get("visit_clouds", 0),
        "submap_bytes": storage.get("submap", 0),
        "regions": len(getattr(pipe.frontend, "regions", {})),
    }
    counts = getattr(pipe.frontend, "counts", {})
    row.update({k: counts[k] for k in ("revisit_searches", "reanchored") if k in counts})
    st = stats_of() if stats_of is not None else {}
    if "optimize_mean_ms" in st:  # the region graph
        row.update(graph_ms=st["optimize_mean_ms"], optimizations=int(st["optimizations"]))
    else:  # iSAM2: one update per keyframe
        row.update(graph_ms=float(np.mean(backend_ms)) if len(backend_ms) else float("nan"))
        row.update(optimizations=len(backend_ms))
    ev = summary.get("eval")
    if ev is not None:
        row.update(ape_rmse=ev.ape_trans["rmse"], loc_err_ave=loc_err_ave(ev.ape_errors))
    if consistency:
        row.update(map_consistency(log, out, max_frames))
        floor = map_consistency(log, out, max_frames, every=1, first=50)
        row["wall_floor_m"] = floor["wall_median_m"]
        row["wall_face_floor_m"] = floor["wall_face_median_m"]
    return row


def _md(rows: list[dict], cols: list[tuple[str, str, str]]) -> str:
    head = "| " + " | ".join(c[1] for c in cols) + " |"
    sep = "|" + "|".join("---" for _ in cols) + "|"
    body = []
    for r in rows:
        body.append("| " + " | ".join(format(r.get(k, float("nan")), f) for k, _, f in cols) + " |")
    return "\n".join([head, sep, *body])


WIDTH_COLUMNS = [
    ("S", "S (m)", "g"),
    ("regions", "regions", "d"),
    ("storage_bytes", "storage (bytes)", ",d"),
    ("ms_per_scan", "time/scan (ms)", ".1f"),
    ("graph_ms", "graph (ms/opt.)", ".1f"),
    ("optimizations", "opt.", "d"),
    ("loc_err_ave", "LocErr_ave (m)", ".3f"),
    ("ape_rmse", "APE RMSE (m)", ".3f"),
]
COMPARE_COLUMNS = [
    ("input", "input", "s"),
    ("method", "method", "s"),
    ("frames", "scans", "d"),
    ("storage_bytes", "map storage (bytes)", ",d"),
    ("ms_per_scan", "time/scan (ms)", ".1f"),
    ("speed_vs_baseline", "speed vs baseline", ".2f"),
    ("graph_ms", "graph (ms/opt.)", ".1f"),
    ("optimizations", "opt.", "d"),
    ("wall_median_m", "wall median (m)", ".3f"),
    ("wall_p90_m", "wall p90 (m)", ".3f"),
    ("wall_doubled", "walls > 15 cm", ".2f"),
    ("wall_floor_m", "first 50 scans (m)", ".3f"),
    ("wall_window_floor_m", "windows of 100 (m)", ".3f"),
    ("wall_face_median_m", "face median (m)", ".3f"),
    ("wall_face_p90_m", "face p90 (m)", ".3f"),
    ("wall_face_doubled", "faces > 15 cm", ".2f"),
    ("wall_face_floor_m", "face, first 50 (m)", ".3f"),
    ("wall_carved_median_m", "map_server median (m)", ".3f"),
    ("wall_carved_p90_m", "map_server p90 (m)", ".3f"),
    ("wall_window_floor_carved_m", "map_server windows (m)", ".3f"),
    ("ape_rmse", "APE RMSE (m)", ".3f"),
    ("loc_err_ave", "LocErr_ave (m)", ".3f"),
]
METHODS = {  # --methods: (config, label, overrides)
    "dpcr": ("dpcr2d_regions", "DPCR", []),  # the paper's region graph
    "visit": ("dpcr2d", "DPCR visit graph", []),  # the default
    "icp": ("configs/icp2d.yaml", "ICP baseline", []),
}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("runs/table_dpcr"))
    ap.add_argument("--plan", default="rooms2d")
    ap.add_argument("--widths", type=float, nargs="*", default=list(WIDTHS))
    ap.add_argument("--real-frames", type=int, default=1500, help="0: the whole logs")
    ap.add_argument("--real", nargs="*", default=["fr079", "intel"])
    ap.add_argument("--skip-width", action="store_true")
    ap.add_argument("--skip-compare", action="store_true")
    ap.add_argument("--skip-sim", action="store_true", help="Table 2 on the real logs only")
    ap.add_argument("--methods", nargs="*", default=["dpcr", "icp"],
                    help="Table 2 methods: dpcr, visit (dpcr2d + visit graph), icp")  # fmt: skip
    return ap.parse_args(argv)


def width_rows(widths: list[float], log: Path, gt, out: Path) -> list[dict]:
    """The region graph at every region width S on the simulated log."""
    rows = []
    for S in widths:
        sets = [f"frontend.region_width={S}", f"factors.region_edges.region_width={S}"]
        r = run("dpcr2d_regions", log, out / f"width_{S:g}", sets, gt=gt)
        rows.append({"S": S, **r})
        print(f"S={S}: {r}", flush=True)
    return rows


def compare_rows(args: argparse.Namespace, log: Path, gt, out: Path) -> list[dict]:
    """Table 2: every method on the simulated log and the real ones; speed vs ICP."""
    rows = []
    inputs = [] if args.skip_sim else [(args.plan, log, gt, None)]
    frames = args.real_frames or None  # 0: the whole log
    inputs += [(n, DATA / f"{n}.clf.bz2", None, frames) for n in args.real]
    for name, path, truth, frames in inputs:
        for m in args.methods:
            config, label, sets = METHODS[m]
            r = run(config, path, out / f"{name}_{m}", sets, truth, frames, True)
            rows.append({"input": name, "method": label, **r})
            print(f"{name} {label}: {r}", flush=True)
        if "icp" in args.methods and len(args.methods) > 1:
            mine = rows[-len(args.methods) :]
            base = mine[args.methods.index("icp")]
            for r in mine:
                r["speed_vs_baseline"] = base["ms_per_scan"] / r["ms_per_scan"]
    return rows


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    log, gt = scene(out / "scene", args.plan)
    results: dict = {}
    if not args.skip_width:
        results["width"] = width_rows(args.widths, log, gt, out)
        print(_md(results["width"], WIDTH_COLUMNS))
    if not args.skip_compare:
        results["compare"] = compare_rows(args, log, gt, out)
        print(_md(results["compare"], COMPARE_COLUMNS))
    (out / "table_dpcr.json").write_text(json.dumps(results, indent=2, default=float))


if __name__ == "__main__":
    main()
