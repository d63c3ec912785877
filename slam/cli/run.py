"""``slam run``: one recipe on one input, with a summary of what came out."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from slam.cli.common import (
    add_run_options,
    apply_source_args,
    default_out_dir,
    eprint,
    gt_path,
    stop_code,
)


def add_parser(sub: Any) -> None:
    q = sub.add_parser("run", help="run SLAM on a bag / KITTI folder / PCD folder")
    q.add_argument("bag")
    q.add_argument("--config", default=None, help="config name in configs/ or a YAML path")
    q.add_argument("--no-loop", action="store_true", help="switch loop closure off")
    q.add_argument(
        "--gt",
        help="ground truth to evaluate against: TUM, or KITTI rows (a KITTI sequence's "
        "poses are taken to the LiDAR frame with its calib.txt)",
    )
    q.add_argument(
        "--viz",
        nargs="?",
        const="",
        metavar="FILE.rrd",
        help="live view in the Rerun viewer (pip install 'pyslam-graph[viz]'); "
        "with FILE.rrd: record the same stream to a file (no display needed)",
    )
    add_run_options(q)
    q.set_defaults(func=cmd_run)


def cmd_run(args: argparse.Namespace) -> int:
    from slam.config import load_config
    from slam.run import disable_loops, run_one

    config = load_config(args.config, args.set)
    apply_source_args(config, args)
    if args.no_loop:
        disable_loops(config)
    out = Path(args.out) if args.out else default_out_dir(config.name)
    observers = []
    if args.viz is not None:  # "" (bare --viz): a viewer on this display; else an .rrd file
        from slam.viz.rerun_view import viz_observer

        observers.append(viz_observer(args.viz))
    try:
        summary = run_one(
            Path(args.bag),
            config,
            out,
            topic=args.topic,
            gt=gt_path(args.gt),
            quiet=args.quiet,
            observers=observers,
        )
    finally:
        for obs in observers:
            obs.close()
    print_run_summary(summary)
    if args.viz:
        eprint(f"live view recorded to {args.viz} (open it with: rerun {args.viz})")
    return stop_code(summary)


def print_run_summary(summary: dict[str, Any]) -> None:
    """Frames, loops, speed, memory, input notes, skipped messages, tracking, degenerate
    frames or an empty map, how the ground truth was taken and APE."""
    out = summary["out"]
    metrics = json.loads((out / "metrics.json").read_text())
    fps = metrics.get("frames_per_second")
    eprint(
        f"{summary['frames']} frames, {summary['keyframes']} keyframes, "
        f"{metrics.get('loops_closed', 0)} loop factors, {fps} frames/s, "
        f"peak memory {metrics.get('peak_memory_mb')} MiB"
    )
    if metrics.get("sensor"):
        eprint(f"sensor: {metrics['sensor']}")
    share = (metrics.get("frontend_means") or {}).get("layout_time_deskewed")
    if share:
        eprint(
            "note: the clouds carry no time field and are not motion-compensated: "
            f"deskewed with times from the azimuth ({100 * share:.0f} % of frames)"
        )
    for note in summary.get("input_notes") or []:
        eprint(f"note: {note}")
    skipped = summary.get("skipped_messages") or {}
    if skipped:
        eprint(
            f"skipped {sum(skipped.values())} input messages: "
            + ", ".join(f"{n} {reason}" for reason, n in sorted(skipped.items()))
        )
    counts = metrics.get("frontend_counts") or {}
    if counts.get("tracking_lost") or counts.get("rejected"):
        eprint(
            f"tracking: {counts.get('rejected', 0)} implausible registrations rejected, "
            f"{counts.get('tracking_lost', 0)} frames lost (prediction kept, not mapped), "
            f"{counts.get('recovered', 0)} recoveries"
        )
    if warning := degenerate_warning(metrics, summary):
        eprint(f"warning: {warning}")
    if warning := along_road_warning(metrics):
        eprint(f"warning: {warning}")
    fe = summary["system"].config.frontend if "system" in summary else {}
    learns = (fe.get("beam_calibration") or {}).get("enabled", False)
    if line := open_road_line(metrics, fe.get("name") == "improved_floam" and not learns):
        eprint(line)
    for note in summary.get("gt_notes") or []:
        eprint(f"note: {note}")
    for warning in summary.get("gt_warnings") or []:
        eprint(f"warning: {warning}")
    if "eval" in summary:
        ape = summary["eval"].ape_trans
        eprint(
            "APE translation [m]: "
            + "  ".join(f"{k} {ape[k]:.4f}" for k in ("rmse", "mean", "median", "max") if k in ape)
        )
    eprint(f"outputs written to {out}/")


def along_road_warning(metrics: dict[str, Any]) -> str | None:
    """One line when most scans' features ran along one horizontal direction (an open road,
    ``slam.features.scatter``) and the front end registered nothing else (its open-road
    mode set to ``never``); else None."""
    means = metrics.get("frontend_means") or {}
    share = means.get("along_road") or 0.0
    if share <= 0.5 or means.get("scatter_points"):
        return None
    return (
        f"the features of {100 * share:.0f} % of the scans run along one direction (an open "
        "road): the odometry may fall behind the motion along it; on motorways and country "
        "roads leave frontend.scatter.mode at auto or use --config improved_floam_open_road "
        "(docs/robustness.md)"
    )


def open_road_line(metrics: dict[str, Any], recipe_hint: bool = False) -> str | None:
    """One line saying for what share of the scans the front end's open-road mode was on
    (``frontend.scatter.mode``); None when it never was. ``recipe_hint`` (improved_floam
    without the beams' calibration): where the mode was on for most scans, the line names
    the open-road recipe, which also learns the beams' angles (docs/robustness.md)."""
    share = (metrics.get("frontend_means") or {}).get("open_road") or 0.0
    if share <= 0:
        return None
    line = (
        f"open road: the front end also registered the points its features leave out on "
        f"{100 * share:.0f} % of the scans (frontend.scatter.mode; docs/robustness.md)"
    )
    if recipe_hint and share > 0.5:
        line += (
            "; for open roads --config improved_floam_open_road also learns each beam's "
            "angle offsets, which turn the attitude over long straight stretches"
        )
    return line


def degenerate_warning(metrics: dict[str, Any], summary: dict[str, Any]) -> str | None:
    """One line when frames were degenerate (registration unconstrained along some
    direction) or the map came out empty though one was asked for; else None."""
    parts = []
    frames = metrics.get("frames") or summary.get("frames") or 0
    degenerate = metrics.get("degenerate_frames") or 0
    if degenerate:
        parts.append(
            f"{degenerate} of {frames} frames were degenerate (the scans constrain the "
            "motion poorly along some direction: a corridor, an open field)"
        )
    system = summary.get("system")
    wants_map = system is None or system.config.output.write_map
    if wants_map and frames and not metrics.get("map_points"):
        parts.append("the map is empty (no keyframe was mapped, or none kept a point)")
    return "; ".join(parts) or None
