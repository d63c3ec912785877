"""``slam demo``: a simulated city drive with revisits, odometry only vs loop closed."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam.cli.common import default_out_dir, eprint, sim_progress, stop_code
from slam.cli.compare import report_compare
from slam.run import compare

# 1200 frames: 860 m of the city drive, the last 150 m back along the first street the
# other way (odometry 0.64 m APE RMSE, loop closed 0.15 m: see slam.viz.demo)
DEMO_SCENE, DEMO_FRAMES = "urban", 1200


def demo_frames(scene: str, frames: int | None) -> int | None:
    """The scans the demo simulates: ``frames`` when given (more than the scene has: the
    simulator's InputError); else the scene's whole drive (None) or its first DEMO_FRAMES
    scans when it is longer."""
    if frames is not None:
        return frames
    from slam.sim.simulate import effective_model, full_frames, make_scene

    world = make_scene(scene)  # ~0.1-0.4 s: the geometry, no scan
    return None if full_frames(world, effective_model(world)) <= DEMO_FRAMES else DEMO_FRAMES


def add_parser(sub: Any) -> None:
    q = sub.add_parser(
        "demo", help="simulate a city drive with revisits; odometry only vs loop closed"
    )
    q.add_argument(
        "--scene",
        default=DEMO_SCENE,
        help=f"a scene of `slam simulate` (default: {DEMO_SCENE}, a city drive with revisits)",
    )
    q.add_argument(
        "--frames",
        type=int,
        help=f"simulate the first N scans (default: the whole scene, at most {DEMO_FRAMES}: "
        f"which for {DEMO_SCENE} ends back on its first street)",
    )
    q.add_argument("--config", default="improved_floam_loop", help="a recipe with loop closure")
    q.add_argument("--configs", nargs="+", help="instead: the papers' table of these recipes")
    q.add_argument("--out")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate a drive with revisits (cached), run it with loop closure, print odometry only
    vs loop closed; with --configs, the papers' table of those recipes instead."""
    from slam.sim.cache import ensure_sequence
    from slam.viz.demo import run_demo

    out = Path(args.out) if args.out else default_out_dir("demo")
    eprint(f"simulating the '{args.scene}' sequence (cached after the first time)...")
    bar, progress = sim_progress(args.scene, args.quiet)
    try:
        seq = ensure_sequence(
            args.scene, frames=demo_frames(args.scene, args.frames), progress=progress
        )
    finally:
        bar.close()
    eprint(f"sequence: {seq.bag} ({seq.frames} scans), ground truth {seq.ground_truth}")
    if args.configs:
        res = compare(seq.bag, seq.ground_truth, args.configs, out, quiet=args.quiet)
        return report_compare(
            res, args.configs, "demo outputs (trajectories, maps, plots, report.html)"
        )
    demo = run_demo(seq.bag, seq.ground_truth, out, config=args.config, quiet=args.quiet)
    if demo.closed is None:
        eprint("the demo stopped before it had two frames to evaluate")
        return stop_code(demo.summary)
    print(demo.tables["text"])
    eprint(f"report (trajectories with the loops, the map before / after): {demo.report}")
    return stop_code(demo.summary)
