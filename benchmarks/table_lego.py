"""Paper 001's Table 1 on the simulated building floor: APE of LeGO-LOAM, LeGO-LOAM-LPB,
improved FLOAM and FLOAM, the ablation of LeGO-LOAM-LPB (each module off in turn) and the
z error with and without the ground residual / ground factor; figures in the paper's
style (Figure 11: trajectories against the truth in xy and xz; Figure 12: trajectory
coloured by its error and the error over time).

    .venv/bin/python benchmarks/table_lego.py [--scenes building building_loop] \\
        [--configs lego_loam lego_lpb improved_floam floam] [--frames N] [--workers 2] \\
        [--no-ablation] [--out runs/table_lego] [--figures docs/lego_lpb]

Every run goes through the framework's own code: ``slam.run.run_one`` (what ``slam run
--gt`` and ``slam compare`` do: trajectory, metrics.json, ape.json, plots, report) and
``slam.eval`` (evo APE with SE(3) Umeyama alignment, the papers' table). Configs that are
not installed yet are listed as missing and left out; the "% vs" rows use ``lego_loam``
when it ran, else the first config that did.

The ablation is read from the resolved ``lego_lpb`` recipe: every ``frontend`` section
with ``enabled: true`` and every factor plugin other than ``prior`` / ``odometry`` that is
enabled is switched off in turn (``--set <section>.enabled=false``), so the ablation
follows the recipe as its modules land. The ground factor is also added to the other
front ends (``--set factors.ground.enabled=true``) when a ``ground`` factor plugin exists.
The ground factor is a back-end plugin and the front end never sees the back end
(DESIGN.md), so a "+ ground factor" row of a config that also runs plainly is not a second
front-end run: the plain run records its front end (``slam.bench.loop_replay.Recorder``,
``record.npz`` in its folder) and the ground row replays that recording with the factor on
(``slam.bench.loop_replay.replay``; seconds instead of ~11 CPU minutes on the whole S
route; ``fps`` is then the recorded run's). ``--no-replay`` runs the ground rows in full.

Loop runs (a ``loops.csv`` in the run folder) get the loop table: APE of the same run's
odometry (``odometry.tum``) and optimised trajectory, loops, and false loops counted against
the ground truth by ``slam.bench.loop_audit`` (a loop edge of graph.g2o more than 1 m or
3 deg from the true relative pose of its keyframes); rows saved before the audit existed
are audited when tabulated.

Writes ``<out>/table_lego.json`` (every row) and ``<out>/table_lego.md`` (the tables);
prints the tables. Speed: frames/s of each run, and its ratio to ``floam``'s in the same
run (the machine is shared, so only ratios are meaningful).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from slam.bench.lego_table import BASELINE, FULL, available, jobs_for, loop_columns, run_job

MAIN_CONFIGS = ("lego_loam", "lego_lpb", "improved_floam", "floam")
COLUMNS = ("Max", "Mean", "Median", "RMSE", "Std")  # the paper's Table 1


# ----------------------------------------------------------------------------- tables


def loop_table(rows: list[dict]) -> str:
    """Odometry vs loop-closed APE RMSE, loops, false loops of the loop runs."""
    lines = [
        "| Config | odometry RMSE (m) | with loops RMSE (m) | change | max (m) | loops | false "
        "| constraint error, median (m) |",
        "|:---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    n = 0
    for r in rows:
        if "false_loops" not in r or "ape" not in r:
            continue
        n += 1
        odo, loop = r["ape_odom_rmse"], r["ape"]["rmse"]
        med = r.get("loop_err_median")
        lines.append(
            f"| {r['label']} | {odo:.3f} | {loop:.3f} | {(loop - odo) / odo * 100:+.1f} % | "
            f"{r['ape']['max']:.3f} | {r['loop_edges']} | {r['false_loops']} | "
            f"{'-' if med is None else f'{med:.3f}'} |"
        )
    return "\n".join(lines) + "\n" if n else ""


def table1(rows: list[dict]) -> str:
    """The paper's Table 1 (APE translation, m) with "% vs LeGO-LOAM" rows."""
    from slam.eval.tables import ape_table, format_table

    ok = {r["label"]: r["ape"] for r in rows if "ape" in r}
    if not ok:
        return "(no run finished)\n"
    base = BASELINE if BASELINE in ok else next(iter(ok))
    table = ape_table(ok, baseline=base)
    table = [{k: v for k, v in row.items() if k in ("Config", *COLUMNS)} for row in table]
    return format_table(table, "markdown", precision=3)


def ablation_table(rows: list[dict]) -> str:
    """RMSE / max of the full LPB and of each module switched off, change vs the full."""
    full = next((r for r in rows if r["label"] == FULL and "ape" in r), None)
    abl = [r for r in rows if r["group"] == "ablation"]
    if full is None or not abl:
        return "(no ablation: lego_lpb did not run)\n"
    lines = [
        "| Config | RMSE (m) | Max (m) | z RMSE (m) | RMSE vs full LPB |",
        "|:---|---:|---:|---:|---:|",
    ]
    for r in [full, *abl]:
        if "ape" not in r:
            lines.append(f"| {r['label']} | failed: {r.get('error', r.get('stopped_by'))} | | | |")
            continue
        ch = (r["ape"]["rmse"] - full["ape"]["rmse"]) / full["ape"]["rmse"] * 100.0
        lines.append(
            f"| {r['label']} | {r['ape']['rmse']:.3f} | {r['ape']['max']:.3f} | "
            f"{r['z_rmse']:.3f} | {'' if r is full else f'{ch:+.1f} %'} |"
        )
    return "\n".join(lines) + "\n"


def z_table(rows: list[dict]) -> str:
    """z error of every run: aligned RMSE / max, drift from the start (RMSE, at the end)."""
    lines = [
        "| Config | z RMSE (m) | z max (m) | z drift RMSE (m) | z drift at end (m) |",
        "|:---|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "z_rmse" in r:
            lines.append(
                f"| {r['label']} | {r['z_rmse']:.3f} | {r['z_max']:.3f} | "
                f"{r['z_drift_rmse']:.3f} | {r['z_drift_end']:+.3f} |"
            )
    return "\n".join(lines) + "\n"


def speed_table(rows: list[dict]) -> str:
    ref = next((r for r in rows if r["label"] == "floam" and r.get("fps")), None)
    lines = ["| Config | frames | keyframes | frames/s | x floam | lost | loops | KITTI drift % |",
             "|:---|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['label']} | failed: {r['error']} | | | | | | |")
            continue
        ratio = f"{r['fps'] / ref['fps']:.2f}" if ref and r.get("fps") else "-"
        drift = r.get("drift_pct")
        lines.append(
            f"| {r['label']} | {r['frames_run']} | {r['keyframes']} | {r['fps'] or 0:.1f} | "
            f"{ratio} | {r.get('lost') or 0} | {r.get('loops') or 0} | "
            f"{'-' if drift is None else f'{drift:.2f}'} |"
        )
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- figures


def figures(rows: list[dict], scene: str, fig_dir: Path) -> list[Path]:
    """Figure 11 (xy / xz overlays of the main configs on the truth) and Figure 12 (per
    config: trajectory coloured by APE, APE over time), with slam.eval.plots (evo)."""
    from slam.eval.metrics import evaluate
    from slam.eval.plots import (
        ape_colormap_figure,
        ape_figure,
        ape_overlay_figure,
        overlay_figure,
        save_png,
    )

    fig_dir.mkdir(parents=True, exist_ok=True)
    results = {}
    for r in rows:
        if r["group"] == "main" and "ape" in r:
            results[r["label"]] = evaluate(Path(r["out"]) / "trajectory.tum", Path(r["gt"]))
    if not results:
        return []
    files = [save_png(overlay_figure(results, p), fig_dir / f"{scene}_overlay_{p}.png")
             for p in ("xy", "xz")]  # fmt: skip
    files.append(save_png(ape_overlay_figure(results), fig_dir / f"{scene}_ape_overlay.png"))
    for name, res in results.items():
        files.append(save_png(ape_colormap_figure(res), fig_dir / f"{scene}_{name}_heatmap.png"))
        files.append(save_png(ape_figure(res), fig_dir / f"{scene}_{name}_ape_time.png"))
    return files


def plan_figure(path: Path) -> Path:
    """Floor plan of the building scenes (walls cut at 1 m) with both routes and the
    lines walked by workers and machinery."""
    from slam.eval.plots import evo_plot, save_png
    from slam.sim import make_scene

    evo_plot()  # Agg backend
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    s_route, loop = make_scene("building"), make_scene("building_loop")
    tri = s_route.vertices[s_route.triangles]
    cut = (tri[:, :, 2].min(axis=1) < 1.0) & (tri[:, :, 2].max(axis=1) > 1.0)
    fig, ax = plt.subplots(figsize=(14.0, 7.5), dpi=100)
    ax.add_collection(PolyCollection(tri[cut][:, :, :2], facecolors="k", edgecolors="k", lw=0.2))
    for scene, color, label, dy in ((s_route, "tab:red", "building (S route)", 0.0),
                                    (loop, "tab:blue", "building_loop", 0.6)):  # fmt: skip
        xy = scene.pose_at(np.arange(0.0, scene.duration, 0.5))[:, :2, 3]
        ax.plot(xy[:, 0], xy[:, 1] + dy, "-", color=color, lw=1.2,
                label=f"{label}: {scene.trajectory.length:.0f} m")  # fmt: skip
        ax.plot(*xy[0], "o", color=color)
    for ped in s_route.pedestrians:
        ax.plot([ped.p0[0], ped.p1[0]], [ped.p0[1], ped.p1[1]], "-", color="tab:green", lw=2)
    ax.plot([], [], "-", color="tab:green", lw=2, label="workers / machinery")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Simulated floor (walls at 1 m height)")
    ax.legend(loc="upper center", ncol=3, bbox_to_anchor=(0.5, -0.08), frameon=True)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_png(fig, path)


# ----------------------------------------------------------------------------- main


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["building", "building_loop"])
    ap.add_argument("--configs", nargs="+", default=list(MAIN_CONFIGS))
    ap.add_argument("--frames", type=int, help="only the first N frames of each sequence")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--no-ablation", action="store_true")
    ap.add_argument("--ablation-scenes", nargs="+", default=["building"])
    ap.add_argument(
        "--ground-configs",
        nargs="*",
        default=[FULL, "improved_floam"],
        help="configs also run with the ground factor added (on the ablation scenes)",
    )
    ap.add_argument(
        "--tabulate-only", action="store_true", help="no new runs: tables of the saved rows"
    )
    ap.add_argument(
        "--reuse", action="store_true", help="keep the rows of identical runs already in --out"
    )
    ap.add_argument("--out", default="runs/table_lego")
    ap.add_argument("--figures", help="folder for the paper-style figures (e.g. docs/lego_lpb)")
    ap.add_argument(
        "--cache-dir",
        help="where the simulated sequences are cached (default <out>/sim: a private cache, "
        "so that no other process's pruning of ~/.cache removes them mid-run)",
    )
    ap.add_argument("--plan-only", action="store_true", help="only draw the floor plan")
    ap.add_argument(
        "--no-replay",
        action="store_true",
        help="run the ground-factor rows in full instead of replaying the plain run's "
        "recorded front end",
    )
    return ap.parse_args(argv)


def build_jobs(args: argparse.Namespace, configs: list[str], out: Path) -> list[dict]:
    """Every scene's jobs, simulated once each, in the order the tables keep (``index``)
    sorted for running: main configs, then the ablation, then the ground factor; slowest
    first."""
    from slam.sim import ensure_sequence, make_scene
    from slam.sim.simulate import effective_model, full_frames

    jobs = []
    for scene in args.scenes:
        # The route's first --frames scans (all when the route is shorter), simulated once.
        frames = None
        if args.frames:
            world = make_scene(scene)
            frames = min(args.frames, full_frames(world, effective_model(world)))
        seq = ensure_sequence(scene, frames=frames, cache_dir=Path(args.cache_dir or out / "sim"))
        abl = not args.no_ablation and scene in args.ablation_scenes
        ground = args.ground_configs if scene in args.ablation_scenes else ()
        jobs += jobs_for(scene, seq, configs, args.frames, out, abl, ground, not args.no_replay)
    for i, job in enumerate(jobs):
        job["index"] = i  # the tables keep this order
    order = {"main": 0, "ablation": 1, "ground": 2}
    jobs.sort(key=lambda j: (order[j["group"]], "improved_floam" not in j["config"]))
    for job in jobs:
        job["reuse"] = args.reuse or args.tabulate_only
        job["tabulate_only"] = args.tabulate_only
    return jobs


def run_jobs(jobs: list[dict], workers: int) -> list[dict]:
    """The rows of all jobs (the replays after the runs they replay), in ``index`` order."""
    print(f"{len(jobs)} runs on {workers} worker(s)", file=sys.stderr)
    t0 = time.perf_counter()
    ctx = mp.get_context("spawn")
    runs = [j for j in jobs if not j.get("replay_of")]
    replays = [j for j in jobs if j.get("replay_of")]  # after the runs they replay
    rows = []

    def done(row: dict) -> None:
        rows.append(row)
        status = row.get("error") or f"RMSE {row.get('ape', {}).get('rmse', float('nan')):.3f} m"
        print(f"[{time.perf_counter() - t0:6.0f} s] {row['scene']} {row['label']}: {status}",
              file=sys.stderr, flush=True)  # fmt: skip

    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        for row in pool.map(run_job, runs):
            done(row)
        for row in pool.map(run_job, replays):
            done(row)
    rows.sort(key=lambda r: r["index"])
    return rows


def scene_report(rows: list[dict], scene: str, figures_dir: str | None) -> list[str]:
    """The tables (and figures) of one scene, as markdown paragraphs."""
    srows = [r for r in rows if r["scene"] == scene and not r.get("not_run")]
    not_run = [r["label"] for r in rows if r["scene"] == scene and r.get("not_run")]
    frames = srows[0]["frames_run"] if srows and "frames_run" in srows[0] else "?"
    text = [f"## {scene} ({frames} frames)\n"]
    text.append(
        "APE (translation, m; SE(3)-aligned, or from the start when the route is straight "
        "and evo's Umeyama alignment is degenerate), the paper's Table 1:\n"
    )
    text.append(table1([r for r in srows if r["group"] == "main"]))
    for r in srows:  # rows saved before the loop audit existed
        if "false_loops" not in r and "ape" in r and "out" in r:
            r.update(loop_columns(Path(r["out"]), Path(r["gt"])))
    loops = loop_table(srows)
    if loops:
        text.append("\nLoop closure (false: constraint > 1 m or 3 deg from the truth):\n")
        text.append(loops)
    text.append("\nAblation of LeGO-LOAM-LPB (each module off in turn):\n")
    text.append(ablation_table(srows))
    text.append("\nz error (m):\n")
    text.append(z_table(srows))
    text.append("\nRuns:\n")
    text.append(speed_table(srows))
    if not_run:
        text.append(f"\nnot run (no saved row): {', '.join(not_run)}\n")
    if figures_dir:
        for f in figures(srows, scene, Path(figures_dir)):
            text.append(f"figure: {f}\n")
    text.append("\n")
    return text


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.figures:
        print(f"figure: {plan_figure(Path(args.figures) / 'building_plan.png')}")
    if args.plan_only:
        return 0
    configs = [c for c in args.configs if available(c)]
    missing = [c for c in args.configs if c not in configs]
    if missing:
        print(f"not installed (left out): {', '.join(missing)}", file=sys.stderr)
    out = Path(args.out)
    rows = run_jobs(build_jobs(args, configs, out), args.workers)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table_lego.json").write_text(json.dumps(rows, indent=2, default=str))
    text = [f"configs left out (not installed): {', '.join(missing) or 'none'}\n"]
    for scene in args.scenes:
        text += scene_report(rows, scene, args.figures)
    report = "\n".join(text)
    (out / "table_lego.md").write_text(report)
    print(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
