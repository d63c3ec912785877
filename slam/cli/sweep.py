"""``slam sweep``: a grid of config values over inputs, in parallel workers."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from slam.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    add_run_options,
    default_out_dir,
    eprint,
    gt_path,
)
from slam.errors import InputError


def add_parser(sub: Any) -> None:
    q = sub.add_parser("sweep", help="grid of config values over bags, in parallel workers")
    q.add_argument("bags", nargs="*", help="inputs (each with its --gt, in order)")
    q.add_argument("--gt", action="append", help="ground truth of each input, in order")
    q.add_argument("--scene", action="append", help="also sweep over a simulated scene")
    q.add_argument("--frames", type=int, help="truncate simulated scenes")
    q.add_argument("--grid", action="append", required=True, metavar="SECTION.KEY=V1,V2,...")
    q.add_argument("--config", help="base config (default improved_floam)")
    q.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    q.add_argument("--ray", metavar="ADDRESS", help="run on a Ray cluster (pip install ray)")
    add_run_options(q)
    q.set_defaults(func=cmd_sweep)


def _sweep_inputs(args: argparse.Namespace) -> list[tuple[str, str]]:
    """(input, ground truth) pairs: simulated --scene sequences, then BAG --gt GT pairs."""
    inputs: list[tuple[str, str]] = []
    if args.scene:
        from slam.sim.cache import ensure_sequence

        for scene in args.scene:
            seq = ensure_sequence(scene, frames=args.frames)
            inputs.append((str(seq.bag), str(seq.ground_truth)))
    bags, gts = args.bags or [], args.gt or []
    if len(bags) != len(gts):
        raise InputError(f"give one --gt per input: {len(bags)} inputs, {len(gts)} --gt")
    inputs += [(b, str(gt_path(g))) for b, g in zip(bags, gts, strict=True)]
    if not inputs:
        raise InputError("nothing to sweep over: give BAG --gt GT, or --scene corridor")
    return inputs


def cmd_sweep(args: argparse.Namespace) -> int:
    from slam.sweep import (
        check_jobs,
        format_rows,
        make_jobs,
        parse_grid,
        plot_heatmap,
        run_sweep,
        write_table,
    )

    inputs = _sweep_inputs(args)
    grid = parse_grid(args.grid)
    out = Path(args.out) if args.out else default_out_dir("sweep")
    jobs = make_jobs(inputs, grid, args.config or "improved_floam", out, args.set, args.max_frames)
    check_jobs(jobs)  # every grid value and ground truth, before the first run
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    with tqdm(
        total=len(jobs), unit="run", desc="sweep", disable=args.quiet, file=sys.stderr
    ) as bar:
        rows = run_sweep(
            jobs, workers=args.workers, ray_address=args.ray, on_done=lambda _row: bar.update(1)
        )
    write_table(rows, out / "sweep.csv")
    plot_heatmap(rows, grid, out / "sweep_heatmap.png")
    print(format_rows(rows))
    eprint(f"sweep table and heat map written to {out}/")
    failed = [r for r in rows if r.get("error")]
    for r in failed:
        eprint(f"failed: {r}")
    return EXIT_BAD_INPUT if failed and len(failed) == len(rows) else EXIT_OK
