"""``slam eval``: APE / RPE / KITTI metrics against ground truth, or Kuemmerle's relation
metric against a relations file."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from slam.cli.common import EXIT_OK, eprint, gt_path
from slam.errors import InputError


def add_parser(sub: Any) -> None:
    q = sub.add_parser("eval", help="APE/RPE/KITTI metrics of a trajectory against ground truth")
    q.add_argument("est")
    q.add_argument("gt", nargs="?", help="ground truth (TUM); or --relations")
    q.add_argument(
        "--relations",
        help="Freiburg relations (t1 t2 x y z roll pitch yaw): Kuemmerle's relation metric",
    )
    q.add_argument(
        "--calib",
        help="KITTI calib.txt whose Tr takes camera poses (GT a poses.txt) to the LiDAR frame "
        "(default: the calib.txt beside GT)",
    )
    q.add_argument("--max-dt", type=float, default=0.01, help="relation stamp match tolerance (s)")
    q.add_argument("--align", default="se3", choices=["se3", "sim3", "none"])
    q.add_argument("--n-align", type=int, default=-1, help="align on the first N poses only")
    q.add_argument("--out", help="write ape.json and plots here")
    q.set_defaults(func=cmd_eval)


def cmd_eval(args: argparse.Namespace) -> int:
    from slam.eval.ground_truth import evaluate_truth, kitti_truth_in_lidar, read_ground_truth
    from slam.eval.metrics import EvalOptions
    from slam.eval.tables import ape_table, format_table

    if args.relations:
        if args.gt:
            raise InputError("give either GT or --relations, not both")
        return _eval_relations(args)
    if not args.gt:
        raise InputError("slam eval EST GT (ground truth) or slam eval EST --relations FILE")
    options = EvalOptions(align=args.align, n_align=args.n_align)
    truth = kitti_truth_in_lidar(read_ground_truth(gt_path(args.gt)), args.calib)
    for line in truth.notes:
        eprint(line)
    for line in truth.warnings:
        eprint(f"warning: {line}")
    result = evaluate_truth(Path(args.est), truth, options)
    print(format_table(ape_table({Path(args.est).stem: result.ape_trans}), "text"))
    data = result.to_dict()
    for key in ("rpe_trans", "rpe_rot", "kitti"):
        if data.get(key):
            print(f"{key}: " + json.dumps(data[key]))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "ape.json").write_text(json.dumps(data, indent=2))
        from slam.eval.plots import plot_all

        plot_all(result, out / "plots")
        eprint(f"results written to {out}/")
    return EXIT_OK


def _eval_relations(args: argparse.Namespace) -> int:
    """``slam eval EST --relations FILE``: Kuemmerle's relation metric of a trajectory."""
    from slam.eval.metrics import read_trajectory
    from slam.eval.relations import format_summary, read_relations, relation_errors

    stamps, poses = read_trajectory(Path(args.est))
    if stamps is None:
        raise InputError(f"{args.est}: relations need stamps; give a TUM trajectory")
    errors = relation_errors(stamps, poses, read_relations(args.relations), args.max_dt)
    if not len(errors.trans):
        raise InputError(
            f"no relation of {args.relations} matches a stamp of {args.est} within "
            f"{args.max_dt} s: is it the trajectory of that log? (--max-dt widens the match)"
        )
    summary = errors.summary()
    print(format_summary(Path(args.est).stem, summary))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "relations.json").write_text(json.dumps(summary, indent=2))
        eprint(f"results written to {out}/relations.json")
    return EXIT_OK
