"""The ``slam`` command: one entry point, sub-commands. Only this module prints and exits.

Exit codes: 0 ok, 1 unexpected failure, 2 bad input or config, 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from slam.errors import ConfigError, InputError, SlamError
from slam.run import compare

EXIT_OK, EXIT_FAIL, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
DEFAULT_COMPARE = ["floam", "improved_floam", "improved_floam_loop"]
# 1200 frames: 860 m of the city drive, the last 150 m back along the first street the
# other way (odometry 0.64 m APE RMSE, loop closed 0.15 m: see slam.viz.demo)
DEMO_SCENE, DEMO_FRAMES = "urban", 1200

log = logging.getLogger("slam")


def _eprint(*args: Any) -> None:
    print(*args, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- running


def default_out_dir(config_name: str) -> Path:
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{config_name}"


def _print_run_summary(summary: dict[str, Any]) -> None:
    out = summary["out"]
    metrics = json.loads((out / "metrics.json").read_text())
    fps = metrics.get("frames_per_second")
    _eprint(
        f"{summary['frames']} frames, {summary['keyframes']} keyframes, "
        f"{metrics.get('loops_closed', 0)} loop factors, {fps} frames/s, "
        f"peak memory {metrics.get('peak_memory_mb')} MiB"
    )
    if metrics.get("sensor"):
        _eprint(f"sensor: {metrics['sensor']}")
    for note in summary.get("input_notes") or []:
        _eprint(f"note: {note}")
    skipped = summary.get("skipped_messages") or {}
    if skipped:
        _eprint(
            f"skipped {sum(skipped.values())} input messages: "
            + ", ".join(f"{n} {reason}" for reason, n in sorted(skipped.items()))
        )
    counts = metrics.get("frontend_counts") or {}
    if counts.get("tracking_lost") or counts.get("rejected"):
        _eprint(
            f"tracking: {counts.get('rejected', 0)} implausible registrations rejected, "
            f"{counts.get('tracking_lost', 0)} frames lost (prediction kept, not mapped), "
            f"{counts.get('recovered', 0)} recoveries"
        )
    if "eval" in summary:
        ape = summary["eval"].ape_trans
        _eprint(
            "APE translation [m]: "
            + "  ".join(f"{k} {ape[k]:.4f}" for k in ("rmse", "mean", "median", "max") if k in ape)
        )
    _eprint(f"outputs written to {out}/")


def _stop_code(summary: dict[str, Any]) -> int:
    stop = summary.get("stop")
    if stop is None:
        return EXIT_OK
    _eprint(f"run stopped early: {stop}; everything computed so far is in {summary['out']}/")
    return _exit_for_stop(stop)


def _exit_for_stop(stop: Any) -> int:
    """130 for Ctrl-C, 1 for a back-end failure, 2 for input that could not be read."""
    from slam.state import StopReason

    return {
        StopReason.INTERRUPTED: EXIT_INTERRUPTED,
        StopReason.BACKEND_FAILED: EXIT_FAIL,
        StopReason.BAD_INPUT: EXIT_BAD_INPUT,
    }[stop.reason]


def apply_source_args(config: Any, args: argparse.Namespace) -> None:
    """--start / --max-frames / --strict / --stamps into the config's source section
    (validated)."""
    import dataclasses

    src = config.source
    config.source = dataclasses.replace(
        src,
        start=args.start if args.start is not None else src.start,
        max_frames=args.max_frames if args.max_frames is not None else src.max_frames,
        strict=bool(args.strict) or src.strict,
        stamps=getattr(args, "stamps", None) or src.stamps,
    )


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
            gt=_gt(args.gt),
            quiet=args.quiet,
            observers=observers,
        )
    finally:
        for obs in observers:
            obs.close()
    _print_run_summary(summary)
    if args.viz:
        _eprint(f"live view recorded to {args.viz} (open it with: rerun {args.viz})")
    return _stop_code(summary)


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
    _eprint(
        f"{run_dir}: {counts['map_points']} map points, {counts['frames']} poses, "
        f"{counts['loops']} loops" + (f" recorded to {args.viz}" if args.viz else "")
    )
    return EXIT_OK


def _gt(path: str | None) -> Path | None:
    if path is None:
        return None
    gt = Path(path)
    if not gt.is_file():
        raise InputError(f"ground-truth file not found: {gt}")
    return gt


# --------------------------------------------------------------------------- compare


def cmd_compare(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else default_out_dir("compare")
    res = compare(
        Path(args.bag),
        _gt(args.gt),
        args.configs or DEFAULT_COMPARE,
        out,
        overrides=args.set,
        topic=args.topic,
        quiet=args.quiet,
        configure=lambda config: apply_source_args(config, args),
    )
    print(res["tables"]["text"])
    _eprint(f"table, plots and report written to {out}/")
    for name, stop in res["stops"].items():
        if stop is not None:
            _eprint(f"{name}: stopped early: {stop}")
            return _exit_for_stop(stop)
    return EXIT_OK


# --------------------------------------------------------------------------- other commands


def _sim_progress(scene: str, quiet: bool = False) -> tuple[Any, Any]:
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


def cmd_simulate(args: argparse.Namespace) -> int:
    from slam.sim.floorplan2d import PLANS, simulate2d, write_sequence
    from slam.sim.simulate import simulate

    if args.scene in PLANS:  # 2D laser in a floor plan: a CARMEN log + ground truth
        seq = simulate2d(args.scene, frames=args.frames, seed=args.seed)
        log, gt = write_sequence(seq, Path(args.out))
        _eprint(f"wrote {len(seq.stamps)} 2D laser scans to {log} and ground truth to {gt}")
        return EXIT_OK

    bar, progress = _sim_progress(args.scene)

    try:
        res = simulate(
            args.scene,
            Path(args.out),
            frames=args.frames,
            fmt=args.format,
            seed=args.seed,
            pedestrians=not args.no_pedestrians,
            sensor=args.sensor,
            progress=progress,
        )
    finally:
        bar.close()
    _eprint(f"wrote {res.frames} scans to {res.bag} and ground truth to {res.ground_truth}")
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
        _eprint(f"results written to {out}/relations.json")
    return EXIT_OK


def cmd_eval(args: argparse.Namespace) -> int:
    from slam.eval.metrics import EvalOptions, evaluate
    from slam.eval.tables import ape_table, format_table

    if args.relations:
        if args.gt:
            raise InputError("give either GT or --relations, not both")
        return _eval_relations(args)
    if not args.gt:
        raise InputError("slam eval EST GT (ground truth) or slam eval EST --relations FILE")
    options = EvalOptions(align=args.align, n_align=args.n_align)
    result = evaluate(Path(args.est), _gt(args.gt), options)
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
        _eprint(f"results written to {out}/")
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    from slam.io.info import describe

    info = describe(Path(args.bag))
    if args.json:
        print(json.dumps(info, indent=2, default=str))
    else:
        _print_info(info)
    return EXIT_OK


def _print_info(info: dict[str, Any]) -> None:
    for key, value in info.items():
        if key != "topics":
            print(f"{key}: {value}")
    for topic, t in (info.get("topics") or {}).items():
        print(f"{topic}")
        for k, v in t.items():
            if k == "fields":
                print(
                    "    fields: "
                    + ", ".join(
                        f"{f['name']}:{f['datatype']}@{f['offset']}"
                        if isinstance(f, dict)
                        else str(f)
                        for f in v
                    )
                )
            else:
                print(f"    {k}: {v}")


def cmd_demo(args: argparse.Namespace) -> int:
    """Simulate a drive with revisits (cached), run it with loop closure, print odometry only
    vs loop closed; with --configs, the papers' table of those recipes instead."""
    from slam.sim.cache import ensure_sequence
    from slam.viz.demo import run_demo

    out = Path(args.out) if args.out else default_out_dir("demo")
    _eprint(f"simulating the '{args.scene}' sequence (cached after the first time)...")
    bar, progress = _sim_progress(args.scene, args.quiet)
    try:
        seq = ensure_sequence(args.scene, frames=args.frames, progress=progress)
    finally:
        bar.close()
    _eprint(f"sequence: {seq.bag} ({seq.frames} scans), ground truth {seq.ground_truth}")
    if args.configs:
        res = compare(seq.bag, seq.ground_truth, args.configs, out, quiet=args.quiet)
        print(res["tables"]["text"])
        _eprint(f"demo outputs (trajectories, maps, plots, report.html) in {out}/")
        return EXIT_OK
    demo = run_demo(seq.bag, seq.ground_truth, out, config=args.config, quiet=args.quiet)
    print(demo.tables["text"])
    _eprint(f"report (trajectories with the loops, the map before / after): {demo.report}")
    return _stop_code(demo.summary)


def cmd_sweep(args: argparse.Namespace) -> int:
    from slam.sweep import format_rows, make_jobs, parse_grid, plot_heatmap, run_sweep, write_table

    inputs: list[tuple[str, str]] = []
    if args.scene:
        from slam.sim.cache import ensure_sequence

        for scene in args.scene:
            seq = ensure_sequence(scene, frames=args.frames)
            inputs.append((str(seq.bag), str(seq.ground_truth)))
    bags, gts = args.bags or [], args.gt or []
    if len(bags) != len(gts):
        raise InputError(f"give one --gt per input: {len(bags)} inputs, {len(gts)} --gt")
    inputs += [(b, str(_gt(g))) for b, g in zip(bags, gts, strict=True)]
    if not inputs:
        raise InputError("nothing to sweep over: give BAG --gt GT, or --scene corridor")
    grid = parse_grid(args.grid)
    out = Path(args.out) if args.out else default_out_dir("sweep")
    out.mkdir(parents=True, exist_ok=True)
    jobs = make_jobs(inputs, grid, args.config or "improved_floam", out, args.set, args.max_frames)
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
    _eprint(f"sweep table and heat map written to {out}/")
    failed = [r for r in rows if r.get("error")]
    for r in failed:
        _eprint(f"failed: {r}")
    return EXIT_BAD_INPUT if failed and len(failed) == len(rows) else EXIT_OK


def cmd_configs(args: argparse.Namespace) -> int:
    from slam import plugins
    from slam.config import available_configs

    print("configs: " + ", ".join(available_configs()))
    for group in plugins.GROUPS:
        print(f"{group}: " + ", ".join(plugins.available(group)))
    return EXIT_OK


# --------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="slam", description="Factor-graph LiDAR SLAM: run, compare, evaluate, simulate."
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def common_run(q: argparse.ArgumentParser) -> None:
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

    q = sub.add_parser("run", help="run SLAM on a bag / KITTI folder / PCD folder")
    q.add_argument("bag")
    q.add_argument("--config", default=None, help="config name in configs/ or a YAML path")
    q.add_argument("--no-loop", action="store_true", help="switch loop closure off")
    q.add_argument("--gt", help="ground truth (TUM) to evaluate against")
    q.add_argument(
        "--viz",
        nargs="?",
        const="",
        metavar="FILE.rrd",
        help="live view in the Rerun viewer (pip install 'pyslam-graph[viz]'); "
        "with FILE.rrd: record the same stream to a file (no display needed)",
    )
    common_run(q)
    q.set_defaults(func=cmd_run)

    q = sub.add_parser("view", help="a finished run's map, trajectories and loops in Rerun")
    q.add_argument("run_dir", help="the --out folder of a run")
    q.add_argument("--viz", metavar="FILE.rrd", help="record to FILE.rrd instead of a viewer")
    q.set_defaults(func=cmd_view)

    q = sub.add_parser("compare", help="run several configs on one bag; the papers' APE table")
    q.add_argument("bag")
    q.add_argument("--gt", required=True, help="ground truth (TUM)")
    q.add_argument("--configs", nargs="+", help=f"configs (default: {' '.join(DEFAULT_COMPARE)})")
    common_run(q)
    q.set_defaults(func=cmd_compare)

    q = sub.add_parser("simulate", help="simulate a LiDAR sequence (16-128 beams) into a bag")
    q.add_argument(
        "scene",
        help="corridor | plaza (ideal sensor) | park (realistic sensor: calibration errors, "
        "mixed pixels, porous trees, terrain) | urban (car-speed city drive, 1.2 km, up to "
        "15 m/s, stops, junctions, streets driven both ways; realistic sensor) | building | "
        "building_loop (paper 001's floor under construction, 1.27 km S-route / 0.41 km "
        "loop) | rooms2d | office2d (2D laser, 360 deg, in floor plans: a CARMEN log)",
    )
    q.add_argument(
        "--sensor",
        default="vlp16",
        choices=["vlp16", "hdl32", "hdl64", "os128"],
        help="vlp16 (default) | hdl32 | hdl64 (KITTI-style bag: no ring/time fields) | "
        "os128 (Ouster layout: t in ns, 48-byte points)",
    )
    q.add_argument("out", help="output folder")
    q.add_argument("--frames", type=int, help="number of scans (default: the whole path)")
    q.add_argument("--format", default="ros1", choices=["ros1", "ros2", "mcap"])
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--no-pedestrians", action="store_true")
    q.set_defaults(func=cmd_simulate)

    q = sub.add_parser("eval", help="APE/RPE/KITTI metrics of a trajectory against ground truth")
    q.add_argument("est")
    q.add_argument("gt", nargs="?", help="ground truth (TUM); or --relations")
    q.add_argument(
        "--relations",
        help="Freiburg relations (t1 t2 x y z roll pitch yaw): Kuemmerle's relation metric",
    )
    q.add_argument("--max-dt", type=float, default=0.01, help="relation stamp match tolerance (s)")
    q.add_argument("--align", default="se3", choices=["se3", "sim3", "none"])
    q.add_argument("--n-align", type=int, default=-1, help="align on the first N poses only")
    q.add_argument("--out", help="write ape.json and plots here")
    q.set_defaults(func=cmd_eval)

    q = sub.add_parser("info", help="topics, message counts, field layout and rate of a bag")
    q.add_argument("bag")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_info)

    q = sub.add_parser(
        "demo", help="simulate a city drive with revisits; odometry only vs loop closed"
    )
    q.add_argument("--scene", default=DEMO_SCENE)
    q.add_argument("--frames", type=int, default=DEMO_FRAMES, help="truncate the sequence")
    q.add_argument("--config", default="improved_floam_loop", help="a recipe with loop closure")
    q.add_argument("--configs", nargs="+", help="instead: the papers' table of these recipes")
    q.add_argument("--out")
    q.add_argument("--quiet", action="store_true")
    q.set_defaults(func=cmd_demo)

    q = sub.add_parser("sweep", help="grid of config values over bags, in parallel workers")
    q.add_argument("bags", nargs="*", help="inputs (each with its --gt, in order)")
    q.add_argument("--gt", action="append", help="ground truth of each input, in order")
    q.add_argument("--scene", action="append", help="also sweep over a simulated scene")
    q.add_argument("--frames", type=int, help="truncate simulated scenes")
    q.add_argument("--grid", action="append", required=True, metavar="SECTION.KEY=V1,V2,...")
    q.add_argument("--config", help="base config (default improved_floam)")
    q.add_argument("--workers", type=int, help="worker processes (default: all cores)")
    q.add_argument("--ray", metavar="ADDRESS", help="run on a Ray cluster (pip install ray)")
    common_run(q)
    q.set_defaults(func=cmd_sweep)

    q = sub.add_parser("configs", help="list built-in configs and installed plugins")
    q.set_defaults(func=cmd_configs)
    return p


def _restore_interrupt() -> None:
    """Let SIGINT interrupt a run that was started with it ignored (a job put in the
    background by a non-interactive shell inherits SIG_IGN): `kill -INT` then stops it
    cleanly with every output written, as Ctrl-C does in the foreground."""
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    ):
        signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    _restore_interrupt()
    try:
        return args.func(args)
    except KeyboardInterrupt:
        _eprint("interrupted")
        return EXIT_INTERRUPTED
    except SystemError as exc:  # Ctrl-C inside compiled code (numba loading a kernel)
        from slam.pipeline import caused_by_interrupt

        if not caused_by_interrupt(exc):
            raise
        _eprint("interrupted")
        return EXIT_INTERRUPTED
    except (InputError, ConfigError) as exc:
        _eprint(f"error: {exc}")
        return EXIT_BAD_INPUT
    except SlamError as exc:
        _eprint(f"error: {exc}")
        return EXIT_FAIL
