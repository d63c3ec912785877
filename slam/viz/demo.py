"""The demo: a simulated car-speed drive that comes back to streets it drove, run once with
loop closure; the front end's own trajectory (``odometry.tum``, exactly what the run gives
with loop closure off) against the loop-closed one, both evaluated against ground truth.

The table, the figure of both trajectories with the loop edges and the map before / after
loop closure make the point of a pose graph visible: odometry drifts, a revisit recognised
and verified pulls the drive back. Nothing is tuned for it: the scene's realistic 16-beam
sensor (calibration errors, range noise, mixed pixels) and the default recipe.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEMO_SCENE = "urban"
DEMO_CONFIG = "improved_floam_loop"
ODOM_ROW, LOOP_ROW = "odometry only", "loop closed"


@dataclass
class DemoResult:
    """The two evaluations, the table in three formats, the run's summary, the report
    (a run stopped too early to evaluate: no evaluations, no tables, ``report`` its folder)."""

    odometry: Any  # EvalResult of odometry.tum, None when stopped too early
    closed: Any  # EvalResult of trajectory.tum, None when stopped too early
    tables: dict[str, str]
    summary: dict[str, Any]
    report: Path


def demo_table(odometry: Any, closed: Any) -> dict[str, str]:
    """The papers' APE table of the two rows plus "% improvement loop closed vs odometry
    only" (positive: loop closure lowered the error), as text, markdown and csv."""
    from slam.eval.tables import ape_table, format_table

    rows = ape_table({ODOM_ROW: odometry, LOOP_ROW: closed})
    return {fmt: format_table(rows, fmt) for fmt in ("text", "markdown", "csv")}


def run_demo(
    bag: Path, gt: Path, out: Path, *, config: str = DEMO_CONFIG, quiet: bool = False
) -> DemoResult:
    """Run ``config`` (a recipe with loop closure) on ``bag`` into ``out/<config>``, evaluate
    its odometry and its loop-closed trajectory, write ``out/demo.md``, ``out/demo.csv``,
    the figures and ``out/report.html`` (first figure: both trajectories with the loops)."""
    from slam.config import load_config
    from slam.eval.metrics import evaluate
    from slam.eval.plots import odometry_vs_loop_figure, save_png
    from slam.eval.report import write_report
    from slam.run import run_one
    from slam.viz.birdseye import loop_positions, map_images

    cfg = load_config(config)
    run_dir = out / cfg.name
    summary = run_one(bag, cfg, run_dir, gt=gt, quiet=quiet, label=cfg.name)
    if "eval" not in summary and summary["stop"] is not None:  # stopped before 2 frames
        return DemoResult(None, None, {}, summary, run_dir)
    if "eval" not in summary:
        from slam.errors import InputError

        raise InputError(f"the demo run wrote no trajectory to evaluate ({summary['stopped_by']})")
    closed = summary["eval"]
    odometry = evaluate(run_dir / "odometry.tum", gt)
    tables = demo_table(odometry, closed)
    (out / "demo.md").write_text(tables["markdown"])
    (out / "demo.csv").write_text(tables["csv"])
    plots = out / "plots"
    plots.mkdir(parents=True, exist_ok=True)
    pipeline = summary["pipeline"]
    lead = save_png(
        odometry_vs_loop_figure(odometry, closed, loop_positions(pipeline)),
        plots / "odometry_vs_loop_closed.png",
    )
    maps = map_images(run_dir, pipeline, plots=plots)
    report = write_report(
        out / "report.html",
        title=f"Loop closure on {bag.name}: odometry only vs loop closed",
        lead=[lead],
        tables={"APE (translation, m), SE(3)-aligned": tables["markdown"]},
        figures={"Map": maps},
        meta={
            "input": str(bag),
            "ground truth": str(gt),
            "config": cfg.name,
            "frames": summary["frames"],
            "keyframes": summary["keyframes"],
            "loops closed": pipeline.state.loops_closed,
            "path length (m)": round(closed.path_length, 1),
            "run folder": str(run_dir),
        },
    )
    return DemoResult(odometry, closed, tables, summary, report)
