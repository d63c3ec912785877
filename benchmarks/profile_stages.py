"""Where a frame's time goes: every stage of full SLAM per frame, on 16-beam, 64-beam and
real KITTI-raw scans, next to small_gicp's own odometry measured in the same run.

    .venv/bin/python benchmarks/profile_stages.py [--frames 150] [--config improved_floam_loop]
        [--datasets corridor park urban-hdl64 kitti-raw] [--markdown] [--cpu]
        [--set frontend.sor.mode=banded] [--variant banded:frontend.sor.mode=banded]

Each dataset is run through the whole pipeline (front end, factor plugins, back end) with
the recipe given. Front-end stages are the front end's own timings (``*_ms`` extras, mean
per frame); factor plugins and the back end are the pipeline's stage clocks, given per
frame and per keyframe; the loop plugin's own detect/verify clocks when it reports them.
``frames/s`` is the whole pipeline; ``x small_gicp`` divides it by small_gicp's VGICP
scan-to-map odometry (``slam.bench.peers.small_gicp_odometry``) on the same scans, timed
right after it on the same machine state. ``... CPU (first100/last100)``: CPU ms of each
stage per frame over the first and last 100 frames (metrics.json stage_cpu_ms_*), which,
unlike wall time, a loaded machine does not inflate. --cpu adds ``cpu <stage>`` rows: CPU ms
per frame (process time, numba's threads included) around improved_floam's stage functions
(the map's k-NN queries are also inside registration and map update: nested, not additive;
idle OpenMP threads spin and count, OMP_WAIT_POLICY=passive removes that);
``x small_gicp (CPU)`` is the same ratio in CPU time per frame. --variant runs each dataset
once more per LABEL:KEY=V[,...] override set (an A/B on the same scans in the same run).
"""

from __future__ import annotations

import argparse
import itertools
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from slam.bench.peers import small_gicp_odometry
from slam.config import load_config
from slam.io.folders import cloud_files, read_cloud
from slam.io.source import open_source
from slam.outputs import metrics
from slam.pipeline import Pipeline
from slam.sim.cache import ensure_sequence
from slam.types import Scan

KITTI = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti_raw_drive"
DATASETS = ("corridor", "park", "urban", "urban-hdl64", "urban-os128", "kitti-raw")


def load_scans(name: str, frames: int, tmp: Path) -> list[Scan]:
    """The scans of a dataset: a cached simulated sequence or the real KITTI-raw drive."""
    if name == "kitti-raw":
        archive = KITTI / "data_1.tar.xz"
        if not archive.is_file():
            raise SystemExit(f"missing {archive}: the shared data folder must sit beside the repo")
        with tarfile.open(archive, "r:xz") as tar:
            tar.extractall(tmp, filter="data")
        files = cloud_files(tmp / "data_1")[:frames]
        return [read_cloud(f, index=i, stamp=0.1 * i) for i, f in enumerate(files)]
    scene, _, sensor = name.partition("-")
    sim = ensure_sequence(scene, frames=frames, sensor=sensor or "vlp16")
    return [s for s in open_source(sim.bag) if isinstance(s, Scan)][:frames]


def stage_cpu_clocks() -> tuple[dict[str, float], list]:
    """CPU clocks (process time: numba's worker threads included, other processes not) around
    the improved_floam stages; returns (clocks in ms, restore list)."""
    import frontends.improved_floam as IF
    from slam.mapping.local_map import VoxelHashMap

    clocks: dict[str, float] = {}
    restore = []

    def timed(owner, attr: str, label) -> None:
        f = getattr(owner, attr)
        restore.append((owner, attr, f))

        def wrapper(*a, **kw):
            c = time.process_time()
            try:
                return f(*a, **kw)
            finally:
                key = label(a, kw) if callable(label) else label
                clocks[key] = clocks.get(key, 0.0) + 1e3 * (time.process_time() - c)

        setattr(owner, attr, wrapper)

    timed(IF, "apply_sor", "cpu sor (k-NN + statistics)")
    timed(IF, "extract_features", "cpu features (LOAM)")
    timed(IF, "kappa_from_neighbours", "cpu curvature kappa")
    timed(IF, "gicp_align", "cpu registration")
    timed(IF.ImprovedFloam, "_insert", "cpu map update")
    timed(IF, "estimate_covariances", lambda a, kw: "cpu map eq.(1)" if "neighbours" in kw
          else "cpu source covariances")  # fmt: skip
    timed(VoxelHashMap, "query", "cpu map k-NN queries")
    return clocks, restore


def profile(
    scans: list[Scan], config: str, overrides: list[str] | None = None, cpu: bool = False
) -> dict[str, float]:
    """Run the pipeline over ``scans``; ms per frame of every stage, frames/s, keyframes.
    cpu: also the CPU ms per frame of the improved_floam stages (``stage_cpu_clocks``)."""
    pipe = Pipeline(load_config(config, overrides or []))
    clocks, restore = stage_cpu_clocks() if cpu else ({}, [])
    t0 = time.perf_counter()
    try:
        state = pipe.run(scans)
    finally:
        for owner, attr, f in restore:
            setattr(owner, attr, f)
    wall = time.perf_counter() - t0
    n, n_kf = max(state.frames, 1), max(len(state.keyframes), 1)
    row: dict[str, float] = {key: value / n for key, value in sorted(clocks.items())}
    for key, value in sorted(state.diagnostic_means().items()):
        if key.endswith("_ms"):
            row[f"frontend {key[:-3]}"] = value
    for stage, seconds in sorted(state.stage_seconds.items()):
        if stage == "frontend":
            continue
        row[f"{stage} (per frame)"] = 1e3 * seconds / n
        row[f"{stage} (per keyframe)"] = 1e3 * seconds / n_kf
    for source in pipe.factor_sources:
        stats = getattr(source.plugin, "stats", None)
        for key, value in (stats() if callable(stats) else {}).items():
            if key.endswith("_ms"):
                row[f"{source.name} {key[:-3]}"] = float(value)
    m = metrics(pipe)
    for name in ("frame_ms_first100", "frame_ms_last100", "frame_cpu_ms_first100",
                 "frame_cpu_ms_last100", "frame_ms_max", "backend_ms_last100",
                 "backend_ms_max", "peak_memory_mb"):  # fmt: skip
        if m.get(name) is not None:
            row[name] = float(m[name])
    # which stage grows: CPU ms per frame over the first and last 100 frames
    for window in ("first100", "last100"):
        for stage, value in m.get(f"stage_cpu_ms_{window}", {}).items():
            row[f"{stage} CPU ({window})"] = float(value)
    row["pipeline total (per frame)"] = 1e3 * wall / n
    row["frames/s"] = n / wall
    row["keyframes"] = float(len(state.keyframes))
    row["points/scan"] = float(np.mean([len(s) for s in scans]))
    return row


def _scans(bag: Path):
    return (s for s in open_source(bag) if isinstance(s, Scan))


def growth(
    scene: str, config: str, window: int = 100, frames: int | None = None
) -> dict[str, tuple[float, float]]:
    """The front end alone over a whole simulated sequence: CPU ms per frame (this thread's
    clock, which other processes on the machine do not inflate) of each improved_floam stage
    and of the local map's k-NN queries, mean over the first and the last ``window`` frames;
    also the map's size. Answers "which stage grows with the length of the run". frames:
    a shorter cached sequence of the scene (default: the whole one)."""
    import frontends.improved_floam as IF
    from slam.mapping.local_map import VoxelHashMap
    from slam.plugins import instantiate

    clocks: dict[str, float] = {}

    def timed(owner, attr: str, label) -> None:
        f = getattr(owner, attr)

        def wrapper(*a, **kw):
            c = time.thread_time()
            try:
                return f(*a, **kw)
            finally:
                key = label(a, kw) if callable(label) else label
                clocks[key] = clocks.get(key, 0.0) + 1e3 * (time.thread_time() - c)

        setattr(owner, attr, wrapper)

    timed(IF, "neighbourhoods", "sor k-NN")
    timed(IF, "apply_sor", "sor filter")
    timed(IF, "extract_features", "features")
    timed(IF, "gicp_align", "registration")
    timed(IF.ImprovedFloam, "_insert", "map update")
    timed(IF, "estimate_covariances", lambda a, kw: "map eq.(1)" if "neighbours" in kw
          else "source covariances")  # fmt: skip
    timed(VoxelHashMap, "query", lambda a, kw: f"map k-NN k={kw.get('k', 1)}")
    section = load_config(config).frontend
    sim = ensure_sequence(scene) if frames is None else ensure_sequence(scene, frames=frames)
    warm = instantiate("slam.frontends", section, "frontend")
    for scan in list(itertools.islice(_scans(sim.bag), 3)):  # load the compiled kernels
        warm.process(scan)
    fe = instantiate("slam.frontends", section, "frontend")
    rows = []
    for scan in _scans(sim.bag):
        clocks.clear()
        c = time.thread_time()
        fe.process(scan)
        row = dict(clocks, frame=1e3 * (time.thread_time() - c))
        row["map points"] = float(fe._map_size())
        rows.append(row)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    n = len(rows)
    first, last = rows[: min(window, n)], rows[max(n - window, 0) :]
    return {k: (float(np.mean([r.get(k, 0.0) for r in first])),
                float(np.mean([r.get(k, 0.0) for r in last]))) for k in keys}  # fmt: skip


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--config", default="improved_floam_loop")
    ap.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=DATASETS)
    ap.add_argument("--markdown", action="store_true", help="print a README table")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="KEY=V")
    ap.add_argument(
        "--variant",
        nargs="+",
        default=[],
        help="LABEL:KEY=V[,KEY=V...]: each dataset once more per variant (A/B in one run)",
    )
    ap.add_argument(
        "--cpu", action="store_true", help="CPU ms per frame of each improved_floam stage"
    )
    ap.add_argument(
        "--growth",
        metavar="SCENE",
        help="instead: the front end over the whole sequence SCENE, CPU ms per stage over its"
        " first / last 100 frames",
    )
    return ap.parse_args()


def with_reference(row: dict, scans: list[Scan]) -> dict:
    """``row`` with small_gicp's odometry on the same scans, timed right after it: its
    frames/s and CPU ms per frame and the ratios to them."""
    c = time.process_time()
    t = time.perf_counter()
    small_gicp_odometry(scans)
    ref_fps = len(scans) / (time.perf_counter() - t)
    row["small_gicp odometry frames/s"] = ref_fps
    row["small_gicp odometry CPU ms/frame"] = 1e3 * (time.process_time() - c) / len(scans)
    row["x small_gicp"] = row["frames/s"] / ref_fps
    row["x small_gicp (CPU)"] = (
        row["small_gicp odometry CPU ms/frame"] / row["frame_cpu_ms_first100"]
        if row.get("frame_cpu_ms_first100")
        else float("nan")
    )
    return row


def print_columns(columns: dict[str, dict[str, float]], config: str, markdown: bool) -> None:
    """One row per stage, one column per dataset (and variant)."""
    stages = list(dict.fromkeys(k for row in columns.values() for k in row))
    names = list(columns)
    print()
    print(f"ms per frame unless stated; config {config}")
    if markdown:
        print("| stage | " + " | ".join(names) + " |")
        print("|---|" + "---:|" * len(names))
    else:
        print(f"{'stage':44s}" + "".join(f"{n:>22s}" for n in names))
    for stage in stages:
        cells = [columns[n].get(stage) for n in names]
        text = ["-" if c is None else f"{c:.2f}" for c in cells]
        if markdown:
            print(f"| {stage} | " + " | ".join(text) + " |")
        else:
            print(f"{stage:44s}" + "".join(f"{c:>22s}" for c in text))


def main() -> None:
    args = parse_args()
    if args.growth:
        config = args.config.removesuffix("_loop")
        print(f"{args.growth}, {config}: CPU ms per frame, first / last 100 frames")
        for key, (a, b) in growth(args.growth, config).items():
            change = f"{100 * (b / a - 1):+6.1f} %" if a else ""
            print(f"{key:28s} {a:12.2f} {b:12.2f}  {change}")
        return
    variants = [("", [])] + [
        (v.partition(":")[0], [x for x in v.partition(":")[2].split(",") if x])
        for v in args.variant
    ]
    columns: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.datasets:
            scans = load_scans(name, args.frames, Path(tmp))
            for label, sets in variants:
                row = profile(scans, args.config, args.overrides + sets, args.cpu)
                row = with_reference(row, scans)
                col = f"{name} ({len(scans)})" + (f" [{label}]" if label else "")
                columns[col] = row
                fps, ratio = row["frames/s"], row["x small_gicp"]
                print(f"{col}: {fps:.1f} frames/s, x{ratio:.3f}", flush=True)
    print_columns(columns, args.config, args.markdown)


if __name__ == "__main__":
    main()
