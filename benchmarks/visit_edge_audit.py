"""Audit the visit graph's loop edges on a real log against the log's revisit relations.

For a finished ``dpcr2d`` run (``odometry.tum``, ``trajectory.tum``) the visit graph is
replayed over the front end's own trajectory with the run's chain information, and every
accepted loop edge (old visit j -> new visit i, z) is compared with what the revisit
relations (``slam.eval.self_relations.revisit_relations``: two scans registered alone)
say about the same pair of visits, composed through the front end inside each visit:

    z_rel = FE(a_j)^-1 FE(s1) R FE(s2)^-1 FE(a_i)     (s1 in visit j, s2 in visit i)

Printed: the edge's error against z_rel and the front end's (FE(a_j)^-1 FE(a_i)) against
it, mean vector (x, y in j's frame, theta) and norms: a systematic bias of the edges shows
as a mean far from zero or edge errors above the front end's.

    .venv/bin/python benchmarks/visit_edge_audit.py LOG.clf.bz2 RUN_DIR REVISIT.relations
        [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from bench_2d_real import load_log
from visit_graph_replay import parse_sets, poses_at

from slam.eval.relations import match_stamps, read_relations, relation_errors, relations_in_frame
from slam.mapping.grid2d import compose2d, inverse2d, matrix_to_pose2, pose2_to_matrix, wrap
from slam.visit_graph import VisitGraphConfig, run_visit_graph, vertex_scans

INFO_SCALE = 64.0  # frontends.dpcr2d_config.graph_info_scale: the chain of a pipeline run


def pipeline_config(**sets) -> VisitGraphConfig:
    """The visit graph as the ``dpcr2d`` recipe runs it (inliers 70 % / 5 cm, the chain at
    the front end's information: the planar model's sigmas / sqrt(64))."""
    k = np.sqrt(INFO_SCALE)
    base = dict(inlier_m=0.05, min_inliers=0.7, odom_sigma_m=0.02 / k, odom_sigma_per_m=0.02 / k,
                odom_sigma_deg=0.5 / k, odom_turn_fraction=0.02 / k)  # fmt: skip
    base.update(sets)
    return VisitGraphConfig(**base)


def score(stamps: np.ndarray, poses: np.ndarray, rel_path: Path) -> dict:
    T = np.stack([pose2_to_matrix(p) for p in poses])
    s = relation_errors(stamps, T, read_relations(rel_path), max_dt=1e-3).summary()
    return {"n": s["relations"], "mean_cm": 100 * s["trans_m"]["mean"],
            "median_cm": 100 * s["trans_m"]["median"], "rot_deg": s["rot_deg"]["mean"]}  # fmt: skip


def audit(stamps, fe, vg, anchors, cfg, rel_path: Path, mount: np.ndarray) -> list[dict]:
    """Per accepted loop edge and per revisit relation joining its two visits: the edge's
    and the front end's error against the relation's z (x, y in j's frame, theta); ``fe``
    the laser's poses, the relations (the robot's) moved to the laser by ``mount``."""
    rel = relations_in_frame(read_relations(rel_path), np.linalg.inv(mount))
    k1 = match_stamps(stamps, rel.t1, 1e-3)
    k2 = match_stamps(stamps, rel.t2, 1e-3)
    lo = np.r_[0, np.maximum(anchors[:-1] + 1 - cfg.pad, 0)]
    rows = []
    for j, i, z in vg.loops:
        in_j1 = (k1 >= lo[j]) & (k1 <= anchors[j])
        in_i2 = (k2 >= lo[i]) & (k2 <= anchors[i])
        in_i1 = (k1 >= lo[i]) & (k1 <= anchors[i])
        in_j2 = (k2 >= lo[j]) & (k2 <= anchors[j])
        for r in np.flatnonzero((in_j1 & in_i2) | (in_i1 & in_j2)):
            R = matrix_to_pose2(rel.poses[r])
            s1, s2 = k1[r], k2[r]
            if not in_j1[r]:  # relation from i to j: reversed
                s1, s2, R = s2, s1, inverse2d(R)
            z_rel = compose2d(compose2d(compose2d(inverse2d(fe[anchors[j]]), fe[s1]), R),
                              compose2d(inverse2d(fe[s2]), fe[anchors[i]]))  # fmt: skip
            z_fe = compose2d(inverse2d(fe[anchors[j]]), fe[anchors[i]])
            e_edge = compose2d(inverse2d(z_rel), z)
            e_fe = compose2d(inverse2d(z_rel), z_fe)
            rows.append({"j": int(j), "i": int(i), "edge": e_edge.tolist(), "fe": e_fe.tolist(),
                         "dist": float(np.hypot(*z[:2]))})  # fmt: skip
    return rows


def summarise(rows: list[dict]) -> dict:
    out = {"pairs": len(rows), "edges": len({(r["j"], r["i"]) for r in rows})}
    for key in ("edge", "fe"):
        e = np.array([r[key] for r in rows]).reshape(-1, 3)
        e[:, 2] = np.degrees(wrap(e[:, 2]))
        n = np.hypot(e[:, 0], e[:, 1])
        out[key] = {"mean_xy_cm": (100 * e[:, :2].mean(axis=0)).round(2).tolist(),
                    "mean_deg": round(float(e[:, 2].mean()), 3),
                    "norm_mean_cm": round(100 * float(n.mean()), 2),
                    "norm_median_cm": round(100 * float(np.median(n)), 2),
                    "abs_deg_mean": round(float(np.abs(e[:, 2]).mean()), 3)}  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("revisits", type=Path)
    ap.add_argument("--short", type=Path, default=None, help="short relations to score too")
    ap.add_argument("--set", action="append", default=[], help="VisitGraphConfig key=value")
    ap.add_argument("--rows", type=Path, default=None, help="write the per-pair rows (json)")
    args = ap.parse_args(argv)
    stamps, scans, _, mount = load_log(args.log, None)
    fe = poses_at(args.run / "odometry.tum", stamps)  # the robot's poses, as the files give
    m = matrix_to_pose2(mount)  # the scans are the laser's: the replay runs in its frame
    fe_laser = np.array([compose2d(p, m) for p in fe])
    cfg = pipeline_config(**parse_sets(args.set))
    replay, vg = run_visit_graph(fe_laser, scans, cfg)
    poses = np.array([compose2d(p, inverse2d(m)) for p in replay])
    anchors = vertex_scans(len(scans), cfg.visit_scans)
    report = {"loops": len(vg.loops), "gated_off": 0 if vg.gate is None else int(vg.gate.off.sum())}
    for name, P in (("front_end", fe), ("replay", poses),
                    ("run", poses_at(args.run / "trajectory.tum", stamps))):  # fmt: skip
        report[name] = {"revisit": score(stamps, P, args.revisits)}
        if args.short is not None:
            report[name]["short"] = score(stamps, P, args.short)
    rows = audit(stamps, fe_laser, vg, anchors, cfg, args.revisits, mount)
    report["audit"] = summarise(rows)
    print(json.dumps(report, indent=1, default=str))
    if args.rows is not None:
        args.rows.write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
