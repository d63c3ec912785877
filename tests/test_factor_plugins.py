"""Built-in factor plugins: prior, odometry, position fixes."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from backends.batch import BatchBackend
from backends.isam2 import Isam2Backend
from slam.errors import ConfigError, InputError
from slam.factor_plugins import (
    OdometryConfig,
    OdometryFactorPlugin,
    PositionConfig,
    PositionFactorPlugin,
    PriorConfig,
    PriorFactorPlugin,
    load_position_fixes,
)
from slam.factors import GraphView, key, pose3
from slam.plugins import instantiate
from slam.types import Keyframe


def random_info(rng: np.random.Generator) -> np.ndarray:
    """A plausible 6x6 information (rotation first), full and positive definite."""
    q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    eig = np.array([4e4, 2e4, 1e4, 2e3, 1e3, 5e2]) * rng.uniform(0.5, 2.0, 6)
    return q @ np.diag(eig) @ q.T


def make_keyframes(n: int, seed: int = 0, yaw_bias: float = 0.0, dt: float = 0.5):
    """Keyframes of a wandering 3D path; relative motions (+ yaw_bias rad per step) chain
    into pose_odom. Returns (keyframes, true poses 4x4)."""
    rng = np.random.default_rng(seed)
    truth = [np.eye(4)]
    kfs: list[Keyframe] = []
    T_odom = np.eye(4)
    for i in range(n):
        if i > 0:
            xi = np.concatenate([rng.normal(0, [0.02, 0.02, 0.15]), [1.0, 0.0, 0.0]])
            xi[3:] += rng.normal(0, 0.1, 3)
            rel_true = gtsam.Pose3.Expmap(xi).matrix()
            truth.append(truth[-1] @ rel_true)
            rel = rel_true @ gtsam.Pose3(gtsam.Rot3.Yaw(yaw_bias), np.zeros(3)).matrix()
            T_odom = T_odom @ rel
        else:
            rel = np.eye(4)
        kfs.append(
            Keyframe(
                id=i,
                stamp=100.0 + dt * i,
                frame_index=3 * i,
                pose_odom=T_odom.copy(),
                relative=rel,
                info=random_info(rng) if i > 0 else np.eye(6),
                cloud=np.zeros((0, 3)),
            )
        )
    return kfs, np.array(truth)


def run_pipeline(keyframes, plugins, backend=None, perturb: float = 0.0, seed: int = 1):
    """What the pipeline does per keyframe: collect factors, one backend update.

    The new keyframe's initial value is the previous estimate composed with the relative
    motion, optionally perturbed by ``perturb`` (tangent sigma)."""
    backend = backend or Isam2Backend()
    rng = np.random.default_rng(seed)
    view = GraphView(keyframes, lambda i: backend.pose(i).matrix())
    for kf in keyframes:
        factors = [f for p in plugins for f in p.on_keyframe(kf, view)]
        guess = pose3(kf.pose_odom) if kf.id == 0 else backend.pose(kf.id - 1) * pose3(kf.relative)
        if perturb:
            guess = guess.compose(gtsam.Pose3.Expmap(rng.normal(0, perturb, 6)))
        backend.update(factors, {kf.id: guess})
    est = backend.finalize()
    return np.array([est[i].matrix() for i in sorted(est)])


def test_odometry_only_reproduces_the_odometry_chain():
    kfs, _ = make_keyframes(40)
    odo = np.array([kf.pose_odom for kf in kfs])
    plugins = [PriorFactorPlugin(), OdometryFactorPlugin()]
    # iSAM2 with the pipeline's initial guess (previous estimate * relative motion)
    isam = run_pipeline(kfs, plugins)
    # batch LM even from perturbed initial guesses (5 cm / 3 deg)
    batch = run_pipeline(kfs, plugins, BatchBackend(), perturb=0.05)
    for poses in (isam, batch):
        assert np.abs(poses[:, :3, 3] - odo[:, :3, 3]).max() <= 1e-6
        assert np.abs(poses[:, :3, :3] - odo[:, :3, :3]).max() <= 1e-6
    # the chain is not trivial: it travels tens of metres and turns
    assert np.linalg.norm(odo[-1, :3, 3]) > 10.0


def test_prior_plugin_only_on_keyframe_zero_with_configured_sigmas():
    kfs, _ = make_keyframes(3)
    view = GraphView(kfs, lambda i: kfs[i].pose_odom)
    plugin = PriorFactorPlugin(PriorConfig(rotation_sigma=0.1, translation_sigma=2.0))
    (factor,) = plugin.on_keyframe(kfs[0], view)
    assert factor.keys() == [key(0)]
    assert np.allclose(factor.noiseModel().sigmas(), [0.1] * 3 + [2.0] * 3)
    assert plugin.on_keyframe(kfs[1], view) == []
    assert PriorFactorPlugin(PriorConfig(enabled=False)).on_keyframe(kfs[0], view) == []
    with pytest.raises(ConfigError, match="rotation_sigma"):
        PriorConfig(rotation_sigma=0.0)


def test_odometry_factor_uses_frontend_information():
    kfs, _ = make_keyframes(3, seed=4)
    view = GraphView(kfs, lambda i: kfs[i].pose_odom)
    plugin = OdometryFactorPlugin()
    assert plugin.on_keyframe(kfs[0], view) == []
    (factor,) = plugin.on_keyframe(kfs[2], view)
    assert factor.keys() == [key(1), key(2)]
    assert np.allclose(factor.measured().matrix(), kfs[2].relative, atol=1e-12)
    # error of a known tangent offset xi is 0.5 xi^T info xi
    xi = np.array([0.01, -0.02, 0.005, 0.1, -0.05, 0.02])
    values = gtsam.Values()
    values.insert(key(1), gtsam.Pose3())
    values.insert(key(2), factor.measured().compose(gtsam.Pose3.Expmap(xi)))
    assert factor.error(values) == pytest.approx(0.5 * xi @ kfs[2].info @ xi, rel=1e-9)
    # fixed sigmas instead
    fixed = OdometryFactorPlugin(
        OdometryConfig(use_frontend_information=False, rotation_sigma=0.1, translation_sigma=0.5)
    )
    (factor,) = fixed.on_keyframe(kfs[2], view)
    expected = 0.5 * np.sum((xi / np.array([0.1] * 3 + [0.5] * 3)) ** 2)
    assert factor.error(values) == pytest.approx(expected, rel=1e-9)


def test_odometry_falls_back_to_fixed_sigmas_on_a_singular_information():
    kfs, _ = make_keyframes(2)
    kfs[1].info = np.diag([1e4, 1e4, 1e4, 1e3, 1e3, 0.0])  # degenerate along z
    plugin = OdometryFactorPlugin()
    (factor,) = plugin.on_keyframe(kfs[1], GraphView(kfs, lambda i: kfs[i].pose_odom))
    assert plugin.fallbacks == 1
    assert np.allclose(factor.noiseModel().sigmas(), [0.01] * 3 + [0.05] * 3)


def test_odometry_robust_kernel_and_enabled_switch():
    kfs, _ = make_keyframes(2)
    view = GraphView(kfs, lambda i: kfs[i].pose_odom)
    cfg = OdometryConfig(
        use_frontend_information=False,
        rotation_sigma=1.0,
        translation_sigma=1.0,
        robust="huber",
        robust_param=1.345,
    )
    (factor,) = OdometryFactorPlugin(cfg).on_keyframe(kfs[1], view)
    values = gtsam.Values()
    values.insert(key(0), gtsam.Pose3())
    values.insert(key(1), factor.measured().compose(gtsam.Pose3(gtsam.Rot3(), [3.0, 4.0, 0.0])))
    # Huber: k * d - k^2 / 2 for a whitened distance d = 5 beyond k, instead of d^2 / 2 = 12.5
    assert factor.error(values) == pytest.approx(1.345 * 5.0 - 1.345**2 / 2, rel=1e-9)
    assert OdometryFactorPlugin(OdometryConfig(enabled=False)).on_keyframe(kfs[1], view) == []
    with pytest.raises(ConfigError, match="unknown key"):
        instantiate("slam.factors", {"kernel": "huber"}, "factors.odometry", name="odometry")
    with pytest.raises(ConfigError, match="robust must be one of"):
        instantiate("slam.factors", {"robust": "l1"}, "factors.odometry", name="odometry")


def write_fixes_csv(path: Path, stamps, xyz) -> None:
    lines = ["stamp,x,y,z"] + [
        f"{t:.6f},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}" for t, p in zip(stamps, xyz, strict=True)
    ]
    path.write_text("\n".join(lines) + "\n")


def ape_rmse(poses: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((poses[:, :3, 3] - truth[:, :3, 3]) ** 2, axis=1))))


def test_position_fixes_pull_a_drifting_trajectory_to_truth(tmp_path):
    kfs, truth = make_keyframes(60, seed=2, yaw_bias=0.01)
    rng = np.random.default_rng(7)
    # fixes every second keyframe, 0.1 m noise, stamps 20 ms off the keyframe stamps
    sel = np.arange(0, len(kfs), 2)
    stamps = np.array([kfs[i].stamp + 0.02 for i in sel])
    fixes = truth[sel, :3, 3] + rng.normal(0, 0.1, (len(sel), 3))
    write_fixes_csv(tmp_path / "fixes.csv", stamps, fixes)
    position = instantiate(
        "slam.factors",
        {"file": str(tmp_path / "fixes.csv"), "sigma": 0.1, "max_dt": 0.05},
        "factors.position",
        name="position",
    )
    base = [PriorFactorPlugin(), OdometryFactorPlugin()]
    odometry_only = run_pipeline(kfs, base)
    with_fixes = run_pipeline(kfs, base + [position])
    assert position.used == len(sel)
    before, after = ape_rmse(odometry_only, truth), ape_rmse(with_fixes, truth)
    # measured: 7.1 m -> 0.09 m (77x)
    assert before > 1.0
    assert before / after > 3.0


def test_position_file_formats_and_time_matching(tmp_path):
    stamps = np.array([3.0, 1.0, 2.0])
    xyz = np.array([[3.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    write_fixes_csv(tmp_path / "a.csv", stamps, xyz)
    tum = np.column_stack([stamps, xyz, np.tile([0, 0, 0, 1.0], (3, 1))])
    np.savetxt(tmp_path / "a.tum", tum, header="timestamp tx ty tz qx qy qz qw")
    for name in ("a.csv", "a.tum"):
        s, p = load_position_fixes(tmp_path / name)
        assert np.allclose(s, [1.0, 2.0, 3.0])
        assert np.allclose(p[:, 0], [1.0, 2.0, 3.0])
    plugin = PositionFactorPlugin(PositionConfig(file=str(tmp_path / "a.csv"), max_dt=0.1))
    assert plugin.nearest(1.96) == 1
    assert plugin.nearest(2.5) is None
    assert plugin.nearest(3.08) == 2
    assert plugin.nearest(0.5) is None
    kfs, _ = make_keyframes(1)
    kfs[0].stamp = 2.05
    (factor,) = plugin.on_keyframe(kfs[0], GraphView(kfs, lambda i: kfs[i].pose_odom))
    assert isinstance(factor, gtsam.GPSFactor)
    assert np.allclose(factor.measurementIn(), [2.0, 0.0, 0.0])


def test_position_plugin_errors_name_the_file(tmp_path):
    missing = tmp_path / "nope.csv"
    with pytest.raises(InputError, match="nope.csv"):
        PositionFactorPlugin(PositionConfig(file=str(missing)))
    with pytest.raises(ConfigError, match="file is required"):
        PositionFactorPlugin(PositionConfig())
    bad = tmp_path / "bad.csv"
    bad.write_text("stamp,x,y,z\n1.0,2.0,3.0,4.0\n2.0,oops,3,4\n")
    with pytest.raises(InputError, match="bad.csv"):
        PositionFactorPlugin(PositionConfig(file=str(bad)))
    short = tmp_path / "short.csv"
    short.write_text("1.0,2.0,3.0\n")
    with pytest.raises(InputError, match="4 columns"):
        load_position_fixes(short)
    with pytest.raises(ConfigError, match="sigma"):
        PositionConfig(file="x", sigma=-1.0)
    # disabled: no file needed, no factors
    kfs, _ = make_keyframes(1)
    off = PositionFactorPlugin(PositionConfig(enabled=False))
    assert off.on_keyframe(kfs[0], GraphView(kfs, lambda i: kfs[i].pose_odom)) == []
