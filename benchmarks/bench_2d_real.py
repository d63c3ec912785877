"""The 2D recipes on the real laser logs, scored by relations (Kuemmerle et al. 2009).

For every real CARMEN log (Intel, FR079, MIT-CSAIL in ``../shared/data/laser2d``) the
trajectories of ``icp2d``, ``dpcr2d``'s front end alone (``odometry.tum``), ``dpcr2d``
(the visit graph) and ``dpcr2d_regions`` (the paper's region graph) are scored against

- the log's self-consistency relations (``slam.eval.self_relations``: scan pairs 0.5 /
  1 / 2 m of path apart registered alone and verified, made once per log and prefix,
  cached as ``<out>/<log>_<frames>.relations``): a graph that worsens the local geometry
  the scans show is caught on every log;
- the log's revisit relations (``slam.eval.self_relations.revisit_relations``: a scan and
  the same place seen again at least 10 m of path later, proposed by the wheel odometry
  and every trajectory of the bench, registered from the two scans alone and verified,
  cached as ``<out>/<log>_<frames>_revisit.relations``): the long-range errors a wrong
  loop edge or drift around a loop makes, which short relations cannot see;
- published relations where given (``--relations intel=FILE``, Freiburg format).

``--beam-stride 2`` runs every log with every second beam (``slam.bench.degrade.
thin_carmen``): FR079 and MIT-CSAIL then scan as the 1 deg, 180-beam lasers of Intel and
the other older Freiburg logs (``--out`` should differ: the relations are made per scan set).

Printed: per log and trajectory the relation count and translation mean / std / median /
p90 / max / share above 0.2 m, rotation mean / p90, and the CPU time per scan of the run.

    .venv/bin/python benchmarks/bench_2d_real.py --out runs/bench_2d_real \
        [--logs intel fr079 mit-csail] [--frames 3000] [--methods icp2d dpcr2d dpcr2d_regions]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from slam.bench.degrade import skew_carmen_odometry, thin_carmen
from slam.config import load_config
from slam.eval.metrics import read_trajectory
from slam.eval.relations import (
    match_stamps,
    read_relations,
    relation_errors,
    relations_in_frame,
    write_relations,
)
from slam.eval.self_relations import SelfRelationConfig, revisit_relations, self_relations
from slam.io.carmen import CarmenSource, mount_matrix
from slam.run import run_one

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "laser2d"
LOGS = ("intel", "fr079", "mit-csail")
METHODS = ("icp2d", "dpcr2d", "dpcr2d_regions")


def load_log(
    log: Path, frames: int | None
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, np.ndarray]:
    """stamps (the log's own, as the trajectory files carry them), scans ((N, 2) within
    0.05-30 m, the laser's frame), wheel odometry (K, 3) of a CARMEN log, and the laser's
    mount on the robot (4x4: relations between scans -> between the robot's poses, the
    trajectory files' frame)."""
    stamps, scans, odom = [], [], []
    source = CarmenSource(log)
    for n, scan in enumerate(source):
        if frames is not None and n >= frames:
            break
        if not hasattr(scan, "xyz"):  # a damaged line
            continue
        xy = np.asarray(scan.xyz[:, :2], dtype=np.float64)
        r = np.linalg.norm(xy, axis=1)
        scans.append(xy[(r > 0.05) & (r < 30.0)])
        stamps.append(float(scan.stamp))
        odom.append(np.asarray(scan.odom, dtype=np.float64))
    mount = mount_matrix(source.mount)
    return source.output_stamps(np.array(stamps)), scans, np.array(odom), mount


def log_relations(log: Path, frames: int | None, out: Path) -> tuple[Path, dict]:
    """The log's self-consistency relations (made once, then read from the cache)."""
    path = out / f"{log.name.split('.')[0]}_{frames or 'all'}.relations"
    meta = path.with_suffix(".json")
    if path.is_file() and meta.is_file():
        return path, json.loads(meta.read_text())
    stamps, scans, odom, mount = load_log(log, frames)
    t = time.process_time()
    rel, stats = self_relations(stamps, scans, odom, SelfRelationConfig())
    rel = relations_in_frame(rel, mount)
    info = {"scans": len(stamps), "pairs": stats.pairs, "kept": stats.kept,
            "rejected": stats.rejected, "cpu_s": time.process_time() - t}  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    write_relations(path, rel, header=f"self-consistency relations of {log.name}: {info}")
    meta.write_text(json.dumps(info, indent=2))
    return path, info


def log_revisits(log: Path, frames: int | None, out: Path, trajs: list[Path]) -> tuple[Path, dict]:
    """The log's revisit relations, proposed by the wheels and ``trajs`` (made once)."""
    path = out / f"{log.name.split('.')[0]}_{frames or 'all'}_revisit.relations"
    meta = path.with_suffix(".json")
    if path.is_file() and meta.is_file():
        return path, json.loads(meta.read_text())
    stamps, scans, odom, mount = load_log(log, frames)
    proposers = [odom]
    for traj in trajs:
        st, T = read_trajectory(traj)
        k = np.maximum(match_stamps(st, stamps, 1e-3), 0)
        proposers.append(np.column_stack([T[k, 0, 3], T[k, 1, 3],
                                          np.arctan2(T[k, 1, 0], T[k, 0, 0])]))  # fmt: skip
    t = time.process_time()
    rel, stats = revisit_relations(stamps, scans, odom, proposers)
    rel = relations_in_frame(rel, mount)
    info = {"scans": len(stamps), "pairs": stats.pairs, "kept": stats.kept,
            "rejected": stats.rejected, "cpu_s": time.process_time() - t,
            "proposed_by": ["wheels"] + [str(p) for p in trajs]}  # fmt: skip
    write_relations(path, rel, header=f"revisit relations of {log.name}: {info}")
    meta.write_text(json.dumps(info, indent=2))
    return path, info


def score(traj: Path, relations: Path) -> dict:
    stamps, poses = read_trajectory(traj)
    summary = relation_errors(stamps, poses, read_relations(relations), max_dt=1e-3).summary()
    summary["n"] = summary.pop("relations")
    return summary


def run_method(method: str, log: Path, out: Path, frames: int | None, sets: list[str]) -> dict:
    """Run a recipe (reused when ``out`` holds a finished run); CPU ms per scan."""
    if not (out / "metrics.json").is_file():
        cfg = load_config(method, sets)
        cfg.source.max_frames = frames
        t = time.process_time()
        summary = run_one(log, cfg, out, quiet=True)
        cpu = (time.process_time() - t) / max(summary["frames"], 1) * 1e3
        (out / "bench.json").write_text(json.dumps({"cpu_ms_per_scan": cpu}))
    bench = out / "bench.json"
    return json.loads(bench.read_text()) if bench.is_file() else {}


def rows_of(log: str, args: argparse.Namespace, published: dict[str, Path]) -> list[dict]:
    path = Path(args.data) / f"{log}.clf.bz2"
    base = Path(args.out)
    if args.beam_stride > 1:  # the older 1 deg scanners, from a 0.5 deg log
        path = thin_carmen(path, base / "logs" / path.name, args.beam_stride)
    run_path = path  # the relations come from the log's own wheels, the runs from `run_path`
    if args.odom_skew:
        yaw, trans, noise = (float(v) for v in args.odom_skew.split(","))
        run_path = skew_carmen_odometry(
            path, base / "logs" / f"skewed_{path.name}", yaw, trans, noise, seed=0
        )
    rel, info = log_relations(path, args.frames, base)
    print(f"{log}: {info['kept']} self relations of {info['pairs']} pairs ({info['rejected']})")
    sets = {"published": published[log]} if log in published else {}
    sets["self"] = rel
    runs = []
    for method in args.methods:
        run_dir = base / log / method
        bench = run_method(method, run_path, run_dir, args.frames, args.set or [])
        if method.startswith("dpcr2d") and not any(r[0] == "dpcr2d front end" for r in runs):
            runs.append(("dpcr2d front end", run_dir / "odometry.tum", bench))
        runs.append((method, run_dir / "trajectory.tum", bench))
    rev, rev_info = log_revisits(path, args.frames, base, [r[1] for r in runs])
    print(f"{log}: {rev_info['kept']} revisit relations of {rev_info['pairs']} pairs")
    sets["revisit"] = rev
    rows = []
    for name, traj, bench in runs:
        for kind, rel_path in sets.items():
            rows.append({"log": log, "trajectory": name, "relations": kind, **bench,
                         **score(traj, rel_path)})  # fmt: skip
    return rows


def table(rows: list[dict]) -> str:
    head = ("| log | trajectory | relations | n | mean (m) | std | median | p90 | max | > 0.2 m "
            "| rot mean (deg) | rot p90 | CPU ms/scan |")  # fmt: skip
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        t, q = r["trans_m"], r["rot_deg"]
        lines.append(
            f"| {r['log']} | {r['trajectory']} | {r['relations']} | {r['n']} | "
            f"{t['mean']:.4f} | {t['std']:.4f} | {t['median']:.4f} | {t['p90']:.4f} | "
            f"{t['max']:.3f} | {100 * t['share_above_0.2m']:.1f} % | {q['mean']:.3f} | "
            f"{q['p90']:.3f} | {r.get('cpu_ms_per_scan', float('nan')):.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/bench_2d_real")
    ap.add_argument("--logs", nargs="+", default=list(LOGS), choices=LOGS)
    ap.add_argument("--data", default=str(DATA), help="folder of the CARMEN logs")
    ap.add_argument("--frames", type=int, help="first N scans of each log (default: all)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS))
    ap.add_argument("--relations", nargs="*", default=[], help="LOG=FILE published relations")
    ap.add_argument("--set", action="append", help="config override for every method")
    ap.add_argument(
        "--beam-stride", type=int, default=1, help="keep every N-th beam (2: 1 deg scanners)"
    )
    ap.add_argument(
        "--odom-skew",
        help="YAW_SCALE,TRANS_SCALE,YAW_NOISE_DEG: the runs read a worse wheel odometry "
        "(e.g. 0.05,0.03,0.2; the relations keep the log's own)",
    )
    args = ap.parse_args(argv)
    published = {k: Path(v) for k, v in (item.split("=", 1) for item in args.relations)}
    rows = []
    for log in args.logs:
        rows.extend(rows_of(log, args, published))
    print(table(rows))
    out = Path(args.out)
    (out / f"bench_{'_'.join(args.logs)}.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
