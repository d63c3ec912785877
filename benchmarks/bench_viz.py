"""Cost of the live view: the same run with and without the Rerun observer (target < 5 %
of the frame rate when on; nothing when off: the pipeline only loops over an empty list).

Runs ``--config`` (default improved_floam_loop) on the first ``--frames`` scans of the urban
drive (VLP-16, realistic errors), alternating off / on ``--reps`` times in this process
(the numba kernels warm), the view recorded to an .rrd file in a temporary folder (the same
stream ``--viz`` sends to a viewer). Reports per frame: wall and CPU ms of the whole run
loop (CPU: this process, every thread, so rerun's own serialising and writing thread is
counted), the ratio on / off, and the time spent inside the observer's calls.

    .venv/bin/python benchmarks/bench_viz.py [--frames 150] [--reps 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from slam.config import load_config
from slam.io.source import open_source
from slam.pipeline import Pipeline
from slam.sim.cache import ensure_sequence
from slam.viz.rerun_view import RerunObserver, open_stream
from slam.warmup import warm_up


class TimedObserver:
    """Forwards every observer call, summing the wall and CPU seconds spent inside them."""

    def __init__(self, inner: Any):
        self.inner, self.wall, self.cpu = inner, 0.0, 0.0

    def _timed(self, name: str, *args: Any) -> None:
        t0, c0 = time.perf_counter(), time.process_time()
        getattr(self.inner, name)(*args)
        self.wall += time.perf_counter() - t0
        self.cpu += time.process_time() - c0

    def on_frame(self, *a: Any) -> None:
        self._timed("on_frame", *a)

    def on_keyframe(self, *a: Any) -> None:
        self._timed("on_keyframe", *a)

    def on_loop(self, *a: Any) -> None:
        self._timed("on_loop", *a)

    def on_optimised(self, *a: Any) -> None:
        self._timed("on_optimised", *a)

    def close(self) -> None:
        self._timed("close")


def one_run(bag: Path, config_name: str, frames: int, rrd: Path | None) -> dict[str, float]:
    """Wall and CPU seconds of the run loop (plus closing the recording) per frame."""
    config = load_config(config_name)
    config.source = dataclasses.replace(config.source, max_frames=frames)
    observers = [TimedObserver(RerunObserver(open_stream(rrd)))] if rrd else []
    pipeline = Pipeline(config, observers=observers)
    warm_up(config.frontend)
    source = open_source(bag, topic=config.source.topic)
    t0, c0 = time.perf_counter(), time.process_time()
    pipeline.run(source, max_frames=frames)
    for obs in observers:
        obs.close()  # the file is complete: rerun's writing is inside the measured time
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    n = pipeline.state.frames
    out = {"frames": n, "wall_ms": 1e3 * wall / n, "cpu_ms": 1e3 * cpu / n}
    if observers:
        out["obs_wall_ms"] = 1e3 * observers[0].wall / n
        out["obs_cpu_ms"] = 1e3 * observers[0].cpu / n
        out["rrd_mb"] = rrd.stat().st_size / 2**20
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--config", default="improved_floam_loop")
    args = p.parse_args()
    seq = ensure_sequence("urban", frames=args.frames)
    rows: dict[str, list[dict[str, float]]] = {"off": [], "on": []}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps):
            rows["off"].append(one_run(seq.bag, args.config, args.frames, None))
            rrd = Path(tmp) / f"view{rep}.rrd"
            rows["on"].append(one_run(seq.bag, args.config, args.frames, rrd))
    mean = {k: {m: float(np.mean([r[m] for r in v])) for m in v[0]} for k, v in rows.items()}
    off, on = mean["off"], mean["on"]
    print(f"{args.config}, urban drive, {int(off['frames'])} frames, {args.reps} reps each")
    print(f"{'':4} {'wall ms/frame':>14} {'CPU ms/frame':>13}")
    for name in ("off", "on"):
        print(f"{name:4} {mean[name]['wall_ms']:14.1f} {mean[name]['cpu_ms']:13.1f}")
    wall, cpu = on["wall_ms"] / off["wall_ms"], on["cpu_ms"] / off["cpu_ms"]
    print(f"on / off: wall {wall:.3f}x, CPU {cpu:.3f}x")
    print(
        f"inside the observer calls: {on['obs_wall_ms']:.2f} ms wall, {on['obs_cpu_ms']:.2f} ms "
        f"CPU per frame = {100 * on['obs_cpu_ms'] / off['cpu_ms']:.1f} % of the frame's CPU; "
        f".rrd {on['rrd_mb']:.1f} MiB"
    )


if __name__ == "__main__":
    main()
