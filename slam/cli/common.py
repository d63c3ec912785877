"""What the sub-commands share: exit codes, stderr printing, the run options, output
folders and the exit code of a run that stopped early."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

from slam.errors import InputError

EXIT_OK, EXIT_FAIL, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


def eprint(*args: Any) -> None:
    """Print to stderr (stdout carries only tables and machine-readable output)."""
    print(*args, file=sys.stderr, flush=True)


def default_out_dir(config_name: str) -> Path:
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{config_name}"


def gt_path(path: str | None) -> Path | None:
    """The ground-truth file of ``--gt`` / ``GT``, checked to exist."""
    if path is None:
        return None
    gt = Path(path)
    if not gt.is_file():
        raise InputError(f"ground-truth file not found: {gt}")
    return gt


def add_run_options(q: argparse.ArgumentParser) -> None:
    """The options of every command that runs a recipe on an input (run, compare, sweep)."""
    q.add_argument("--topic", help="point-cloud topic (default: the only one in the bag)")
    q.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a config value, e.g. --set frontend.sor.k=8",
    )
    q.add_argument("--out", help="output folder (default: runs/<time>-<config>)")
    q.add_argument("--start", type=int, metavar="N", help="start at input message N (0-based)")
    q.add_argument("--max-frames", type=int, metavar="M", help="stop after M frames")
    q.add_argument(
        "--strict",
        action="store_true",
        help="stop (exit 2) at the first damaged message or bad stamp instead of "
        "skipping and counting it",
    )
    q.add_argument(
        "--stamps",
        choices=("auto", "header", "record"),
        default=None,
        help="the clock of a scan: the header stamp, the bag's record time, or auto "
        "(default: the header stamp unless it does not increase, then the record time)",
    )
    q.add_argument("--quiet", action="store_true", help="no progress bar")


def apply_source_args(config: Any, args: argparse.Namespace) -> None:
    """--start / --max-frames / --strict / --stamps into the config's source section
    (validated)."""
    src = config.source
    config.source = dataclasses.replace(
        src,
        start=args.start if args.start is not None else src.start,
        max_frames=args.max_frames if args.max_frames is not None else src.max_frames,
        strict=bool(args.strict) or src.strict,
        stamps=getattr(args, "stamps", None) or src.stamps,
    )


def stop_code(summary: dict[str, Any]) -> int:
    """0 for a run that finished; else say why it stopped and return its exit code."""
    stop = summary.get("stop")
    if stop is None:
        return EXIT_OK
    eprint(f"run stopped early: {stop}; everything computed so far is in {summary['out']}/")
    return exit_for_stop(stop)


def exit_for_stop(stop: Any) -> int:
    """130 for Ctrl-C, 1 for a back-end failure, 2 for input that could not be read."""
    from slam.state import StopReason

    return {
        StopReason.INTERRUPTED: EXIT_INTERRUPTED,
        StopReason.BACKEND_FAILED: EXIT_FAIL,
        StopReason.BAD_INPUT: EXIT_BAD_INPUT,
    }[stop.reason]


def sim_progress(scene: str, quiet: bool = False) -> tuple[Any, Any]:
    """A progress bar of a simulation and its ``progress(done, total)`` callback."""
    from tqdm import tqdm

    bar = tqdm(
        unit="scan",
        desc=f"simulate {scene}",
        file=sys.stderr,
        dynamic_ncols=True,
        disable=quiet,
        mininterval=0.1 if sys.stderr.isatty() else 10.0,
    )

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)

    return bar, progress
