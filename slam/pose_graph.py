"""Pose graphs in g2o format: export of a run's graph, reading the standard data sets,
and the two ways of optimising them (iSAM2 fed pose by pose, batch Levenberg-Marquardt).

g2o files carry no prior, so the optimisers here anchor the first pose with a tiny prior
at its initial value. 2D graphs use Pose2 factors, 3D graphs Pose3 factors.
"""

from __future__ import annotations

import time
from pathlib import Path

import gtsam

from slam.errors import InputError, SlamError
from slam.factors import key

ANCHOR_SIGMA = 1e-6

_BETWEEN = (gtsam.BetweenFactorPose2, gtsam.BetweenFactorPose3)
_3D_FACTORS = (gtsam.BetweenFactorPose3, gtsam.PriorFactorPose3)


def values_from_poses(poses: dict[int, gtsam.Pose3]) -> gtsam.Values:
    """gtsam.Values keyed by ``slam.factors.key(id)`` from keyframe id -> Pose3."""
    values = gtsam.Values()
    for kf_id, pose in poses.items():
        values.insert(key(kf_id), pose)
    return values


def detect_3d(path: str | Path) -> bool:
    """True if the g2o file holds SE3 vertices/edges, False for SE2."""
    path = Path(path)
    try:
        with path.open() as handle:
            for line in handle:
                tag = line.split(maxsplit=1)[0] if line.strip() else ""
                if tag.startswith(("VERTEX_SE3", "EDGE_SE3")):
                    return True
                if tag.startswith(("VERTEX_SE2", "EDGE_SE2")):
                    return False
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read g2o file {path}: {exc}") from exc
    raise InputError(f"{path}: no VERTEX_SE2/SE3 or EDGE_SE2/SE3 lines, not a g2o pose graph")


def read_g2o(
    path: str | Path, is3d: bool | None = None
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Factor graph (between factors) and initial values of a g2o file; is3d=None detects it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"g2o file not found: {path}")
    if is3d is None:
        is3d = detect_3d(path)
    try:
        graph, values = gtsam.readG2o(str(path), is3d)
    except (RuntimeError, ValueError) as exc:
        raise InputError(f"{path}: cannot parse g2o: {exc}") from exc
    if values.size() == 0:
        raise InputError(f"{path}: no {'SE3' if is3d else 'SE2'} vertices found")
    return graph, values


def write_g2o(path: str | Path, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> int:
    """Write the between factors and the poses of ``values`` as g2o; returns the edge count.

    g2o has no priors or unary factors (position fixes, ...): those are left out. Robust
    noise models are written as their underlying Gaussian. Vertex ids are the symbols'
    indices (keyframe ``x<i>`` -> ``i``, GTSAM's convention), so they must be unique.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"cannot write g2o file {path}: folder {path.parent} does not exist")
    out_graph = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        factor = graph.at(i)
        if not isinstance(factor, _BETWEEN):
            continue
        noise = factor.noiseModel()
        if isinstance(noise, gtsam.noiseModel.Robust):
            noise = noise.noise()
        a, b = factor.keys()
        out_graph.add(type(factor)(a, b, factor.measured(), noise))
    out_values = gtsam.Values()
    ids: set[int] = set()
    for k in values.keys():
        pose = _any_pose(values, k)
        if pose is None:  # landmarks and other variables have no g2o vertex here
            continue
        index = gtsam.Symbol(k).index()
        if index in ids:
            raise SlamError(f"cannot write g2o file {path}: two poses share vertex id {index}")
        ids.add(index)
        out_values.insert(k, pose)
    try:
        gtsam.writeG2o(out_graph, out_values, str(path))
    except (RuntimeError, ValueError) as exc:
        raise SlamError(f"cannot write g2o file {path}: {exc}") from exc
    return out_graph.size()


def _any_pose(values: gtsam.Values, k: int) -> gtsam.Pose3 | gtsam.Pose2 | None:
    for getter in (values.atPose3, values.atPose2):
        try:
            return getter(k)
        except RuntimeError:
            continue
    return None


def _graph_is_3d(graph: gtsam.NonlinearFactorGraph) -> bool:
    for i in range(graph.size()):
        factor = graph.at(i)
        if isinstance(factor, _3D_FACTORS):
            return True
        if isinstance(factor, (gtsam.BetweenFactorPose2, gtsam.PriorFactorPose2)):
            return False
    raise InputError("pose graph holds no Pose2/Pose3 between or prior factors")


def _pose(values: gtsam.Values, k: int, is3d: bool):
    return values.atPose3(k) if is3d else values.atPose2(k)


def anchor_prior(values: gtsam.Values, k: int, is3d: bool, sigma: float = ANCHOR_SIGMA):
    """Tiny prior holding pose ``k`` at its value in ``values`` (fixes the gauge)."""
    if is3d:
        return gtsam.PriorFactorPose3(
            k, values.atPose3(k), gtsam.noiseModel.Isotropic.Sigma(6, sigma)
        )
    return gtsam.PriorFactorPose2(k, values.atPose2(k), gtsam.noiseModel.Isotropic.Sigma(3, sigma))


def anchored(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, is3d: bool | None = None
) -> gtsam.NonlinearFactorGraph:
    """A copy of ``graph`` with a prior on its first (smallest) key."""
    if is3d is None:
        is3d = _graph_is_3d(graph)
    out = gtsam.NonlinearFactorGraph(graph)
    out.add(anchor_prior(values, min(values.keys()), is3d))
    return out


def batch_lm(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    params: gtsam.LevenbergMarquardtParams | None = None,
    anchor: bool = True,
) -> tuple[gtsam.Values, float]:
    """Levenberg-Marquardt optimum of the whole graph and the seconds it took.

    params: gtsam's own (e.g. ``backends.batch.lm_params(config)``); default: gtsam's."""
    start = time.perf_counter()
    full = anchored(graph, initial) if anchor else graph
    try:
        result = gtsam.LevenbergMarquardtOptimizer(
            full, initial, params or gtsam.LevenbergMarquardtParams()
        ).optimize()
    except (RuntimeError, ValueError, IndexError) as exc:
        raise SlamError(f"batch optimisation failed: {exc}") from exc
    return result, time.perf_counter() - start


def incremental_isam2(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    is3d: bool | None = None,
    params: gtsam.ISAM2Params | None = None,
    anchor: bool = True,
) -> tuple[gtsam.Values, float]:
    """Feed the graph to iSAM2 pose by pose in key order, one update per pose.

    params: gtsam's own (e.g. ``backends.isam2.isam2_params(config)``); default: gtsam's.

    Each new pose gets the factors whose keys are then all present; its initial guess is
    the current estimate of a connected earlier pose composed with the connecting edge
    (the file's value when none connects). Returns the final estimate and the seconds.
    """
    start = time.perf_counter()
    if is3d is None:
        is3d = _graph_is_3d(graph)
    keys = sorted(initial.keys())
    if not keys:
        raise InputError("pose graph has no poses")
    order = {k: i for i, k in enumerate(keys)}
    buckets: list[list] = [[] for _ in keys]
    if anchor:
        buckets[0].append(anchor_prior(initial, keys[0], is3d))
    for i in range(graph.size()):
        factor = graph.at(i)
        try:
            last = max(order[k] for k in factor.keys())
        except KeyError as exc:
            raise InputError(f"factor {i} refers to a pose without an initial value") from exc
        buckets[last].append(factor)

    isam = gtsam.ISAM2(params or gtsam.ISAM2Params())
    pose_of = isam.calculateEstimatePose3 if is3d else isam.calculateEstimatePose2
    guesses: dict[int, object] = {}
    try:
        for i, k in enumerate(keys):
            new_factors = gtsam.NonlinearFactorGraph()
            guess = None
            for factor in buckets[i]:
                new_factors.add(factor)
                if guess is None and isinstance(factor, _BETWEEN):
                    a, b = factor.keys()
                    if b == k and a in guesses:
                        guess = guesses[a].compose(factor.measured())
                    elif a == k and b in guesses:
                        guess = guesses[b].compose(factor.measured().inverse())
            if guess is None:
                guess = _pose(initial, k, is3d)
            new_values = gtsam.Values()
            new_values.insert(k, guess)
            isam.update(new_factors, new_values)
            # A loop closure moves the new pose: refresh its guess from the solver then.
            guesses[k] = pose_of(k) if len(buckets[i]) > 1 else guess
        result = isam.calculateEstimate()
    except (RuntimeError, ValueError, IndexError) as exc:
        raise SlamError(f"iSAM2 failed on the pose graph: {exc}") from exc
    return result, time.perf_counter() - start


def total_error(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, anchor: bool = False
) -> float:
    """GTSAM error 0.5 * sum of squared whitened residuals (optionally with the anchor)."""
    return float((anchored(graph, values) if anchor else graph).error(values))
