"""Replay the visit graph (``slam.visit_graph``) over a finished 2D run: the front end's
own trajectory (``odometry.tum`` of a ``dpcr2d`` run, or the log's wheel odometry) and
the log's scans -> optimised scan poses -> the map's wall thickness (every 2nd scan
fused, ``slam.eval.map2d``), next to the run's own ``trajectory.tum``.

    .venv/bin/python benchmarks/visit_graph_replay.py LOG.clf.bz2 RUN_DIR [--frames N]
        [--set visit_scans=30 ...] [--out DIR]

The front end does not depend on the back end (graph feedback off), so the replay is the
pipeline with the visit graph as back end, without running the front end again.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
from bench_2d_real import load_log

from slam.eval.map2d import (
    fuse_scans,
    map_server_grid,
    view_directions,
    wall_thickness,
    windowed_floor,
)
from slam.eval.metrics import evaluate, evaluate_arrays, read_trajectory
from slam.mapping.grid2d import compose2d, matrix_to_pose2, pose2_to_matrix
from slam.visit_graph import (
    VisitGraphConfig,
    run_visit_graph,
    vertex_scans,
)
from slam.visit_refine import offset_stats, visit_offsets


def load_scans(
    log: Path, frames: int | None
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, np.ndarray]:
    """``bench_2d_real.load_log`` with the laser's mount on the robot as (x, y, theta)."""
    stamps, scans, odom, mount = load_log(log, frames)
    return stamps, scans, odom, matrix_to_pose2(mount)


def poses_at(path: Path, stamps: np.ndarray, mount: np.ndarray | None = None) -> np.ndarray:
    """(K, 3) poses of a TUM trajectory at ``stamps`` (every scan must be in it); with the
    laser's ``mount`` (x, y, theta on the robot) the laser's poses of the robot's in the
    file."""
    st, T = read_trajectory(path)
    order = np.argsort(st)
    st = np.asarray(st, dtype=np.float64)[order]
    pos = np.clip(np.searchsorted(st, stamps), 1, len(st) - 1)
    pos = np.where(np.abs(st[pos - 1] - stamps) < np.abs(st[pos] - stamps), pos - 1, pos)
    gap = np.abs(st[pos] - stamps)
    if gap.max() > 1e-3:
        raise SystemExit(f"{path}: no pose within 1 ms of stamp {stamps[np.argmax(gap)]:.6f}")
    poses = np.array([matrix_to_pose2(T[order[k]]) for k in pos])
    return poses if mount is None else np.array([compose2d(p, mount) for p in poses])


def walls(poses: np.ndarray, scans: list[np.ndarray], every: int = 2) -> dict:
    """Hits only (``fuse_scans``, one face at a time too) and on the probabilistic map as
    map_server reads it (``map_server_grid``: hits and misses, p > occupied_thresh)."""
    p, s = poses[::every], scans[::every]
    grid = fuse_scans(p, s)
    w = wall_thickness(grid)
    face = wall_thickness(grid, views=view_directions(grid, p, s))
    carved = wall_thickness(map_server_grid(p, s))
    return {"median": w.median, "p90": w.p90, "doubled": w.doubled,
            "face_median": face.median, "face_p90": face.p90,
            "carved_median": carved.median, "carved_p90": carved.p90,
            "carved_doubled": carved.doubled}  # fmt: skip


def parse_sets(items: list[str]) -> dict:
    types = {f.name: f.type for f in fields(VisitGraphConfig)}
    out = {}
    for item in items:
        k, v = item.split("=", 1)
        if k not in types:
            raise SystemExit(f"unknown visit_graph key {k}; valid: {', '.join(types)}")
        out[k] = int(v) if types[k] in ("int", int) else float(v)
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("run", type=Path, help="a dpcr2d run folder (odometry.tum, trajectory.tum)")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--wheels", action="store_true", help="start from the wheel odometry")
    ap.add_argument("--set", action="append", default=[], help="VisitGraphConfig key=value")
    ap.add_argument("--out", type=Path, default=None, help="write trajectory.tum + events")
    ap.add_argument("--skip-run-walls", action="store_true")
    ap.add_argument("--gt", type=Path, default=None, help="ground truth (TUM): APE RMSE")
    return ap.parse_args(argv)


def summary_row(vg, scans, cpu: float, poses, fe) -> dict:
    """Counts, timings and wall sharpness of the visit graph and of the front end."""
    acc = [e for e in vg.events if e.accepted]
    return {
        "scans": len(scans),
        "visits": len(vg.fe),
        "candidates": len(vg.events),
        "loops": len(acc),
        "ambiguous": sum(e.reason == "ambiguous" for e in vg.events),
        "cpu_s": cpu,
        "ms_per_scan": 1e3 * cpu / len(scans),
        "search_ms": float(np.mean(vg.search_ms)) if vg.search_ms else 0.0,
        "optimize_ms": float(np.mean(vg.optimize_ms)) if vg.optimize_ms else 0.0,
        "loop_corr_m_median": float(np.median([e.correction_m for e in acc])) if acc else 0.0,
        "refine": vg.refine_stats,
        "visit_graph": walls(poses, scans),
        "front_end": walls(fe, scans),
        "floor_50": walls(fe[:50], scans[:50], every=1)["median"],
    }


def add_window_floor(row: dict, fe, scans) -> None:
    """The front end's wall floor over windows of 50 scans, plain and carved."""
    floor = windowed_floor(fe[::2], scans[::2], window=50, every=1)
    carved = windowed_floor(fe[::2], scans[::2], window=50, every=1, carve=True)
    row["window_floor"] = floor.median
    row["window_floor_p90"] = floor.p90
    row["window_floor_carved"] = carved.median
    row["window_floor_carved_p90"] = carved.p90


def add_ape(row: dict, args: argparse.Namespace, stamps, poses, fe) -> None:
    """APE RMSE of the visit graph, the front end and the run against ``--gt``."""
    gs, gT = read_trajectory(args.gt)
    for name, P in [("visit_graph", poses), ("front_end", fe)]:
        ev = evaluate_arrays(stamps, np.stack([pose2_to_matrix(p) for p in P]), gs, gT)
        row[f"ape_rmse_{name}"] = ev.ape_trans["rmse"]
    if (args.run / "trajectory.tum").is_file():
        row["ape_rmse_run"] = evaluate(args.run / "trajectory.tum", args.gt).ape_trans["rmse"]


def write_outputs(out: Path, stamps, poses, vg, row: dict) -> None:
    """trajectory.tum, loops.csv (every candidate) and summary.json in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    with (out / "trajectory.tum").open("w") as fh:
        for s, p in zip(stamps, poses, strict=True):
            q = [0.0, 0.0, np.sin(p[2] / 2), np.cos(p[2] / 2)]
            fh.write(f"{s:.6f} {p[0]:.6f} {p[1]:.6f} 0 {q[0]} {q[1]} {q[2]:.9f} {q[3]:.9f}\n")
    with (out / "loops.csv").open("w") as fh:
        fh.write("new,old,score,uniqueness,inliers,correction_m,correction_deg,accepted,reason\n")
        for e in vg.events:
            row_ = [e.new, e.old, f"{e.score:.3f}", f"{e.uniqueness:.3f}", f"{e.inliers:.3f}",
                    f"{e.correction_m:.3f}", f"{e.correction_deg:.2f}", int(e.accepted),
                    e.reason]  # fmt: skip
            fh.write(",".join(map(str, row_)) + "\n")
    (out / "summary.json").write_text(json.dumps(row, indent=1))


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    stamps, scans, odom, mount = load_scans(args.log, args.frames)
    fe = odom if args.wheels else poses_at(args.run / "odometry.tum", stamps, mount)
    cfg = VisitGraphConfig(**parse_sets(args.set))
    t = time.process_time()
    poses, vg = run_visit_graph(fe, scans, cfg)
    cpu = time.process_time() - t
    row = summary_row(vg, scans, cpu, poses, fe)
    # how far each visit lies from the others where they see the same walls (m, its own
    # cloud registered on theirs), at the vertices of each trajectory
    anchors = vertex_scans(len(scans), cfg.visit_scans)
    clouds = [vg.loop_search.clouds[i] for i in range(len(anchors))]
    path = np.array([vg.loop_search.path[i] for i in range(len(anchors))])

    def offsets(P: np.ndarray) -> dict:
        return offset_stats(visit_offsets(P[anchors], clouds, path, cfg))

    row["visit_graph"]["offsets"] = offsets(poses)
    row["front_end"]["offsets"] = offsets(fe)
    if not args.skip_run_walls and (args.run / "trajectory.tum").is_file():
        run_poses = poses_at(args.run / "trajectory.tum", stamps, mount)
        row["run_trajectory"] = walls(run_poses, scans)
        row["run_trajectory"]["offsets"] = offsets(run_poses)
    add_window_floor(row, fe, scans)
    if args.gt is not None:
        add_ape(row, args, stamps, poses, fe)
    print(json.dumps(row, indent=1))
    if args.out is not None:
        write_outputs(args.out, stamps, poses, vg, row)


if __name__ == "__main__":
    main()
