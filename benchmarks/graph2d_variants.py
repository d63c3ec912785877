"""Re-optimise a finished 2D run's keyframe graph under other noise models, offline, and
score each result on relation files: where does a graph lose its front end's local accuracy?

    .venv/bin/python benchmarks/graph2d_variants.py RUN_DIR REL.relations[,REVISIT.relations]

RUN_DIR is a ``dpcr2d`` run (``graph.g2o``, ``odometry.tum``, ``trajectory.tum``); the
relations are ``bench_2d_real.py``'s (short, revisits). Loop edges (non-consecutive keys) are
put under the Cauchy kernel and the gate of ``slam.graph2d_gate`` (all of them: the file does
not say which were Gaussian re-anchor edges), the frames follow their keyframe's correction
spread evenly per frame (``slam.spread``). Prints mean / p90 / max cm per relation file, the
largest odometry residual (claimed sigmas) and the loop edges switched off.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from slam.eval.metrics import read_trajectory
from slam.eval.relations import read_relations, relation_errors
from slam.graph2d_gate import is_loop, optimize_gated
from slam.spread import spread_corrections

CAUCHY = 1.0  # the visit graph's robust_param
GATE_SIGMA, GATE_ROUNDS = 4.0, 3  # the visit graph's defaults


def read_g2o_planar(path: Path) -> tuple[int, list[gtsam.BetweenFactorPose2]]:
    """Vertex count and the planar between factors of a ``graph.g2o`` (EDGE_SE3:QUAT with its
    upper-triangular 6x6 information; x, y, yaw kept)."""
    vertices, factors = 0, []
    for line in path.read_text().splitlines():
        p = line.split()
        if not p:
            continue
        if p[0].startswith("VERTEX"):
            vertices += 1
        elif p[0].startswith("EDGE"):
            a, b, v = int(p[1]), int(p[2]), np.array(p[3:], dtype=float)
            yaw = Rotation.from_quat(v[3:7]).as_euler("zyx")[0]
            info = np.zeros((6, 6))
            info[np.triu_indices(6)] = v[7:28]
            sig = 1.0 / np.sqrt(info[[0, 1, 5], [0, 1, 5]])
            noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
            if abs(b - a) != 1:
                noise = gtsam.noiseModel.Robust.Create(
                    gtsam.noiseModel.mEstimator.Cauchy.Create(CAUCHY), noise
                )
            factors.append(gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(v[0], v[1], yaw), noise))
    return vertices, factors


def _rebuilt(f: gtsam.BetweenFactorPose2, sigmas: np.ndarray) -> gtsam.BetweenFactorPose2:
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    if is_loop(f):
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(CAUCHY), noise
        )
    return gtsam.BetweenFactorPose2(f.keys()[0], f.keys()[1], f.measured(), noise)


def _sigmas(f: gtsam.BetweenFactorPose2) -> np.ndarray:
    model = f.noiseModel()
    return (model.noise() if isinstance(model, gtsam.noiseModel.Robust) else model).sigmas()


def variants(
    turn: np.ndarray,
) -> dict[str, Callable[[gtsam.BetweenFactorPose2], gtsam.BetweenFactorPose2]]:
    """Name -> how each factor is rewritten; turn (rad): the front end's absolute turn
    over the stretch ending at each keyframe."""

    def odometry(fn):
        return lambda f: f if is_loop(f) else _rebuilt(f, fn(f))

    def loops(k):
        return lambda f: _rebuilt(f, k * _sigmas(f)) if is_loop(f) else f

    def drift(f):
        length = float(np.hypot(f.measured().x(), f.measured().y()))
        return np.array([0.002 + 0.003 * length] * 2 + [np.radians(0.05 + 0.05 * length)])

    def turning(c):  # translation sigma widened by c (m per rad) x the stretch's turn
        def fn(f):
            s = _sigmas(f).copy()
            s[:2] = np.hypot(s[:2], c * turn[max(int(k) for k in f.keys())])
            return s

        return fn

    cap = np.array([0.01, 0.01, 0.004])
    return {
        "as given": lambda f: f,
        "odometry sigmas capped at 1 cm / 0.23 deg": odometry(
            lambda f: np.minimum(_sigmas(f), cap)
        ),
        "loop sigmas x 2": loops(2.0),
        "loop sigmas x 4": loops(4.0),
        "odometry: 2 mm + 0.3 %, 0.05 deg + 0.05 deg/m": odometry(drift),
        "odometry translation + 1 cm per rad turned": odometry(turning(0.01)),
        "odometry translation + 2 cm per rad turned": odometry(turning(0.02)),
        "odometry translation + 4 cm per rad turned": odometry(turning(0.04)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("relations", help="relation files, comma-separated")
    args = ap.parse_args()
    stamps, traj = read_trajectory(args.run / "trajectory.tum")
    _, odom = read_trajectory(args.run / "odometry.tum")
    n, factors = read_g2o_planar(args.run / "graph.g2o")
    rels = [read_relations(Path(r)) for r in args.relations.split(",")]
    # a keyframe's frame: where the run's trajectory passes through its optimised vertex
    verts = np.array(
        [np.array(line.split()[2:5], dtype=float) for line in
         (args.run / "graph.g2o").read_text().splitlines() if line.startswith("VERTEX")]
    )  # fmt: skip
    kf_index = np.array([int(np.argmin(np.linalg.norm(traj[:, :3, 3] - v, axis=1))) for v in verts])
    if np.any(np.diff(kf_index) <= 0):
        raise SystemExit(
            f"{args.run}: keyframes do not map to frames in order (a graph with anchors?)"
        )
    frame_kf = np.maximum(np.searchsorted(kf_index, np.arange(len(traj)), side="right") - 1, 0)

    def score(poses: np.ndarray) -> str:
        out = []
        for rel in rels:
            t = relation_errors(stamps, poses, rel, max_dt=1e-3).summary()["trans_m"]
            out.append(f"{100 * t['mean']:.3f} / {100 * t['p90']:.2f} / {100 * t['max']:.1f}")
        return " | ".join(out)

    prior = gtsam.PriorFactorPose2(
        0, gtsam.Pose2(), gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, 1e-4]))
    )
    print(f"{'front end (odometry.tum)':48s} {score(odom)}")
    print(f"{'the run (trajectory.tum)':48s} {score(traj)}")
    yaw = np.unwrap(np.arctan2(odom[:, 1, 0], odom[:, 0, 0]))
    turned = np.r_[0.0, np.cumsum(np.abs(np.diff(yaw)))][kf_index]
    for name, rewrite in variants(np.r_[0.0, np.diff(turned)]).items():
        graph = [prior, *(rewrite(f) for f in factors)]
        start = gtsam.Values()
        start.insert(0, gtsam.Pose2())
        chain = {int(f.keys()[0]): f.measured() for f in graph[1:] if not is_loop(f)}
        for k in range(1, n):
            start.insert(k, start.atPose2(k - 1).compose(chain[k - 1]))

        def gauss_newton(g, v):
            params = gtsam.GaussNewtonParams()
            params.setMaxIterations(30)
            params.setRelativeErrorTol(1e-6)
            return gtsam.GaussNewtonOptimizer(g, v, params).optimize()

        res = optimize_gated(graph, start, gauss_newton, GATE_SIGMA, GATE_ROUNDS)
        odo = np.array([not is_loop(f) for f in graph[1:]])
        est = {}
        for k in range(n):
            p = res.values.atPose2(k)
            m = np.eye(4)
            m[:2, :2] = [
                [np.cos(p.theta()), -np.sin(p.theta())],
                [np.sin(p.theta()), np.cos(p.theta())],
            ]
            m[:2, 3] = [p.x(), p.y()]
            est[k] = m
        base = traj[kf_index[0]] @ np.linalg.inv(est[0])
        est = {k: base @ m for k, m in est.items()}
        poses = spread_corrections(
            odom, frame_kf, {k: int(i) for k, i in enumerate(kf_index)}, est, np.ones(len(traj))
        )
        worst = float(np.nanmax(res.sigmas[1:][odo]))
        print(
            f"{name:48s} {score(poses)}  odometry max {worst:.2f} sigma, {int(res.off.sum())} off"
        )


if __name__ == "__main__":
    main()
