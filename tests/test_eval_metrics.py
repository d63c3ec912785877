"""APE/RPE through evo: agreement with evo's own CLI, alignment, association, file formats."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.errors import ConfigError, InputError
from slam.eval.metrics import EvalOptions, evaluate, evaluate_arrays
from slam.io.trajectory import write_kitti, write_tum

BIN = Path(sys.executable).parent


def make_pair(n: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps, ground truth on an ellipse, and a noisy drifting estimate in another frame."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 6 * np.pi, n)
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, 3] = np.column_stack([20 * np.cos(s / 3), 15 * np.sin(s / 3), 0.5 * np.sin(s)])
    ypr = np.column_stack([s / 3 + np.pi / 2, 0.05 * np.sin(s), 0.02 * np.cos(s)])
    gt[:, :3, :3] = Rotation.from_euler("ZYX", ypr).as_matrix()
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, 0.2, (n, 3)) + np.linspace(0, 1, n)[:, None]
    est[:, :3, :3] = est[:, :3, :3] @ Rotation.from_rotvec(rng.normal(0, 0.02, (n, 3))).as_matrix()
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 0.7).as_matrix()
    T[:3, 3] = [5.0, -3.0, 1.0]
    return np.arange(n) * 0.1, gt, T @ est


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("traj")
    stamps, gt, est = make_pair()
    write_tum(d / "gt.tum", stamps, gt)
    # estimate stamps shifted by 3 ms (within max_diff) and its first 5 poses missing
    write_tum(d / "est.tum", stamps[5:] + 0.003, est[5:])
    est_s = est.copy()
    est_s[:, :3, 3] *= 0.8
    write_tum(d / "est_scaled.tum", stamps[5:] + 0.003, est_s[5:])
    return {"dir": d, "gt": d / "gt.tum", "est": d / "est.tum", "est_s": d / "est_scaled.tum"}


@pytest.fixture(scope="module")
def evo_cli(files) -> dict[str, dict]:
    """Statistics of evo_ape / evo_rpe CLI runs on the same files (in parallel, own HOMEs)."""
    from evo.tools import file_interface

    d = files["dir"]
    common = ["--t_max_diff", "0.02", "--no_warnings"]
    runs = {
        "ape_trans": ["evo_ape", "tum", files["gt"], files["est"], "-a", "-r", "trans_part"],
        "rpe_trans": [
            "evo_rpe",
            "tum",
            files["gt"],
            files["est"],
            "-a",
            "-r",
            "trans_part",
            "--delta",
            "1",
            "--delta_unit",
            "m",
        ],  # fmt: skip
    }
    # our evaluate() in a fresh interpreter alongside: it must neither create nor need ~/.evo
    runs["ours"] = [
        Path(sys.executable).name,
        "-c",
        f"from slam.eval import evaluate; print(evaluate({str(files['est'])!r}, "
        f"{str(files['gt'])!r}).ape_trans['rmse'])",
    ]
    procs = {}
    for name, cmd in runs.items():
        home = d / f"home_{name}"  # evo writes ~/.evo on first start: no shared HOME race
        home.mkdir()
        env = {**os.environ, "HOME": str(home), "MPLBACKEND": "Agg"}
        if name == "ours":
            cmd = [sys.executable, *cmd[1:]]
        else:
            cmd = [str(BIN / cmd[0]), *map(str, cmd[1:]), *common]
            cmd += ["--save_results", str(d / f"{name}.zip")]
        procs[name] = subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
    out = {}
    for name, proc in procs.items():
        log, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0, log
        if name == "ours":
            out[name] = {"stdout": log, "home": d / f"home_{name}"}
        else:
            out[name] = file_interface.load_res_file(d / f"{name}.zip").stats
    return out


def evo_main(kind: str, files: dict, relation: str, est: str = "est", **kw) -> dict:
    """Stats from evo's own CLI entry functions (main_ape.ape / main_rpe.rpe) in-process."""
    from evo.core import metrics, sync
    from evo.main_ape import ape
    from evo.main_rpe import rpe
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(files["gt"])
    traj = file_interface.read_tum_trajectory_file(files[est])
    ref, traj = sync.associate_trajectories(ref, traj, max_diff=0.02)
    rel = metrics.PoseRelation(relation)
    if kind == "ape":
        return ape(ref, traj, rel, align=True, **kw).stats
    return rpe(ref, traj, rel, delta=1.0, delta_unit=metrics.Unit.meters, align=True, **kw).stats


def assert_stats_equal(ours: dict, evo_stats: dict) -> None:
    assert set(ours) == set(evo_stats) == {"max", "mean", "median", "min", "rmse", "sse", "std"}
    for key, value in evo_stats.items():
        assert ours[key] == pytest.approx(value, rel=1e-9, abs=1e-6), key


def test_se3_ape_and_rpe_match_evo_cli(files, evo_cli):
    res = evaluate(files["est"], files["gt"])
    assert res.n_matched == 395 and res.n_est == 395 and res.n_gt == 400
    assert_stats_equal(res.ape_trans, evo_cli["ape_trans"])
    assert_stats_equal(res.rpe_trans, evo_cli["rpe_trans"])
    assert_stats_equal(res.ape_rot, evo_main("ape", files, "rotation angle in degrees"))
    assert_stats_equal(res.rpe_rot, evo_main("rpe", files, "rotation angle in degrees"))
    assert res.scale == 1.0
    # the recovered alignment undoes the 0.7 rad yaw applied to the estimate
    yaw = Rotation.from_matrix(res.alignment[:3, :3]).as_euler("ZYX")[0]
    assert yaw == pytest.approx(-0.7, abs=0.02)


def test_sim3_matches_evo_main_and_recovers_scale(files):
    res = evaluate(files["est_s"], files["gt"], EvalOptions(align="sim3"))
    sim3_ape = evo_main("ape", files, "translation part", est="est_s", correct_scale=True)
    assert_stats_equal(res.ape_trans, sim3_ape)
    sim3_rpe = evo_main("rpe", files, "translation part", est="est_s", correct_scale=True)
    assert_stats_equal(res.rpe_trans, sim3_rpe)
    assert res.scale == pytest.approx(1 / 0.8, rel=0.01)
    assert np.linalg.det(res.alignment[:3, :3]) == pytest.approx(res.scale**3, rel=1e-9)
    # the full aligned estimate carries the same Sim(3) as the matched poses
    np.testing.assert_allclose(res.est_full[res.est_indices], res.est_poses, atol=1e-9)


def test_result_arrays_and_json(files):
    res = evaluate(files["est"], files["gt"])
    stamps, errors = res.errors_over_time
    assert stamps.shape == errors.shape == (395,)
    assert stamps[0] == pytest.approx(0.503)
    assert np.sqrt(np.mean(errors**2)) == pytest.approx(res.ape_trans["rmse"], rel=1e-12)
    assert res.est_indices.tolist() == list(range(395))
    np.testing.assert_allclose(res.est_full[:, :3, 3], res.est_poses[:, :3, 3], atol=1e-9)
    d = json.loads(json.dumps(res.to_dict(arrays=True)))
    assert d["n_matched"] == 395 and len(d["ape_errors"]) == 395
    assert d["options"]["align"] == "se3"
    assert d["kitti"]["segments"] > 0 and d["kitti"]["t_rel_pct"] > 0


def test_kitti_files_are_paired_by_index(tmp_path):
    stamps, gt, est = make_pair(n=200)
    write_kitti(tmp_path / "gt.txt", gt)
    write_kitti(tmp_path / "est.txt", est)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    write_tum(tmp_path / "est.tum", stamps, est)
    by_index = evaluate(tmp_path / "est.txt", tmp_path / "gt.txt")
    by_time = evaluate(tmp_path / "est.tum", tmp_path / "gt.tum")
    assert by_index.n_matched == by_time.n_matched == 200
    for key, value in by_time.ape_trans.items():
        assert by_index.ape_trans[key] == pytest.approx(value, rel=1e-6)
    mixed = evaluate(tmp_path / "est.txt", tmp_path / "gt.tum")
    assert mixed.ape_trans["rmse"] == pytest.approx(by_time.ape_trans["rmse"], rel=1e-6)
    write_kitti(tmp_path / "short.txt", est[:-1])
    with pytest.raises(InputError, match="one pose per frame"):
        evaluate(tmp_path / "short.txt", tmp_path / "gt.txt")


def test_alignment_modes_on_known_offset():
    stamps, gt, _ = make_pair(n=100)
    est = gt.copy()
    est[:, :3, 3] += [3.0, 4.0, 0.0]  # pure translation: APE is 5 m everywhere unaligned
    none = evaluate_arrays(stamps, est, stamps, gt, EvalOptions(align="none"))
    assert none.ape_trans["min"] == pytest.approx(5.0) and none.ape_trans["max"] == pytest.approx(
        5.0
    )
    assert none.ape_rot["max"] == pytest.approx(0.0, abs=1e-6)
    assert none.rpe_trans["max"] == pytest.approx(0.0, abs=1e-9)
    se3 = evaluate_arrays(stamps, est, stamps, gt, EvalOptions(align="se3"))
    assert se3.ape_trans["max"] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(se3.alignment[:3, 3], [-3.0, -4.0, 0.0], atol=1e-9)
    origin = evaluate_arrays(stamps, est, stamps, gt, EvalOptions(align="origin"))
    assert origin.ape_trans["max"] == pytest.approx(0.0, abs=1e-9)
    # aligning on the first 10 poses only: still exact for a rigid offset
    first = evaluate_arrays(stamps, est, stamps, gt, EvalOptions(n_align=10))
    assert first.ape_trans["rmse"] == pytest.approx(0.0, abs=1e-9)


def test_association_tolerance_and_rpe_in_frames():
    stamps, gt, est = make_pair(n=100)
    res = evaluate_arrays(stamps[::2] + 0.015, est[::2], stamps, gt, EvalOptions(max_diff=0.02))
    assert res.n_matched == 50
    with pytest.raises(InputError, match="associate"):
        evaluate_arrays(stamps + 0.05, est, stamps, gt, EvalOptions(max_diff=0.02))
    frames = evaluate_arrays(stamps, est, stamps, gt, EvalOptions(rpe_delta=1, rpe_unit="frames"))
    assert frames.n_matched == 100
    # one pair per consecutive frame: sse / rmse^2 = number of pairs
    pairs = frames.rpe_trans["sse"] / frames.rpe_trans["rmse"] ** 2
    assert pairs == pytest.approx(99)


def test_short_run_has_no_rpe_and_scaled_kitti():
    stamps = np.arange(20) * 0.1
    gt = np.tile(np.eye(4), (20, 1, 1))
    gt[:, 0, 3] = np.arange(20) * 0.02  # 0.38 m: no 1 m RPE pair, no 100 m segment
    gt[:, 1, 3] = np.sin(np.arange(20)) * 0.01
    est = gt.copy()
    est[:, :3, 3] *= 1.05
    res = evaluate_arrays(stamps, est, stamps, gt, EvalOptions(align="none"))
    assert res.rpe_trans is None and res.rpe_rot is None
    assert any("RPE not computed" in note for note in res.notes)
    assert res.kitti["scaled"] is True and res.kitti["segments"] > 0
    assert res.kitti["t_rel_pct"] == pytest.approx(5.0, rel=0.05)


def test_bad_options_and_inputs(tmp_path):
    for bad in ({"align": "affine"}, {"rpe_unit": "s"}, {"rpe_delta": 0}, {"n_align": 0}):
        with pytest.raises(ConfigError):
            EvalOptions(**bad)
    with pytest.raises(InputError, match="not found"):
        evaluate(tmp_path / "nope.tum", tmp_path / "nope2.tum")
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="columns"):
        evaluate(tmp_path / "bad.txt", tmp_path / "bad.txt")


def test_evaluate_never_touches_home(evo_cli):
    """evo's settings live in ~/.evo; our evaluation must not create or need them."""
    ours = evo_cli["ours"]
    assert float(ours["stdout"]) == pytest.approx(evo_cli["ape_trans"]["rmse"], rel=1e-9)
    assert list(ours["home"].iterdir()) == []
    # whereas evo's CLI did write its settings into its own HOME
    assert (ours["home"].parent / "home_ape_trans" / ".evo" / "settings.json").is_file()


def _tum_text(stamps: np.ndarray, poses: np.ndarray) -> list[str]:
    """TUM lines of poses (one per pose) to edit before writing."""
    from slam.io.trajectory import poses_to_tum_rows

    return [" ".join(f"{v:.9f}" for v in row) for row in poses_to_tum_rows(stamps, poses)]


def test_a_row_that_is_no_pose_names_its_file_and_line(tmp_path):
    from slam.eval.metrics import read_trajectory
    from slam.io.trajectory import read_tum

    stamps, gt, _ = make_pair(n=20)
    lines = _tum_text(stamps, gt)
    lines[3] = f"{stamps[3]:.9f} 1 2 3 0 0 0 0"  # zero quaternion
    path = tmp_path / "zeroq.tum"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n" + "\n".join(lines) + "\n")
    for read in (read_trajectory, read_tum):  # was scipy's ValueError: zero norm quaternions
        with pytest.raises(InputError, match=r"zeroq.tum, line 6: zero quaternion"):
            read(path)
    lines[3] = f"{stamps[3]:.9f} 1 nan 3 0 0 0 1"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"line 4: values not finite"):
        read_trajectory(path)
    kitti = np.zeros((5, 12))
    kitti[2, 0] = np.inf
    np.savetxt(tmp_path / "k.txt", kitti)
    with pytest.raises(InputError, match=r"k.txt, line 3: values not finite"):
        read_trajectory(tmp_path / "k.txt")


def test_stamps_all_equal_or_twice_are_errors_going_back_is_sorted(tmp_path, caplog):
    from slam.eval.metrics import read_for_eval, read_trajectory

    stamps, gt, est = make_pair(n=30)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    path = tmp_path / "same.tum"
    write_tum(path, np.full(30, 1.7e9), est)  # every stamp the same: was APE 10.8 m, exit 0
    for read in (read_trajectory, read_for_eval):
        with pytest.raises(InputError, match="all 30 poses have the same stamp"):
            read(path)
    lines = _tum_text(stamps, est)
    twice = lines[:5] + [lines[5].replace(lines[5].split()[1], "9.0", 1)] + lines[5:]
    (tmp_path / "twice.tum").write_text("\n".join(twice) + "\n")
    with pytest.raises(InputError, match=r"line 7: stamp 0.50+ is also the stamp of line 6"):
        evaluate(tmp_path / "twice.tum", tmp_path / "gt.tum")
    # stamps that go back (a CARMEN run's files keep the log's own): evaluated in time
    # order, the file read as it is; a line written twice verbatim is dropped
    back = lines[:10] + [lines[12]] + lines[10:12] + lines[13:] + [lines[20]]
    (tmp_path / "back.tum").write_text("\n".join(back) + "\n")
    assert read_trajectory(tmp_path / "back.tum")[0][10] == pytest.approx(1.2)
    write_tum(tmp_path / "est.tum", stamps, est)
    with caplog.at_level("WARNING"):
        got_stamps, got = read_for_eval(tmp_path / "back.tum")
        res = evaluate(tmp_path / "back.tum", tmp_path / "gt.tum")
    np.testing.assert_allclose(got_stamps, stamps)
    np.testing.assert_allclose(got, read_trajectory(tmp_path / "est.tum")[1], atol=1e-8)
    ref = evaluate(tmp_path / "est.tum", tmp_path / "gt.tum")
    assert res.n_matched == 30 and res.rpe_trans == pytest.approx(ref.rpe_trans)
    assert "2 stamp(s) go back in time (first: line 12); evaluated in time order" in caplog.text
    assert "1 line(s) repeat another verbatim (first: line 31); dropped" in caplog.text


def test_eval_cli_bad_rows_exit_2_without_traceback(tmp_path, capsys):
    from slam.cli import main

    stamps, gt, est = make_pair(n=20)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    lines = _tum_text(stamps, est)
    lines[0] = f"{stamps[0]:.9f} 0 0 0 0 0 0 0"
    (tmp_path / "zeroq.tum").write_text("\n".join(lines) + "\n")
    assert main(["eval", str(tmp_path / "zeroq.tum"), str(tmp_path / "gt.tum")]) == 2
    err = capsys.readouterr().err
    assert "zeroq.tum, line 1: zero quaternion" in err and "Traceback" not in err
    write_tum(tmp_path / "same.tum", np.zeros(20), est)
    assert main(["eval", str(tmp_path / "same.tum"), str(tmp_path / "gt.tum")]) == 2
    assert "same stamp" in capsys.readouterr().err
