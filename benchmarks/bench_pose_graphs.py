"""Speed and final error of iSAM2 fed pose by pose vs batch Levenberg-Marquardt (the baseline)
on the standard g2o pose graphs.

    .venv/bin/python benchmarks/bench_pose_graphs.py [--graphs intel parking-garage sphere2500]

Errors are GTSAM's 0.5 * sum of squared whitened residuals over the file's edges.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from backends.isam2 import Isam2Config, isam2_params
from slam.pose_graph import batch_lm, incremental_isam2, read_g2o, total_error

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pose_graphs"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--graphs", nargs="+", default=["intel", "parking-garage", "sphere2500"])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--relinearize-threshold", type=float, default=0.1)
    parser.add_argument("--relinearize-skip", type=int, default=10)
    args = parser.parse_args(argv)
    config = Isam2Config(
        relinearize_threshold=args.relinearize_threshold, relinearize_skip=args.relinearize_skip
    )
    print(
        f"iSAM2: relinearize_threshold={config.relinearize_threshold} "
        f"relinearize_skip={config.relinearize_skip}; baseline: batch LM"
    )
    header = (
        f"{'graph':<16}{'poses':>7}{'edges':>7}{'initial err':>14}{'batch s':>9}"
        f"{'batch err':>12}{'iSAM2 s':>9}{'iSAM2 err':>12}{'err gap %':>10}"
        f"{'time x':>8}{'ms/pose':>9}"
    )
    print(header)
    print("-" * len(header))
    for name in args.graphs:
        path = args.data / f"{name}.g2o"
        if not path.is_file():
            print(f"{name:<16}missing: {path}")
            continue
        graph, initial = read_g2o(path)
        batch, t_batch = batch_lm(graph, initial)
        isam, t_isam = incremental_isam2(graph, initial, params=isam2_params(config))
        e_init, e_batch, e_isam = (total_error(graph, v) for v in (initial, batch, isam))
        gap = 100.0 * (e_isam - e_batch) / e_batch
        print(
            f"{name:<16}{initial.size():>7}{graph.size():>7}{e_init:>14.4g}{t_batch:>9.2f}"
            f"{e_batch:>12.6g}{t_isam:>9.2f}{e_isam:>12.6g}{gap:>10.3f}{t_isam / t_batch:>8.1f}"
            f"{1000 * t_isam / initial.size():>9.2f}",
            flush=True,
        )
    print("time x = iSAM2 seconds / batch seconds; ms/pose = iSAM2 mean latency per pose")
    print("(iSAM2 has an estimate after every pose, batch only once at the end)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
