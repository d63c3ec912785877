"""The measures of benchmarks/robustness.py (in slam.bench): stops found in the ground
truth, the drift over them, the ran-away rule, and the degraded bags it writes (no
ring/time, jittered stamps, dropped messages) read back as intended."""

import json

import numpy as np
import pytest

from slam.bench import degrade, robustness
from slam.io.source import open_source
from slam.types import Scan


def _drive(speeds: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) of a car driving along x at ``speeds`` (m per frame)."""
    T = np.tile(np.eye(4), (len(speeds), 1, 1))
    T[:, 0, 3] = np.cumsum(speeds)
    return T


def test_stops_and_the_drift_over_them():
    # 2 s at 1 m per frame, 3 s standing, 2 s driving again, 0.5 s standing (too short)
    speeds = np.r_[np.ones(20), np.zeros(30), np.ones(20), np.zeros(5), np.ones(5)]
    stamps = 0.1 * np.arange(len(speeds))
    gt = _drive(speeds)
    spans = robustness.stops(stamps, gt)
    assert spans == [(19, 49)]
    est = gt.copy()
    est[20:50, 1, 3] = np.linspace(0.0, 0.3, 30)  # creeps 0.3 m sideways while standing
    est[50:, 1, 3] = 0.3
    drift, n = robustness.stop_drift(stamps, est, gt)
    assert n == 1 and drift == pytest.approx(0.3, abs=1e-9)
    steps = robustness.step_errors(est, gt)
    assert steps.max() == pytest.approx(0.3 / 29, rel=1e-6)


def test_ran_away_rule():
    ok = robustness.verdict(
        {"frames": 100, "messages": 100, "path_m": 100.0, "ape_rmse": 0.5, "step_err_max": 0.1}
    )
    assert ok["ran_away"] == "" and ok["ape_pct"] == pytest.approx(0.5)
    assert "step error" in robustness.verdict({"frames": 9, "step_err_max": 0.6})["ran_away"]
    far = robustness.verdict({"frames": 9, "path_m": 100.0, "ape_rmse": 6.0})
    assert "APE 6.0 % of path" in far["ran_away"]
    # a short path (a standing robot) is not judged by its APE share
    assert robustness.verdict({"frames": 9, "path_m": 5.0, "ape_rmse": 1.0})["ran_away"] == ""
    assert "stop drift" in robustness.verdict({"frames": 9, "stop_drift_max": 0.7})["ran_away"]
    lost = robustness.verdict({"frames": 1, "messages": 400})
    assert lost["ran_away"] == "1 of 400 messages written"


def test_degraded_bags(tmp_path, corridor_short):
    clean = [s for s in open_source(corridor_short.bag) if isinstance(s, Scan)]
    true = np.array([s.stamp for s in clean])
    bag, stamp_map = degrade.rewrite_bag(corridor_short.bag, tmp_path / "strip.bag", "strip")
    strip = [s for s in open_source(bag) if isinstance(s, Scan)]
    assert len(strip) == len(clean) and all(s.ring is None and s.time is None for s in strip)
    assert np.abs(strip[5].xyz - clean[5].xyz).max() < 1e-5
    bag, stamp_map = degrade.rewrite_bag(corridor_short.bag, tmp_path / "jit.bag", "jitter")
    jit = np.array([s.stamp for s in open_source(bag) if isinstance(s, Scan)])
    pairs = np.load(stamp_map)
    assert np.allclose(pairs[:, 1], true) and np.allclose(pairs[:, 0], jit, atol=1e-6)
    assert 0.01 < np.abs(jit - true).max() <= 0.02 + 1e-6
    bag, stamp_map = degrade.rewrite_bag(corridor_short.bag, tmp_path / "drop.bag", "drop5")
    drop = np.array([s.stamp for s in open_source(bag) if isinstance(s, Scan)])
    assert len(drop) == len(clean) - len(clean) // 5
    assert np.allclose(drop, np.delete(true, np.arange(4, len(true), 5)), atol=1e-6)


def _run(bag, out, *extra):
    from slam.cli import main

    return main(["run", str(bag), "--out", str(out), "--quiet", "--max-frames", "30", *extra])


def test_swapped_and_reversed_stamps_keep_every_frame(tmp_path, corridor_short, capsys, caplog):
    """urban-swap / urban-reversed in small: a bag with every 10th pair of messages recorded
    swapped keeps all 30 frames with the clean bag's poses (before: 3 dropped); a bag whose
    header stamps run backwards is stamped with the record time, one warning, all 30 frames
    (before: 1 frame, exit 0); forcing the header stamps on it stops with exit 2 and says
    what to do."""
    from slam.eval.metrics import evaluate
    from slam.io.trajectory import read_tum, write_tum

    assert _run(corridor_short.bag, tmp_path / "clean") == 0
    s0, t0 = read_tum(tmp_path / "clean" / "trajectory.tum")
    bag, _ = degrade.rewrite_bag(corridor_short.bag, tmp_path / "swap.bag", "swap")
    assert _run(bag, tmp_path / "swap") == 0
    s1, t1 = read_tum(tmp_path / "swap" / "trajectory.tum")
    np.testing.assert_array_equal(s1, s0)
    assert np.abs(t1[:, :3, 3] - t0[:, :3, 3]).max() < 1e-3
    capsys.readouterr()
    bag, stamp_map = degrade.rewrite_bag(corridor_short.bag, tmp_path / "rev.bag", "reversed")
    assert _run(bag, tmp_path / "rev") == 0
    err = capsys.readouterr().err
    warned = [r for r in caplog.records if r.levelname == "WARNING" and "backwards" in r.message]
    assert len(warned) == 1 and err.count("note: scans stamped with the bag's record time") == 1
    s2, t2 = read_tum(tmp_path / "rev" / "trajectory.tum")
    pairs = np.load(stamp_map)
    assert len(s2) == 30 and np.allclose(s2, pairs[:30, 2], atol=1e-6)  # the record time
    assert np.abs(t2[:, :3, 3] - t0[:, :3, 3]).max() < 0.01
    write_tum(tmp_path / "rev_true.tum", degrade.true_stamps(pairs, s2), t2)
    ape_clean = evaluate(tmp_path / "clean" / "trajectory.tum", corridor_short.ground_truth)
    ape_rev = evaluate(tmp_path / "rev_true.tum", corridor_short.ground_truth)
    assert ape_rev.ape_trans["rmse"] < 1.1 * ape_clean.ape_trans["rmse"] + 0.005
    m = json.loads((tmp_path / "rev" / "metrics.json").read_text())
    assert m["frames"] == 30 and "record time" in m["input_notes"][0]
    assert _run(bag, tmp_path / "forced", "--set", "source.stamps=header") == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--set source.stamps=record" in err
    # what the header stamps can order: the first 5 messages (the 4 held + 1), backwards
    assert len(read_tum(tmp_path / "forced" / "trajectory.tum")[0]) == 5


def test_stamp_and_start_up_variants(tmp_path, corridor_short):
    """The sweep's stamp variants and start-up variants read back as intended."""
    clean = [s for s in open_source(corridor_short.bag) if isinstance(s, Scan)]
    true = np.array([s.stamp for s in clean])
    n = len(clean)

    def read(variant):
        bag, stamp_map = degrade.rewrite_bag(
            corridor_short.bag, tmp_path / f"{variant}.bag", variant
        )
        return [s for s in open_source(bag)], np.load(stamp_map)

    got, pairs = read("zerostamps")
    assert all(s.stamp == 0.0 for s in got) and np.all(np.diff(pairs[:, 2]) > 0)
    assert np.all((pairs[:, 2] - true >= 0.05) & (pairs[:, 2] - true <= 0.06))  # record time
    got, pairs = read("clockback")
    stamps = np.array([s.stamp for s in got])
    assert np.allclose(np.diff(stamps)[n // 2 - 1], 0.1 - 2.55, atol=1e-6)
    got, _ = read("glitch")
    assert np.allclose([s.stamp for s in got][n // 2], true[n // 2] + 100.0, atol=1e-6)
    got, pairs = read("gap20")
    assert len(got) == n - 20 and np.allclose(np.diff(pairs[:, 1])[n // 3 - 1], 2.1, atol=1e-6)
    got, _ = read("empty3")
    assert [type(s).__name__ for s in got[:4]] == ["SkippedMessage"] * 3 + ["Scan"]
    got, _ = read("partial1")
    az = np.degrees(np.arctan2(got[0].xyz[:, 1], got[0].xyz[:, 0]))
    assert az.min() > 143.9 and len(got[0]) < 0.2 * len(clean[0])
    got, _ = read("nan30")
    assert 0.6 < len(got[3]) / len(clean[3]) < 0.8  # the NaN points are dropped on reading


def test_a_bag_cut_short_gives_every_frame_before_the_cut(tmp_path, corridor_short, capsys):
    """urban-truncated in small: the bag cut at 60 % of its bytes (no index). Before: no
    frame, "cannot open". Now: the frames of every complete message before the cut, then
    exit 2 saying where the file ends (the outputs are written)."""
    from slam.cli import main
    from slam.io.trajectory import read_tum

    bag = degrade.truncate_bag(corridor_short.bag, tmp_path / "cut.bag", keep=0.6)
    assert main(["run", str(bag), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "is cut short: read error at its end" in err and "Traceback" not in err
    assert "the 36 messages on /velodyne_points before the cut were read" in err
    stamps, _ = read_tum(tmp_path / "o" / "trajectory.tum")
    clean = [s.stamp for s in open_source(corridor_short.bag)]
    np.testing.assert_allclose(stamps, clean[:36], atol=1e-6)


def test_true_stamps_follow_the_clock_the_run_used():
    """The evaluation maps a trajectory's stamps back to the true ones whether the run used
    the header stamps, the record time or its own clock across a step (urban-clockback)."""
    true = 100.0 + 0.1 * np.arange(40)
    header = true.copy()
    header[20:] -= 2.55  # the clock stepped back
    record = true + 0.05
    stamp_map = np.column_stack([header, true, record])
    np.testing.assert_allclose(degrade.true_stamps(stamp_map, header[:20]), true[:20])
    np.testing.assert_allclose(degrade.true_stamps(stamp_map, record[5:]), true[5:])
    followed = true + 1e-7  # the run followed the step: back on the true clock
    np.testing.assert_allclose(degrade.true_stamps(stamp_map, followed), true)
    jittered = np.column_stack([true + 0.013 * np.sin(np.arange(40)), true, record])
    np.testing.assert_allclose(degrade.true_stamps(jittered, jittered[:, 0]), true)


def test_a_bag_cut_within_its_first_scans_gives_them(tmp_path, corridor_short, capsys):
    """A cut before the 10 scans that choose the clock: those scans were lost (0 frames)."""
    import re

    from slam.cli import main
    from slam.io.trajectory import read_tum

    bag = degrade.truncate_bag(corridor_short.bag, tmp_path / "cut.bag", keep=0.1)
    assert main(["run", str(bag), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    n = int(re.search(r"the (\d+) messages on /velodyne_points before the cut", err).group(1))
    assert 3 <= n < 10 and "Traceback" not in err
    stamps, _ = read_tum(tmp_path / "o" / "trajectory.tum")
    clean = [s.stamp for s in open_source(corridor_short.bag)]
    np.testing.assert_allclose(stamps, clean[:n], atol=1e-6)
