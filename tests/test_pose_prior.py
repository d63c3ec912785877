"""The tracked prediction as a Gaussian prior of GICP (``slam.registration.pose_prior``): it
holds what the scan does not observe and leaves the rest to the scan."""

import numpy as np
import pytest

from slam.errors import ConfigError
from slam.registration.gicp import GicpConfig, gicp_align
from slam.registration.pose_prior import MotionPriorConfig, PosePrior
from slam.registration.se3 import se3_exp, transform


def corridor(rng, n=8000):
    """A 40 m corridor along x: floor and two walls 4 m apart, nothing across it."""
    x = rng.uniform(-20, 20, n)
    u = rng.uniform(size=n)
    face = rng.integers(0, 3, n)
    p = np.c_[x, (u - 0.5) * 4, np.zeros(n)]
    p[face == 1] = np.c_[x, np.full(n, -2.0), u * 3][face == 1]
    p[face == 2] = np.c_[x, np.full(n, 2.0), u * 3][face == 2]
    return p + rng.normal(0, 0.003, p.shape)


def room(rng, n=6000):
    """A closed 12 x 8 x 3 m room: every direction observed."""
    p = corridor(rng, n)
    p[:, 0] = p[:, 0] * 0.3
    ends = rng.integers(0, 4, n) == 0
    p[ends] = np.c_[np.sign(rng.uniform(-1, 1, ends.sum())) * 6, p[ends, 1], p[ends, 2]]
    return p


def test_residual_is_the_solvers_tangent():
    T0 = se3_exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, -0.5]))
    xi = np.array([1e-3, -2e-3, 5e-4, 0.02, -0.01, 0.03])
    prior = PosePrior.isotropic(T0, 0.02, np.radians(0.2))
    assert np.allclose(prior.residual(T0 @ se3_exp(xi)), xi, atol=1e-4)  # first order
    T = T0 @ se3_exp(xi)
    H, b, cost = prior.linearised(T)
    assert np.allclose(np.diag(H), [np.radians(0.2) ** -2] * 3 + [0.02**-2] * 3)
    d = prior.residual(T)
    assert cost == pytest.approx(d @ H @ d) == pytest.approx(prior.cost(T))
    assert np.allclose(b, H @ d)


def test_the_prior_holds_only_what_the_scan_does_not_observe():
    rng = np.random.default_rng(3)
    target = corridor(rng)
    T_true = se3_exp(np.array([0.0, 0.0, np.radians(1.0), 0.30, 0.05, 0.02]))
    source = transform(np.linalg.inv(T_true), corridor(rng))
    # the prediction: right along the corridor, 8 cm and 0.5 deg off across it
    T_pred = se3_exp(np.array([0.0, 0.0, np.radians(1.5), 0.30, 0.13, 0.02]))
    prior = MotionPriorConfig(enabled=True).prior(T_pred, 0.1)  # 2 cm, 0.2 deg
    res = gicp_align(source, target, T_pred, GicpConfig(), prior=prior)
    D = np.linalg.inv(T_true) @ res.T_target_source
    assert abs(D[1, 3]) < 0.005 and abs(D[2, 3]) < 0.005  # across: the scan's
    assert abs(np.degrees(np.arctan2(D[1, 0], D[0, 0]))) < 0.05
    assert abs(D[0, 3]) < 0.01  # along: the prediction's
    # the information returned is the scan's own: nothing along the corridor
    w = np.linalg.eigvalsh(res.H[3:, 3:])
    assert w[0] < 0.01 * w[-1]


def test_where_everything_is_observed_the_prior_changes_nothing():
    rng = np.random.default_rng(4)
    target = room(rng)
    T_true = se3_exp(np.array([0.01, -0.02, 0.05, 0.20, -0.10, 0.03]))
    source = transform(np.linalg.inv(T_true), room(rng))
    T_pred = T_true @ se3_exp(np.array([0.0, 0.0, np.radians(0.3), 0.03, -0.02, 0.0]))
    free = gicp_align(source, target, T_pred, GicpConfig())
    held = gicp_align(
        source, target, T_pred, GicpConfig(), prior=MotionPriorConfig().prior(T_pred, 0.1)
    )
    D = np.linalg.inv(free.T_target_source) @ held.T_target_source
    assert np.linalg.norm(D[:3, 3]) < 1e-3  # within 1 mm of the scan's own answer
    assert (
        np.linalg.norm(np.linalg.inv(T_true)[:3, :3] @ free.T_target_source[:3, :3] - np.eye(3))
        < 2e-3
    )


def test_config_is_checked():
    with pytest.raises(ConfigError):
        MotionPriorConfig(acceleration=0.0)


def test_only_the_tracked_prediction_is_a_prior(urban_short):
    """The frame loop offers the prior only while registering from a tracked velocity: not
    at the first scans, not in the start-in-motion search; the run stays on the truth."""
    from itertools import islice

    from slam.config import load_config
    from slam.eval.metrics import EvalOptions, evaluate_arrays
    from slam.io.source import open_source
    from slam.plugins import instantiate
    from slam.types import Scan

    scans = list(islice((s for s in open_source(urban_short.bag) if isinstance(s, Scan)), 30))
    cfg = load_config("improved_floam", []).frontend  # on by default
    fe = instantiate("slam.frontends", cfg, "frontend")
    seen, estimate = [], fe._estimate

    def recording(scan, T_pred, timings, wide):
        seen.append((scan.index, fe.tracked_horizon, fe._motion_prior(T_pred)))
        return estimate(scan, T_pred, timings, wide)

    fe._estimate = recording
    poses = np.stack([fe.process(s).pose for s in scans])
    # frame 0 starts the map; frame 1 is the first-motion search (its own starts, no
    # velocity yet); every later frame registers from the tracked prediction
    assert seen[0][:2] == (0, None) and 1 not in {i for i, _, _ in seen}
    tracked = [(h, p) for i, h, p in seen if i >= 2]
    assert len(tracked) == len(scans) - 2
    assert all(h == pytest.approx(0.1, rel=1e-3) for h, _ in tracked)
    sigma_t = 1 / np.sqrt(tracked[0][1].information[3, 3])
    assert sigma_t == pytest.approx(0.02, rel=1e-3)  # 2 m/s^2 x (0.1 s)^2
    _, gt = urban_short.read_ground_truth()
    res = evaluate_arrays(None, poses, None, gt[: len(poses)], EvalOptions())
    assert res.ape_trans["rmse"] < 0.03
