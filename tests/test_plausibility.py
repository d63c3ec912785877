"""The registration gate: each test of ``implausibility`` fires alone, relative to the run's
own running normal (so the same gate holds on a dense indoor and a vegetated outdoor scene)."""

import numpy as np
import pytest

from slam.errors import ConfigError
from slam.registration.gicp import RegistrationResult, se3_exp
from slam.registration.plausibility import (
    PlausibilityConfig,
    RunningNormal,
    implausibility,
    relaxed,
)

DT = 0.1


def result(rmse=0.2, inliers=1800, source=2000, stop="step"):
    return RegistrationResult(
        T_target_source=np.eye(4),
        H=np.eye(6),
        b=np.zeros(6),
        cost=1.0,
        fitness=rmse**2,
        rmse=rmse,
        num_inliers=inliers,
        num_source=source,
        iterations=30 if stop == "max_iterations" else 4,
        converged=stop in ("step", "fitness"),
        stop_reason=stop,
    )


def normal_of(scale: float) -> RunningNormal:
    """A normal of 20 registrations at RMSE ~ scale (m), 90 % inliers, information ~ 30."""
    rng = np.random.default_rng(0)
    n = RunningNormal(50)
    for _ in range(20):
        n.add(result(scale * rng.uniform(0.9, 1.1), int(rng.integers(1700, 1900))), 30.0)
    return n


def step(v=1.2, yaw_rate_deg=10.0, dt=DT):
    return se3_exp(np.array([0, 0, np.radians(yaw_rate_deg) * dt, v * dt, 0, 0]))


@pytest.mark.parametrize("scale", [0.02, 0.2])  # a crisp indoor and a vegetated outdoor scene
def test_gate_is_relative_to_the_scene(scale):
    cfg = PlausibilityConfig()
    n = normal_of(scale)

    def why(res, info=30.0):
        return implausibility(res, info, n, step(), np.eye(4), DT, cfg)

    assert why(result(1.5 * scale)) is None
    assert "fitness" in why(result(4.0 * scale))
    assert "inlier share" in why(result(scale, inliers=800))
    assert "correspondences" in why(result(scale, inliers=130, source=140))
    assert "information" in why(result(scale), info=0.004)
    assert why(result(scale), info=0.8) is None  # a corridor's weak axis: 0.026 x normal
    # an iteration cap / stall is believed only when it fits as well as usual
    assert why(result(scale, stop="max_iterations")) is None
    assert "max_iterations" in why(result(1.8 * scale, stop="max_iterations"))
    assert "stalled" in why(result(1.8 * scale, stop="stalled"))


def test_motion_bounds_are_physical():
    cfg = PlausibilityConfig()
    n = normal_of(0.1)
    ok = result(0.1)
    assert implausibility(ok, 30.0, n, step(v=15.0), np.eye(4), DT, cfg) is None  # a car
    assert "speed" in implausibility(ok, 30.0, n, step(v=45.0), np.eye(4), DT, cfg)
    assert "turn rate" in implausibility(ok, 30.0, n, step(yaw_rate_deg=200), np.eye(4), DT, cfg)
    off = se3_exp(np.array([0, 0, 0, 0.6, 0, 0]))  # 0.6 m off the constant-velocity prediction
    assert "prediction" in implausibility(ok, 30.0, n, step(), off, DT, cfg)
    # after 1 s without a trusted pose the prediction may have drifted that far
    assert implausibility(ok, 30.0, n, step(dt=1.0), off, 1.0, cfg) is None
    # improved FLOAM's floor: a car braking at 1 g leaves the prediction by 5 cm in one
    # 10 Hz frame: believed; a registration sliding 0.25 m along a corridor is not
    from frontends.improved_floam import ImprovedFloamConfig

    tight = ImprovedFloamConfig().plausibility
    assert tight.prediction_floor == 0.1 and cfg.prediction_floor == 0.3
    brake = se3_exp(np.array([0, 0, 0, 0.5 * 9.81 * DT**2, 0, 0]))
    assert implausibility(ok, 30.0, n, step(v=15.0), brake, DT, tight) is None
    slide = se3_exp(np.array([0, 0, 0, 0.25, 0, 0]))
    assert "prediction" in implausibility(ok, 30.0, n, step(), slide, DT, tight)
    assert implausibility(ok, 30.0, n, step(), slide, DT, cfg) is None  # the common floor


def test_no_normal_yet_and_disabled():
    cfg = PlausibilityConfig()
    empty = RunningNormal(50)
    assert implausibility(result(5.0, inliers=10), 1e-9, empty, step(), np.eye(4), DT, cfg) is None
    capped = result(0.1, stop="max_iterations")
    assert "max_iterations" in implausibility(capped, 30.0, empty, step(), np.eye(4), DT, cfg)
    off = PlausibilityConfig(enabled=False)
    assert implausibility(capped, 30.0, empty, step(v=99), np.eye(4), DT, off) is None
    with pytest.raises(ConfigError):
        PlausibilityConfig(min_support_ratio=1.5)
    with pytest.raises(ConfigError):
        PlausibilityConfig(max_fitness_ratio=0.5)


def test_running_normal_is_a_windowed_median():
    n = RunningNormal(3)
    for r in (1.0, 2.0, 3.0, 100.0):
        n.add(result(r, inliers=int(r * 10)), r)
    assert len(n) == 3
    assert n.median("rmse") == 3.0 and n.median("num_inliers") == 30.0
    n.add(result(float("inf")), 1.0)  # a failed registration never enters the normal
    assert len(n) == 3
    n.clear()
    assert len(n) == 0 and np.isnan(n.median("information"))


def test_relaxed_gate_accepts_a_changed_scene_but_not_a_blinded_sensor():
    """After long lost tracking the tolerances widen: a scene with 0.15 x the usual
    correspondences passes at factor 2, a blinded sensor's 0.07 x only at factor 4."""
    cfg = PlausibilityConfig()
    n = normal_of(0.1)

    def why(res, factor):
        return implausibility(res, 30.0, n, step(), np.eye(4), DT, relaxed(cfg, factor))

    changed, blind = result(0.25, inliers=270, source=300), result(0.1, inliers=130, source=140)
    assert why(changed, 1.0) is not None and why(changed, 2.0) is None
    assert why(blind, 2.0) is not None and why(blind, 4.0) is None
    assert relaxed(cfg, 1.0) is cfg
    assert relaxed(cfg, 2.0).max_speed == cfg.max_speed  # physics does not relax


def test_fitness_relaxes_on_its_own_clock():
    """A residual that rose with the scene (a normal set while the car stood) is believed
    once the fitness ratios alone are widened; the support test stays as strict, so a
    blinded sensor is still rejected (the front end widens the fitness ratios every 0.5 s
    of lost tracking, the others every 5 s)."""
    cfg = PlausibilityConfig()
    n = normal_of(0.06)

    def why(res, factor, fitness_factor):
        gate = relaxed(cfg, factor, fitness_factor)
        return implausibility(res, 30.0, n, step(), np.eye(4), DT, gate)

    risen, blind = result(0.22), result(0.1, inliers=130, source=140)
    assert "fitness" in why(risen, 1.0, 1.0)
    assert why(risen, 1.0, 2.0) is None
    assert "correspondences" in why(blind, 1.0, 8.0)
    gate = relaxed(cfg, 1.0, 2.0)
    assert gate.max_fitness_ratio == 2 * cfg.max_fitness_ratio
    assert gate.min_support_ratio == cfg.min_support_ratio
