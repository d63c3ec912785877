"""Running one configuration on one input and writing everything: the library side of
``slam run`` (also used by ``slam compare``, ``slam demo`` and the sweep workers).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from slam.errors import InputError


def disable_loops(config: Any) -> None:
    """``--no-loop``: switch off every factor plugin that closes loops."""
    from slam import plugins

    for name, params in config.factors.items():
        cls = plugins.load("slam.factors", params.get("plugin", name))
        if getattr(cls, "is_loop", False):
            params["enabled"] = False


def _warm_up(pipeline: Any, config: Any) -> float | None:
    """Load (on the very first run: compile) the numba kernels of a LiDAR front end before
    the first frame is timed (``slam.warmup``): the first frame otherwise carries them, 10-100x
    slower than the next (warm cache 2.1 s wall / 0.63 s CPU, saving ~1.2 s of the first
    frame). Seconds taken, or None for front ends it does not apply to (2D, plugins)."""
    from frontends.common import ScanToMapFrontend
    from slam.warmup import warm_up

    if not isinstance(pipeline.frontend, ScanToMapFrontend):
        return None
    return round(warm_up(config.frontend), 3)


def run_one(
    bag: Path,
    config: Any,
    out: Path,
    *,
    topic: str | None = None,
    gt: Path | None = None,
    quiet: bool = False,
    label: str | None = None,
    observers: Any = (),
) -> dict[str, Any]:
    """Run one configuration on one input, write all outputs; returns a summary dict.

    observers: watchers of the run (``slam.viz.rerun_view.RerunObserver``), told of every
    frame, keyframe, loop and optimisation."""
    from tqdm import tqdm

    from slam.io.source import open_source
    from slam.outputs import write_outputs
    from slam.pipeline import Pipeline, resolved_config

    resolved = resolved_config(config)
    source = open_source(bag, topic=topic or config.source.topic)
    pipeline = Pipeline(config, observers=observers)
    src = config.source
    total = max(len(source) - src.start, 0) if len(source) else 0
    if src.start and len(source) and src.start >= len(source):
        raise InputError(f"--start {src.start}: {bag} has only {len(source)} messages")
    if src.max_frames is not None:
        total = min(total, src.max_frames) if total else src.max_frames
    warmup_seconds = _warm_up(pipeline, config)
    bar = tqdm(
        total=total or None,
        unit="frame",
        desc=label or config.name,
        disable=quiet,
        dynamic_ncols=True,
        file=sys.stderr,
        mininterval=0.1 if sys.stderr.isatty() else 10.0,  # logs get a line per 10 s
    )
    last = [0]

    def on_frame(n: int) -> None:
        bar.update(n - last[0])
        last[0] = n

    try:
        state = pipeline.run(
            source,
            on_frame=on_frame,
            max_frames=src.max_frames,
            start=src.start,
            strict=src.strict,
        )
    finally:
        bar.close()
    written = write_outputs(
        pipeline,
        out,
        resolved_config=resolved,
        extra_metrics={
            "input": str(bag),
            "topic": getattr(source, "topic", None),
            "input_notes": list(getattr(source, "notes", [])),
            "warmup_seconds": warmup_seconds,
        },
    )
    from slam.io.grid_map import write_region_map

    for path in write_region_map(pipeline, out):  # 2D runs: map_server files
        written[path.stem + path.suffix] = path
    summary: dict[str, Any] = {
        "out": out,
        "frames": state.frames,
        "keyframes": len(state.keyframes),
        "stopped_by": state.stopped_by,
        "skipped_messages": dict(state.skipped_messages),
        "input_notes": list(getattr(source, "notes", [])),
        "written": written,
        "pipeline": pipeline,
    }
    if gt is not None and state.frames > 1:
        summary["eval"] = evaluate_run(out, gt, pipeline, title=label or config.name)
    return summary


def evaluate_run(out: Path, gt: Path, pipeline: Any = None, title: str = "run") -> Any:
    """APE/RPE against ground truth, plots and the HTML report of one run."""
    from slam.eval.metrics import evaluate
    from slam.eval.plots import plot_all
    from slam.eval.report import write_report
    from slam.eval.tables import ape_table, format_table

    result = evaluate(out / "trajectory.tum", gt)
    (out / "ape.json").write_text(json.dumps(result.to_dict(), indent=2))
    loops = _loop_positions(pipeline) if pipeline is not None else None
    images = plot_all(result, out / "plots", loop_positions=loops)
    from slam.viz.birdseye import map_images

    maps = map_images(out, pipeline)
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


def _loop_positions(pipeline: Any) -> list | None:
    """Pairs of optimised keyframe positions for each accepted loop, for the plots."""
    st = pipeline.state
    pairs = []
    for source in pipeline.factor_sources:
        for ev in getattr(source.plugin, "events", []):
            if ev.accepted and ev.source in st.estimates and ev.target in st.estimates:
                pairs.append(
                    (st.estimates[ev.target][:3, 3].copy(), st.estimates[ev.source][:3, 3].copy())
                )
    return pairs or None
