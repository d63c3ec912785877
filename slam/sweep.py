"""Parameter sweeps: a grid of config overrides over one or more inputs.

Each grid point is an independent ``slam run`` in a worker process
(``concurrent.futures.ProcessPoolExecutor`` on one machine). With ``ray_address``
the same function runs through ``ray.util.multiprocessing.Pool`` on a Ray cluster:
no scheduler of our own, one code path for the work itself.
"""

from __future__ import annotations

import csv
import itertools
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from slam.errors import ConfigError, SlamError

METRIC_KEYS = ("rmse", "mean", "median", "max", "min", "std")
# per-frame front-end means added to each row (paper 000 section 2.3 discusses removal rate,
# retained features and neighbourhood-search time next to accuracy)
SWEEP_DIAGNOSTICS = ("n_edges", "n_planes", "sor_ms", "total_ms")


@dataclass(frozen=True)
class SweepJob:
    """One grid point on one input."""

    bag: str
    gt: str
    config: str
    overrides: tuple[str, ...]
    out: str
    max_frames: int | None = None


def parse_grid(specs: Sequence[str]) -> dict[str, list[Any]]:
    """``["frontend.sor.k=5,8,10", ...]`` -> ordered {key: [values]} (values parsed as YAML)."""
    grid: dict[str, list[Any]] = {}
    for spec in specs:
        key, sep, values = spec.partition("=")
        if not sep or not key.strip() or not values.strip():
            raise ConfigError(f"grid '{spec}' must look like section.key=v1,v2,...")
        grid[key.strip()] = [yaml.safe_load(v) for v in values.split(",") if v.strip()]
    if not grid:
        raise ConfigError("a sweep needs at least one --grid section.key=v1,v2,...")
    return grid


def grid_points(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    keys = list(grid)
    return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*grid.values())]


def point_name(point: dict[str, Any]) -> str:
    return "_".join(f"{k.split('.')[-1]}={v}" for k, v in point.items())


def make_jobs(
    inputs: Sequence[tuple[str, str]],
    grid: dict[str, list[Any]],
    config: str,
    out: Path,
    base_overrides: Sequence[str] = (),
    max_frames: int | None = None,
) -> list[SweepJob]:
    jobs = []
    for bag, gt in inputs:
        for point in grid_points(grid):
            overrides = tuple(base_overrides) + tuple(f"{k}={v}" for k, v in point.items())
            folder = out / Path(bag).stem / point_name(point)
            jobs.append(SweepJob(bag, gt, config, overrides, str(folder), max_frames))
    return jobs


def check_jobs(jobs: Sequence[SweepJob]) -> None:
    """Build the config of every grid point (plugin keys included) and read every ground
    truth before anything runs: ConfigError / InputError naming the first bad one."""
    from slam.config import load_config
    from slam.eval.metrics import read_for_eval
    from slam.pipeline import resolved_config

    for config_name, sets in dict.fromkeys((job.config, job.overrides) for job in jobs):
        try:
            resolved_config(load_config(config_name, list(sets)))
        except ConfigError as exc:
            raise ConfigError(f"grid point {' '.join(sets)}: {exc}") from exc
    for gt in dict.fromkeys(job.gt for job in jobs):
        read_for_eval(gt)


def run_job(job: SweepJob) -> dict[str, Any]:
    """Run one grid point (in a worker); returns the row of the results table."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from slam.config import load_config
    from slam.run import run_one

    row: dict[str, Any] = {"input": Path(job.bag).name}
    row.update(dict(o.split("=", 1) for o in job.overrides))
    try:
        config = load_config(job.config, list(job.overrides))
        if job.max_frames is not None:
            config.source.max_frames = job.max_frames
        summary = run_one(Path(job.bag), config, Path(job.out), gt=Path(job.gt), quiet=True)
        ape = summary["eval"].ape_trans
        row.update({f"ape_{k}": float(ape[k]) for k in METRIC_KEYS if k in ape})
        row["frames"] = summary["frames"]
        means = summary["pipeline"].state.diagnostic_means()
        row.update({k: round(means[k], 3) for k in SWEEP_DIAGNOSTICS if k in means})
        if means.get("n_after_crop") and "n_after_sor" in means:
            row["kept_pct"] = round(100.0 * means["n_after_sor"] / means["n_after_crop"], 2)
        row["error"] = summary["stopped_by"] or ""
    except SlamError as exc:
        row["error"] = str(exc)
    return row


def run_sweep(
    jobs: Sequence[SweepJob],
    *,
    workers: int | None = None,
    ray_address: str | None = None,
    on_done: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Run all jobs in parallel; rows in job order."""
    if ray_address:
        try:
            from ray.util.multiprocessing import Pool
        except ImportError as exc:
            raise ConfigError(
                "--ray needs the optional dependency: pip install 'pyslam-graph[ray]'"
            ) from exc
        with Pool(ray_address=ray_address) as pool:
            rows = []
            for row in pool.imap(run_job, jobs):
                rows.append(row)
                if on_done:
                    on_done(row)
            return rows
    workers = workers or max(1, (os.cpu_count() or 1))
    if workers == 1:
        rows = []
        for job in jobs:
            rows.append(run_job(job))
            if on_done:
                on_done(rows[-1])
        return rows
    results: dict[int, dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(run_job, job): i for i, job in enumerate(jobs)}
        for fut in as_completed(futures):
            results[futures[fut]] = fut.result()
            if on_done:
                on_done(results[futures[fut]])
    return [results[i] for i in range(len(jobs))]


def write_table(rows: list[dict[str, Any]], path: Path) -> None:
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


def format_rows(rows: list[dict[str, Any]], metric: str = "ape_rmse") -> str:
    """Plain text table of the sweep, best first."""
    keys = [k for k in rows[0] if not k.startswith("ape_") and k not in ("frames", "error")]
    ordered = sorted(rows, key=lambda r: r.get(metric, float("inf")))
    head = keys + ["rmse", "mean", "max"]
    lines = ["  ".join(f"{h:>12}" for h in head)]
    for r in ordered:
        vals = [str(r.get(k, "")) for k in keys]
        vals += [f"{r[m]:.4f}" if m in r else "failed" for m in ("ape_rmse", "ape_mean", "ape_max")]
        lines.append("  ".join(f"{v:>12}" for v in vals))
    return "\n".join(lines)


def plot_heatmap(
    rows: list[dict[str, Any]], grid: dict[str, list[Any]], path: Path, metric: str = "ape_rmse"
) -> Path | None:
    """Heat map of ``metric`` over the first two grid axes (mean over inputs); a line for 1 axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    keys = list(grid)
    if not keys:
        return None

    def cell(values: dict[str, Any]) -> float:
        hits = [
            r[metric]
            for r in rows
            if metric in r and all(str(r.get(k)) == str(v) for k, v in values.items())
        ]
        return float(np.mean(hits)) if hits else float("nan")

    # an explicit layout engine: evo's plot settings (imported by slam.eval.plots in the
    # same process) switch matplotlib's default one, and tight_layout then fails on colorbars
    fig, ax = plt.subplots(figsize=(6.4, 4.8), layout="constrained")
    if len(keys) == 1:
        xs = grid[keys[0]]
        ax.plot([str(x) for x in xs], [cell({keys[0]: x}) for x in xs], "o-")
        ax.set_xlabel(keys[0])
        ax.set_ylabel(f"APE {metric.removeprefix('ape_')} [m]")
    else:
        ys, xs = grid[keys[0]], grid[keys[1]]
        data = np.array([[cell({keys[0]: y, keys[1]: x}) for x in xs] for y in ys])
        im = ax.imshow(data, cmap="viridis_r", origin="lower", aspect="auto")
        ax.set_xticks(range(len(xs)), [str(x) for x in xs])
        ax.set_yticks(range(len(ys)), [str(y) for y in ys])
        ax.set_xlabel(keys[1])
        ax.set_ylabel(keys[0])
        lo, hi = np.nanmin(data), np.nanmax(data)
        for (i, j), v in np.ndenumerate(data):
            light = np.isfinite(v) and hi > lo and (v - lo) / (hi - lo) < 0.5  # yellow end
            ax.text(
                j,
                i,
                "-" if np.isnan(v) else f"{v:.3f}",
                ha="center",
                va="center",
                color="black" if light else "white",
                fontsize=8,
            )
        fig.colorbar(im, ax=ax, label=f"APE {metric.removeprefix('ape_')} [m]")
    ax.set_title("parameter sweep")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
