"""Kuemmerle's relation metric (``slam.eval.relations``, ``slam eval EST --relations``) on
a simulated 2D sequence scored against relations computed from its ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from slam.cli import main
from slam.eval.relations import (
    read_relations,
    relation_errors,
    relations_in_frame,
    relations_of,
    write_relations,
)
from slam.io.trajectory import read_tum, write_tum
from slam.sim.floorplan2d import simulate2d, write_sequence


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    """office2d's first 150 scans: the CARMEN log, its ground truth, and relations of
    every scan with the scans 1, 5 and 20 later, from that ground truth."""
    out = tmp_path_factory.mktemp("office2d")
    seq = simulate2d("office2d", frames=150, speed=1.0)
    _, gt = write_sequence(seq, out)
    stamps, poses = read_tum(gt)
    i = np.concatenate([np.arange(150 - d) for d in (1, 5, 20)])
    j = np.concatenate([np.arange(d, 150) for d in (1, 5, 20)])
    rel = out / "office2d.relations"
    write_relations(rel, relations_of(stamps, poses, i, j))
    return gt, rel, stamps, poses, i, j


def _planar(x, y, yaw):
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = x, y
    return T


def test_the_exact_trajectory_scores_zero(office, capsys):
    gt, rel, stamps, poses, *_ = office
    err = relation_errors(stamps, poses, read_relations(rel))
    assert len(err.trans) == 3 * 150 - 26 and err.unmatched == 0
    assert err.trans.max() < 1e-5 and err.rot_deg.max() < 1e-4
    assert main(["eval", str(gt), "--relations", str(rel)]) == 0
    printed = capsys.readouterr().out
    assert "424 relations (0 unmatched)" in printed and "mean 0.0000" in printed


def test_an_error_between_two_stamps_is_found(office, tmp_path, capsys):
    """Every pose after scan 60 moved by 0.3 m and 2 deg about scan 60 (a wrong loop edge
    between scans 60 and 61): exactly the relations across 60 | 61 see it, 0.3 m and more."""
    gt, rel, stamps, poses, i, j = office
    bad = poses.copy()
    jump = poses[60] @ _planar(0.3, 0.0, np.radians(2.0)) @ np.linalg.inv(poses[60])
    bad[61:] = jump @ poses[61:]
    err = relation_errors(stamps, bad, read_relations(rel))
    across = (i[err.index] <= 60) & (j[err.index] >= 61)
    assert across.sum() == 1 + 5 + 20
    assert err.trans[~across].max() < 1e-5 and err.rot_deg[~across].max() < 1e-4
    assert err.trans[across].min() > 0.29
    np.testing.assert_allclose(err.rot_deg[across], 2.0, atol=1e-3)
    s = err.summary()
    assert s["trans_m"]["share_above_0.2m"] == pytest.approx(26 / 424)
    assert s["trans_m"]["median"] < 1e-5 and s["trans_m"]["max"] > 0.29
    est = tmp_path / "bad.tum"
    write_tum(est, stamps, bad)
    assert main(["eval", str(est), "--relations", str(rel), "--out", str(tmp_path)]) == 0
    assert "> 0.2 m 6.1 %" in capsys.readouterr().out
    assert (tmp_path / "relations.json").is_file()


def test_stamps_are_matched_within_the_tolerance(office):
    _, rel, stamps, poses, *_ = office
    shifted = stamps + 0.004  # a trajectory stamped 4 ms late still matches
    assert relation_errors(shifted, poses, read_relations(rel)).unmatched == 0
    err = relation_errors(stamps[:100], poses[:100], read_relations(rel))
    assert err.unmatched == 424 - len(err.trans) and err.unmatched > 0


def test_bad_input_says_what_is_wrong(office, tmp_path, capsys):
    gt, rel, *_ = office
    wrong = tmp_path / "wrong.relations"
    wrong.write_text("1 2 3\n")
    assert main(["eval", str(gt), "--relations", str(wrong)]) == 2
    assert "8 (t1 t2 x y z roll pitch yaw)" in capsys.readouterr().err
    assert main(["eval", str(gt)]) == 2
    far = tmp_path / "far.relations"
    far.write_text("5.0 6.0 0 0 0 0 0 0\n")
    assert main(["eval", str(gt), "--relations", str(far)]) == 2
    assert "matches a stamp" in capsys.readouterr().err


def test_relations_move_from_the_sensor_to_the_body(office):
    """Relations between sensor poses, moved by the mount, are the body's relations: the
    body's trajectory scores 0 on them and 13.9 cm (mean) on the sensor's own."""
    _, _, stamps, body, i, j = office
    mount = _planar(0.3, 0.1, 0.2)  # T_body_sensor
    sensor = body @ mount
    on_sensor = relations_of(stamps, sensor, i, j)
    moved = relations_in_frame(on_sensor, mount)
    assert relation_errors(stamps, body, moved).trans.max() < 1e-9
    np.testing.assert_array_equal(moved.t1, on_sensor.t1)
    wrong = relation_errors(stamps, body, on_sensor).trans
    assert wrong.mean() == pytest.approx(0.1394, abs=1e-3)
