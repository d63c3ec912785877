"""A visit's re-anchor edge under the gate (``region_edges.anchor_robust``): the front end's
wide search of its submap on an old map can land on a second minimum along a corridor
(Intel: three re-anchors within 8 scans of a turn on the spot, 43 cm apart along it). A
Gaussian re-anchor is never switched off: the graph follows it and switches off the loop
edges that disagree; under the robust kernel the gate switches off the re-anchor instead."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from slam.factors import key, pose3, robust_noise
from slam.graph2d_gate import is_gated, optimize_gated
from slam.mapping.grid2d import compose2d, inverse2d, matrix_to_pose2, pose2_to_matrix
from slam.region_edges import RegionEdgeConfig, RegionEdgePlugin
from slam.types import Keyframe, RegionAnchor, RegionTag

ALIAS = 0.44  # m along the corridor: the re-anchor's second minimum


def _corridor():
    """Keyframes 0-5 out along a corridor (x, 1 m apart), 6-11 back (turned 180 deg); the
    front end's turn at the end (5 -> 6) slides 0.3 m along the corridor. Returns the true
    poses and the front end's."""
    out = [np.array([float(k), 0.0, 0.0]) for k in range(6)]
    back = [np.array([float(11 - k), 0.05, np.pi]) for k in range(6, 12)]
    true = out + back
    slide = np.array([0.3, 0.0, 0.0])
    fe = out + [compose2d(slide, p) for p in back]
    return true, fe


def _graph(anchor_robust: bool):
    """The corridor's graph: the chain (1 cm / 0.1 deg; the turn 30 cm / 1 deg), loop edges
    0 -> 11, 1 -> 10, 3 -> 8 at the truth (5 cm / 1 deg, Cauchy), and the re-anchor of
    keyframe 9 on keyframe 2's map ``ALIAS`` off along the corridor, made by the plugin."""
    true, fe = _corridor()
    factors = [gtsam.PriorFactorPose3(key(0), pose3(pose2_to_matrix(fe[0])),
                                      gtsam.noiseModel.Isotropic.Sigma(6, 1e-4))]  # fmt: skip
    for k in range(11):
        rel = compose2d(inverse2d(fe[k]), fe[k + 1])
        s_t, s_r = (0.3, np.radians(1.0)) if k == 5 else (0.01, np.radians(0.1))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, s_r, s_t, s_t, 1e-3]))
        factors.append(gtsam.BetweenFactorPose3(key(k), key(k + 1), pose3(pose2_to_matrix(rel)),
                                                noise))  # fmt: skip
    loop = robust_noise(
        gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-3, 1e-3, np.radians(1.0), 0.05, 0.05, 1e-3])),
        "cauchy",
        1.0,
    )
    for j, i in ((0, 11), (1, 10), (3, 8)):
        z = compose2d(inverse2d(true[j]), true[i])
        factors.append(gtsam.BetweenFactorPose3(key(j), key(i), pose3(pose2_to_matrix(z)), loop))
    z = compose2d(compose2d(inverse2d(true[2]), true[9]), np.array([ALIAS, 0.0, 0.0]))
    cloud = np.zeros((0, 3), dtype=np.float32)
    kfs = [Keyframe(k, float(k), k, pose2_to_matrix(fe[k]), np.eye(4), np.eye(6), cloud)
           for k in range(12)]  # fmt: skip
    kfs[9] = Keyframe(9, 9.0, 9, pose2_to_matrix(fe[9]), np.eye(4), np.eye(6), cloud,
                      region=RegionTag(visit=True, anchor=RegionAnchor(2, tuple(z))))  # fmt: skip
    plugin = RegionEdgePlugin(RegionEdgeConfig(anchor_robust=anchor_robust))
    anchors = plugin._anchor(kfs[9], robust=plugin.config.anchor_robust)
    assert len(anchors) == 1 and is_gated(anchors[0]) == anchor_robust
    factors += anchors
    start = gtsam.Values()
    for k in range(12):
        start.insert(key(k), pose3(pose2_to_matrix(fe[k])))
    return factors, start, true


def _solve(factors, start):
    params = gtsam.LevenbergMarquardtParams()
    return optimize_gated(
        factors,
        start,
        lambda g, v: gtsam.LevenbergMarquardtOptimizer(g, v, params).optimize(),
        4.0,
        3,
    )


@pytest.mark.parametrize("robust", [False, True])
def test_an_aliased_re_anchor_is_switched_off_only_under_the_kernel(robust):
    factors, start, true = _graph(robust)
    res = _solve(factors, start)
    err = [
        float(np.hypot(*(matrix_to_pose2(res.values.atPose3(key(k)).matrix())[:2] - true[k][:2])))
        for k in range(6, 12)
    ]
    anchor_off = bool(res.off[-1])
    if robust:
        assert anchor_off and not res.off[:-1].any()
        assert max(err) < 0.01
    else:
        assert not anchor_off
        assert max(err) > 0.1
