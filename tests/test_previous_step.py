"""The gate around one bad frame at motorway speed: a registration rejected against the
velocity a wrongly short step taught is believed when it follows the motion before it
(``previous_step_check``), and after one lost frame the next registration is judged by
the mean velocity over the stretch (``recovered_velocity_frames``)."""

from __future__ import annotations

import numpy as np
import pytest

from slam.odometry import CommonConfig, Estimate, ScanToMapFrontend
from slam.registration.plausibility import PlausibilityConfig
from slam.registration.result import RegistrationResult
from slam.types import Scan

STEP = 2.5  # m per 0.1 s frame: 25 m/s along x


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


class Scripted(ScanToMapFrontend):
    """Registrations that land where the script says, whatever their start; every one
    fits alike (the gate's quality tests pass)."""

    def __init__(self, cfg: CommonConfig, script: dict[int, float], poor: set[int]):
        super().__init__(cfg)
        self.script = script
        self.poor = poor  # frames whose registration fits 5x worse than usual

    def _estimate(self, scan: Scan, T_pred: np.ndarray, timings: dict, wide: bool) -> Estimate:
        if scan.index == 0:
            return Estimate(pose=np.eye(4))
        rmse = 5e-2 if scan.index in self.poor else 1e-2
        res = RegistrationResult(
            T_target_source=_pose(self.script[scan.index]),
            H=np.eye(6) * 1e4,
            b=np.zeros(6),
            cost=1.0,
            fitness=rmse**2,
            rmse=rmse,
            num_inliers=900,
            num_source=1000,
            iterations=5,
            converged=True,
            dof=994,
        )
        return Estimate(pose=res.T_target_source, result=res)

    def _insert(self, est: Estimate, timings: dict) -> None:
        pass


def _run(script: dict[int, float], check: bool, poor=(), recovered: int = 2) -> list:
    cfg = CommonConfig(
        deskew=False,
        start_max_speed=0.0,
        plausibility=PlausibilityConfig(
            previous_step_check=check, recovered_velocity_frames=recovered
        ),
    )
    fe = Scripted(cfg, script, set(poor))
    rng = np.random.default_rng(0)
    outs = []
    for i in range(max(script) + 1):
        xyz = rng.uniform(-20, 20, (500, 3))
        outs.append(fe.process(Scan(stamp=100.0 + 0.1 * i, xyz=xyz, index=i)))
    return outs


def _script(n: int, wrong: dict[int, float]) -> dict[int, float]:
    return {i: STEP * i + wrong.get(i, 0.0) for i in range(1, n)}


@pytest.mark.parametrize("check", [True, False])
def test_a_short_step_is_undone_by_the_next_registration(check):
    # frame 20 lands 0.36 m short (within the floor of 0.3 m + 0.1 m): accepted; frame 21
    # lands on the truth, 0.72 m off the short velocity's prediction
    outs = _run(_script(26, {20: -0.36}), check)
    x = np.array([o.pose[0, 3] for o in outs])
    rejected = [i for i, o in enumerate(outs) if o.diagnostics.rejected]
    assert abs(x[20] - (STEP * 20 - 0.36)) < 1e-9
    if check:
        assert rejected == []
        assert outs[21].diagnostics.counts.get("previous_step_off") == 1
        # on the truth from frame 21 on; the velocity from the two frames' mean
        assert np.abs(x[21:] - STEP * np.arange(21, 26)).max() < 1e-9
    else:  # the right registration is rejected and the short velocity kept
        assert 21 in rejected
        assert abs(x[21] - (x[20] + STEP - 0.36)) < 1e-6


def test_a_wrong_registration_after_a_good_step_stays_rejected():
    # frame 21 alone lands 0.6 m short: off both predictions
    outs = _run(_script(24, {21: -0.6}), True)
    assert outs[21].diagnostics.rejected
    assert not outs[21].diagnostics.counts.get("previous_step_off")
    assert abs(outs[21].pose[0, 3] - STEP * 21) < 1e-6  # the prediction, on the truth


@pytest.mark.parametrize("recovered", [2, 0])
def test_after_one_lost_frame_the_mean_velocity_judges(recovered):
    # frame 20 fits poorly (rejected: the prediction stands), 21 is right, 22 slides 0.5 m
    # back (a LeGO registration among the motorway's rails, lego_loam seed 2 frame 122)
    outs = _run(_script(25, {22: -0.5}), True, poor={20}, recovered=recovered)
    x = np.array([o.pose[0, 3] for o in outs])
    assert outs[20].diagnostics.rejected and not outs[21].diagnostics.rejected
    if recovered:
        assert outs[22].diagnostics.rejected
        assert abs(x[22] - STEP * 22) < 1e-6  # the mean velocity's prediction
    else:  # not judged against a prediction: the slide is the trajectory
        assert not outs[22].diagnostics.rejected
        assert abs(x[22] - (STEP * 22 - 0.5)) < 1e-9
