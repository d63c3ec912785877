"""``slam view``: a finished run's map, trajectories and loops in the Rerun viewer."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam.cli.common import EXIT_OK, eprint
from slam.errors import InputError


def add_parser(sub: Any) -> None:
    q = sub.add_parser("view", help="a finished run's map, trajectories and loops in Rerun")
    q.add_argument("run_dir", help="the --out folder of a run")
    q.add_argument("--viz", metavar="FILE.rrd", help="record to FILE.rrd instead of a viewer")
    q.set_defaults(func=cmd_view)


def cmd_view(args: argparse.Namespace) -> int:
    """A finished run's map, trajectories and loops in the Rerun viewer or an .rrd file."""
    from slam.viz.replay import replay_run
    from slam.viz.rerun_view import open_stream

    run_dir = Path(args.run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run folder not found: {run_dir}")
    rec = open_stream(args.viz)
    try:
        counts = replay_run(run_dir, rec)
    finally:
        rec.flush()
        rec.disconnect()
    eprint(
        f"{run_dir}: {counts['map_points']} map points, {counts['frames']} poses, "
        f"{counts['loops']} loops" + (f" recorded to {args.viz}" if args.viz else "")
    )
    return EXIT_OK
