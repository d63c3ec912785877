"""``slam compare``: several recipes on one input; the papers' APE table."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam.cli.common import (
    EXIT_OK,
    add_run_options,
    apply_source_args,
    default_out_dir,
    eprint,
    exit_for_stop,
    gt_path,
)
from slam.run import compare

DEFAULT_COMPARE = ["floam", "improved_floam", "improved_floam_loop"]


def add_parser(sub: Any) -> None:
    q = sub.add_parser("compare", help="run several configs on one bag; the papers' APE table")
    q.add_argument("bag")
    q.add_argument("--gt", required=True, help="ground truth (TUM)")
    q.add_argument("--configs", nargs="+", help=f"configs (default: {' '.join(DEFAULT_COMPARE)})")
    add_run_options(q)
    q.set_defaults(func=cmd_compare)


def cmd_compare(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else default_out_dir("compare")
    res = compare(
        Path(args.bag),
        gt_path(args.gt),
        args.configs or DEFAULT_COMPARE,
        out,
        overrides=args.set,
        topic=args.topic,
        quiet=args.quiet,
        configure=lambda config: apply_source_args(config, args),
    )
    return report_compare(res, args.configs or DEFAULT_COMPARE)


def report_compare(
    res: dict[str, Any], configs: list[str], written: str = "table, plots and report"
) -> int:
    """Print the table of a comparison (``slam.run.compare``'s result) and say where its
    outputs are; for a run that stopped early, where its partial outputs are and which
    configs did not run. Returns the exit code (that of the stop: 130 for Ctrl-C)."""
    out = res["out"]
    if res["tables"]:
        print(res["tables"]["text"])
        eprint(f"{written} written to {out}/")
    else:
        eprint("no run was evaluated: no table")
    for name, error in res.get("eval_errors", {}).items():
        eprint(f"{name}: not in the table: {error}")
    for name, stop in res["stops"].items():
        if stop is None:
            continue
        run_dir = out / name
        kept = (
            f"; what it computed is in {run_dir}/" if (run_dir / "metrics.json").is_file() else ""
        )
        eprint(f"{name}: stopped early: {stop}{kept}")
        rest = configs[len(res["stops"]) :]
        if rest:
            eprint(f"not run: {' '.join(rest)}")
        return exit_for_stop(stop)
    return EXIT_OK
