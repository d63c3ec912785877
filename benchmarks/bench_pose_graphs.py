"""Speed and final error of iSAM2 fed pose by pose vs batch Levenberg-Marquardt (the baseline)
on the standard g2o pose graphs, and the per-keyframe cost of the pipeline's back end on a
synthetic drive of N keyframes with loop closures (does it grow with the run?).

    .venv/bin/python benchmarks/bench_pose_graphs.py [--graphs intel parking-garage sphere2500]
    .venv/bin/python benchmarks/bench_pose_graphs.py --synthetic 1000 [--laps 3]

Errors are GTSAM's 0.5 * sum of squared whitened residuals over the file's edges.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gtsam
import numpy as np

from backends.batch import BatchBackend, BatchConfig
from backends.isam2 import Isam2Backend, Isam2Config, isam2_params
from slam.factors import key, robust_noise
from slam.pose_graph import batch_lm, incremental_isam2, read_g2o, total_error

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pose_graphs"


def synthetic_drive(
    n: int, laps: int = 3, loop_every: int = 10, seed: int = 0
) -> tuple[list[gtsam.Pose3], list[list], list[gtsam.Pose3]]:
    """A car driving ``laps`` laps of a 2 x 1 block loop (``n`` keyframes, ~1.4 m apart, as
    the 1.2 km urban drive's 871 keyframes), with a gently climbing road.

    Returns (truth, factors per keyframe, odometry-chained initial guesses). Odometry:
    BetweenFactorPose3 with the front end's typical sigmas (1 mrad, 1 cm); after the first
    lap every ``loop_every``-th keyframe gets a Huber-robust loop factor to the same place
    one lap earlier (5 cm / 0.5 deg), as the loop plugin adds them.
    """
    rng = np.random.default_rng(seed)
    per_lap = n / laps
    s = np.arange(n) / per_lap  # laps done
    a = 2 * np.pi * s
    # a rounded rectangle 300 x 150 m: superellipse
    x = 150.0 * np.sign(np.cos(a)) * np.abs(np.cos(a)) ** 0.3
    y = 75.0 * np.sign(np.sin(a)) * np.abs(np.sin(a)) ** 0.3
    z = 2.0 * np.sin(a)
    yaw = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    truth = [
        gtsam.Pose3(gtsam.Rot3.Yaw(float(yaw[i])), gtsam.Point3(x[i], y[i], z[i])) for i in range(n)
    ]
    odo_sigmas = np.array([1e-3] * 3 + [1e-2] * 3)
    odo_noise = gtsam.noiseModel.Diagonal.Sigmas(odo_sigmas)
    loop_sigmas = np.array([np.radians(0.5)] * 3 + [0.05] * 3)
    loop_noise = robust_noise(gtsam.noiseModel.Diagonal.Sigmas(loop_sigmas), "huber", 1.345)
    prior = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
    factors: list[list] = [[gtsam.PriorFactorPose3(key(0), truth[0], prior)]]
    initial = [truth[0]]
    for i in range(1, n):
        rel = truth[i - 1].between(truth[i])
        measured = rel.compose(gtsam.Pose3.Expmap(rng.normal(0.0, odo_sigmas)))
        fs = [gtsam.BetweenFactorPose3(key(i - 1), key(i), measured, odo_noise)]
        j = int(round(i - per_lap))
        if j >= 0 and i % loop_every == 0:
            loop = (
                truth[j]
                .between(truth[i])
                .compose(gtsam.Pose3.Expmap(rng.normal(0.0, loop_sigmas / 3)))
            )
            fs.append(gtsam.BetweenFactorPose3(key(j), key(i), loop, loop_noise))
        factors.append(fs)
        initial.append(initial[-1].compose(measured))
    return truth, factors, initial


def run_synthetic(
    factors: list[list], initial: list[gtsam.Pose3], config: Isam2Config, cpu: bool = False
) -> tuple[np.ndarray, dict[int, gtsam.Pose3], float]:
    """Feed the drive keyframe by keyframe as the pipeline does (initial guess: previous
    estimate composed with the odometry); returns ms per update, final estimate, final s.
    ``cpu``: ms of process CPU time instead of wall time (a loaded machine's wall time is
    mostly waiting for a core)."""
    n = len(factors)
    backend = Isam2Backend(config)
    ms = np.zeros(n)
    guess = initial[0]
    clock = time.process_time if cpu else time.perf_counter
    for i, fs in enumerate(factors):
        t0 = clock()
        backend.update(fs, {i: guess}, loop_closed=len(fs) > 1)
        if i + 1 < n:
            guess = backend.pose(i).compose(factors[i + 1][0].measured())
        ms[i] = 1e3 * (clock() - t0)
    t0 = time.perf_counter()
    est = backend.finalize()
    return ms, est, time.perf_counter() - t0


def bench_synthetic(
    n: int, laps: int, loop_every: int, configs: list[Isam2Config], cpu: bool = False
) -> None:
    """Per-keyframe iSAM2 update at 1..n keyframes for each config, against batch LM on the
    whole graph once (the baseline, measured in the same run)."""
    truth, factors, initial = synthetic_drive(n, laps, loop_every)
    is_loop = np.array([len(fs) > 1 for fs in factors])
    batch = BatchBackend(BatchConfig(relative_error_tol=1e-10, absolute_error_tol=1e-10))
    for i, fs in enumerate(factors):
        batch.update(fs, {i: initial[i]})
    t0 = time.perf_counter()
    opt = batch.finalize()
    t_batch = time.perf_counter() - t0
    true = np.array([p.translation() for p in truth])
    p_batch = np.array([opt[i].translation() for i in range(n)])
    print(
        f"synthetic drive: {n} keyframes, {laps} laps, {int(is_loop.sum())} loop factors; "
        f"batch LM once at the end: {t_batch:.2f} s, max error vs truth "
        f"{np.abs(p_batch - true).max():.3f} m (odometry "
        f"{np.abs(np.array([p.translation() for p in initial]) - true).max():.2f} m)"
    )
    for config in configs:
        ms, est, t_final = run_synthetic(factors, initial, config, cpu)
        p_isam = np.array([est[i].translation() for i in range(n)])
        print(
            f"\niSAM2 relinearize_threshold={config.relinearize_threshold} relinearize_skip="
            f"{config.relinearize_skip} extra_updates_after_loop="
            f"{config.extra_updates_after_loop} partial_relinearization_check="
            f"{config.partial_relinearization_check}" + (" (CPU ms)" if cpu else "")
        )
        print(f"{'keyframes':<12}{'mean ms':>9}{'max ms':>9}{'loop mean':>11}{'no-loop mean':>14}")
        for lo in range(0, n, 100):
            part = slice(lo, min(lo + 100, n))
            loops, plain = ms[part][is_loop[part]], ms[part][~is_loop[part]]
            print(
                f"{lo:>5}-{min(lo + 100, n) - 1:<6}{ms[part].mean():>9.2f}{ms[part].max():>9.2f}"
                f"{loops.mean() if len(loops) else float('nan'):>11.2f}"
                f"{plain.mean() if len(plain) else float('nan'):>14.2f}"
            )
        print(
            f"total {ms.sum() / 1e3:.2f} s + final {t_final:.3f} s = "
            f"{(ms.sum() / 1e3 + t_final) / t_batch:.2f} x batch; last-100 / first-100 mean "
            f"{ms[-100:].mean() / ms[:100].mean():.1f}; max error vs truth "
            f"{np.abs(p_isam - true).max():.3f} m, max gap to batch "
            f"{np.abs(p_isam - p_batch).max() * 1e3:.1f} mm"
        )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--graphs", nargs="+", default=["intel", "parking-garage", "sphere2500"])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--relinearize-threshold", type=float, default=None)
    parser.add_argument("--relinearize-skip", type=int, default=None)
    parser.add_argument("--extra-updates", type=int, default=None)
    parser.add_argument(
        "--synthetic", type=int, default=0, help="keyframes of the synthetic drive (0 = g2o)"
    )
    parser.add_argument("--laps", type=int, default=3)
    parser.add_argument(
        "--variants",
        nargs="*",
        default=[],
        help="more iSAM2 configs: threshold:skip:extra[:partial 0/1]",
    )
    parser.add_argument("--cpu", action="store_true", help="time updates in process CPU ms")
    parser.add_argument("--loop-every", type=int, default=10)
    return parser.parse_args(argv)


def synthetic_configs(args: argparse.Namespace) -> list[Isam2Config]:
    """The iSAM2 config of the command line and one per ``--variants`` entry."""
    over = {
        "relinearize_threshold": args.relinearize_threshold,
        "relinearize_skip": args.relinearize_skip,
        "extra_updates_after_loop": args.extra_updates,
    }
    configs = [Isam2Config(**{k: v for k, v in over.items() if v is not None})]
    for text in args.variants:  # threshold:skip:extra[:partial]
        thr, skip, extra, *partial = text.split(":")
        configs.append(
            Isam2Config(
                float(thr),
                int(skip),
                True,
                int(extra),
                partial_relinearization_check=bool(int(partial[0])) if partial else False,
            )  # fmt: skip
        )
    return configs


def bench_g2o(graphs: list[str], data: Path, config: Isam2Config) -> None:
    """Batch LM against iSAM2 (pose by pose) on each g2o benchmark graph: time and error."""
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
    for name in graphs:
        path = data / f"{name}.g2o"
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


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.synthetic:
        configs = synthetic_configs(args)
        bench_synthetic(args.synthetic, args.laps, args.loop_every, configs, args.cpu)
        return 0
    config = Isam2Config(
        relinearize_threshold=args.relinearize_threshold or 0.1,
        relinearize_skip=args.relinearize_skip or 10,
    )
    bench_g2o(args.graphs, args.data, config)
    return 0


if __name__ == "__main__":
    sys.exit(main())
