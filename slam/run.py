"""Running configurations on an input and writing everything: the library side of ``slam
run`` and ``slam compare`` (also used by ``slam demo`` and the sweep workers).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slam.errors import InputError

if TYPE_CHECKING:  # imported lazily at run time: the CLI starts fast
    import numpy as np

    from slam.io.stream import ScanStream
    from slam.observer import RunObserver
    from slam.system import SlamSystem


def disable_loops(config: Any) -> None:
    """``--no-loop``: switch off every factor plugin that closes loops."""
    from slam import plugins

    for name, params in config.factors.items():
        cls = plugins.load("slam.factors", params.get("plugin", name))
        if getattr(cls, "is_loop", False):
            params["enabled"] = False


def _warm_up(system: SlamSystem, config: Any) -> float | None:
    """Load (on the very first run: compile) the numba kernels of a LiDAR front end before
    the first frame is timed (``slam.warmup``): the first frame otherwise carries them, 10-100x
    slower than the next (warm cache 2.1 s wall / 0.63 s CPU, saving ~1.2 s of the first
    frame). Seconds taken, or None for front ends it does not apply to (2D, plugins)."""
    from frontends.common import ScanToMapFrontend
    from slam.warmup import warm_up

    if not isinstance(system.frontend, ScanToMapFrontend):
        return None
    return round(warm_up(config.frontend), 3)


def _open_stream(bag: Path, source: Any, system: SlamSystem) -> tuple[ScanStream, int]:
    """The scan stream of ``source`` per the config's ``source`` section, and the number
    of messages it will read (0: unknown)."""
    from slam.io.stream import ScanStream

    src = system.config.source
    total = max(len(source) - src.start, 0) if len(source) else 0
    if src.start and len(source) and src.start >= len(source):
        raise InputError(f"--start {src.start}: {bag} has only {len(source)} messages")
    if src.max_frames is not None:
        total = min(total, src.max_frames) if total else src.max_frames
    stream = ScanStream(
        source,
        src,
        start=src.start,
        max_frames=src.max_frames,
        strict=src.strict,
        stats=system.state.input,
    )
    return stream, total


def _write_all(
    system: SlamSystem,
    out: Path,
    resolved: dict[str, Any],
    extra: dict[str, Any],
    to_output: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> dict[str, Path]:
    """Every output of a run (``slam.outputs``), and a 2D run's map_server files;
    ``to_output``: the input's convention for the trajectory files (``output_trajectory``)."""
    from slam.io.grid_map import write_region_map
    from slam.outputs import write_outputs

    written = write_outputs(
        system, out, resolved_config=resolved, extra_metrics=extra, to_output=to_output
    )
    for path in write_region_map(system, out):
        written[path.stem + path.suffix] = path
    return written


def _progress_bar(total: int, desc: str, quiet: bool) -> Any:
    """A tqdm bar on stderr counting input messages; logs get a line per 10 s."""
    from tqdm import tqdm

    return tqdm(
        total=total or None,
        unit="frame",
        desc=desc,
        disable=quiet,
        dynamic_ncols=True,
        file=sys.stderr,
        mininterval=0.1 if sys.stderr.isatty() else 10.0,
    )


def run_one(
    bag: Path,
    config: Any,
    out: Path,
    *,
    topic: str | None = None,
    gt: Path | None = None,
    quiet: bool = False,
    label: str | None = None,
    observers: Sequence[RunObserver] = (),
) -> dict[str, Any]:
    """Run one configuration on one input, write all outputs; returns a summary dict.

    ``gt`` is read and checked before the first scan (``slam.eval.ground_truth``);
    ``observers``: ``slam.observer.RunObserver`` s that watch the run (a live viewer)."""
    from slam.interrupts import StopRequest
    from slam.io.source import open_source
    from slam.pipeline import resolved_config, run_stream
    from slam.state import StopReason
    from slam.system import SlamSystem

    resolved = resolved_config(config)
    source = open_source(
        bag, topic=topic or config.source.topic, frame_period=config.source.frame_period
    )
    truth = None
    if gt is not None:
        from slam.eval.ground_truth import read_ground_truth

        truth = read_ground_truth(gt, source)
    system = SlamSystem(config, observers=observers)
    try:
        stream, total = _open_stream(bag, source, system)
        warmup_seconds = _warm_up(system, config)
    except BaseException:
        system.observers.close()  # the run never started: finish() would have closed them
        raise
    bar = _progress_bar(total, label or config.name, quiet)
    try:
        state = run_stream(system, stream, on_message=lambda n: bar.update(n - bar.n))
    finally:
        bar.close()
    notes = list(getattr(source, "notes", []))
    extra = {"input": str(bag), "topic": getattr(source, "topic", None), "input_notes": notes}
    extra = {**extra, "warmup_seconds": warmup_seconds}
    with StopRequest("writing the outputs first") as late:  # Ctrl-C: they are written
        written = _write_all(
            system, out, resolved, extra, getattr(source, "output_trajectory", None)
        )
    if late.requested and state.stop is None:
        state.stopped(StopReason.INTERRUPTED)
    summary: dict[str, Any] = {
        "out": out,
        "frames": state.frames,
        "keyframes": len(state.keyframes),
        "stop": state.stop,  # slam.state.Stop or None
        "stopped_by": state.stopped_by,  # the same in words
        "skipped_messages": dict(state.skipped_messages),
        "input_notes": notes,
        "written": written,
        "system": system,
        "pipeline": system,  # the name scripts used before
    }
    if truth is not None:
        summary["gt_notes"], summary["gt_warnings"] = truth.notes, truth.warnings
        if state.frames > 1:
            try:
                summary["eval"] = evaluate_run(out, truth, system, title=label or config.name)
            except InputError as exc:  # a run stopped after a few frames: too few to align
                if state.stop is None:
                    raise
                summary["eval_error"] = str(exc)
    return summary


def compare(
    bag: Path,
    gt: Path,
    configs: list[str],
    out: Path,
    *,
    overrides: list[str] | None = None,
    topic: str | None = None,
    quiet: bool = False,
    configure: Callable[[Any], None] | None = None,
) -> dict[str, Any]:
    """Run each config on the same input (``out/<config>``; the first that stops early ends
    the comparison, Ctrl-C too, even between two runs); the papers' APE table, plots and
    report of the configs evaluated in ``out``. Every config is loaded and checked before
    the first run, and the ground truth read before its scans.

    ``configure(config)``: applied to every loaded config (e.g. the CLI's --start/--strict).
    Returns results (config -> evaluation), tables (by format; none when a run stopped
    before any was evaluated), out, stops (config -> ``slam.state.Stop`` or None, for each
    config started) and eval_errors (config -> why a run that stopped early could not be
    evaluated)."""
    from slam.config import load_config
    from slam.eval.plots import plot_all
    from slam.eval.report import write_report
    from slam.eval.tables import ape_table, format_table
    from slam.interrupts import caused_by_interrupt
    from slam.pipeline import resolved_config
    from slam.state import Stop, StopReason

    results: dict[str, Any] = {}
    stops: dict[str, Any] = {}
    eval_errors: dict[str, str] = {}
    loaded = [load_config(name, overrides) for name in configs]  # every name, before any run
    for config in loaded:
        if configure is not None:
            configure(config)
        resolved_config(config)  # plugin keys checked too: a bad one stops nothing half-way
    for config in loaded:
        name = config.name
        try:
            summary = run_one(bag, config, out / name, topic=topic, gt=gt, quiet=quiet, label=name)
        except (KeyboardInterrupt, SystemError) as exc:
            # Ctrl-C outside a run's frames (loading, warm-up, writing, evaluation): the
            # configs before it still get their table; SystemError: Ctrl-C in numba
            if not caused_by_interrupt(exc):
                raise
            stops[name] = Stop(StopReason.INTERRUPTED)
            break
        stops[name] = summary["stop"]
        if "eval" in summary:
            results[name] = summary["eval"]
        if "eval_error" in summary:
            eval_errors[name] = summary["eval_error"]
        if summary["stop"] is not None:
            break
    res = {"results": results, "tables": {}, "out": out, "stops": stops, "eval_errors": eval_errors}
    if not results and any(stop is not None for stop in stops.values()):
        return res  # stopped before any run was evaluated: no table
    rows = ape_table({k: v.ape_trans for k, v in results.items()})
    res["tables"] = tables = {fmt: format_table(rows, fmt) for fmt in ("text", "markdown", "csv")}
    (out / "compare.md").write_text(tables["markdown"])
    (out / "compare.csv").write_text(tables["csv"])
    images = plot_all(results, out / "plots", prefix="compare_")
    write_report(
        out / "report.html",
        title=f"SLAM comparison on {bag.name}",
        tables={"APE (translation, m)": tables["markdown"]},
        images=images,
        meta={"input": str(bag), "ground truth": str(gt), "configs": ", ".join(configs)},
    )
    return res


def evaluate_run(out: Path, gt: Any, system: Any = None, title: str = "run") -> Any:
    """APE/RPE against ground truth (a file, or ``slam.eval.ground_truth.GroundTruth``),
    plots and the HTML report of one run."""
    from slam.eval.ground_truth import GroundTruth, evaluate_truth, read_ground_truth
    from slam.eval.plots import plot_all
    from slam.eval.report import write_report
    from slam.eval.tables import ape_table, format_table

    truth = gt if isinstance(gt, GroundTruth) else read_ground_truth(gt)
    gt = truth.path
    result = evaluate_truth(out / "trajectory.tum", truth)
    (out / "ape.json").write_text(json.dumps(result.to_dict(), indent=2))
    from slam.viz.birdseye import loop_positions, map_images

    loops = (loop_positions(system) or None) if system is not None else None
    images = plot_all(result, out / "plots", loop_positions=loops)

    maps = map_images(out, system)
    table = format_table(ape_table({title: result.ape_trans}), "markdown")
    metrics = (
        json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").exists() else {}
    )
    write_report(
        out / "report.html",
        title=f"SLAM run: {title}",
        tables={"APE (translation, m)": table},
        images=images,
        figures={"Map": maps},
        meta={
            "ground truth": str(gt),
            **{k: v for k, v in metrics.items() if not isinstance(v, dict)},
        },
    )
    return result
