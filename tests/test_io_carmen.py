"""CARMEN 2D laser logs: the real Intel / FR079 / MIT-CSAIL logs and damaged lines."""

from __future__ import annotations

import bz2
import json

import numpy as np
import pytest
from shared_data import shared_path

from slam.errors import InputError
from slam.io.carmen import CarmenSource, fan_angles, repaired_stamps
from slam.io.source import open_source
from slam.types import Scan, SkippedMessage


def test_fan_angles_cover_180_degrees():
    assert np.degrees(fan_angles(180))[[0, 1, -1]] == pytest.approx([-90, -89, 89])
    assert np.degrees(fan_angles(361))[[0, 1, -1]] == pytest.approx([-90, -89.5, 90])
    assert np.degrees(fan_angles(360))[[0, 1, -1]] == pytest.approx([-90, -89.5, 89.5])


def _first(path, n: int) -> list[Scan]:
    out = []
    for item in open_source(path):
        out.append(item)
        if len(out) == n:
            break
    return out


@pytest.mark.parametrize(
    ("name", "beams", "span_m"),
    [("intel", 180, 20.0), ("fr079", 360, 15.0), ("mit-csail", 361, 30.0)],
)
def test_real_logs_give_planar_scans(name, beams, span_m):
    path = shared_path("laser2d", f"{name}.clf.bz2")
    scans = _first(path, 50)
    assert all(isinstance(s, Scan) for s in scans)
    first = scans[0]
    assert 0.5 * beams < len(first) <= beams  # no-return readings (~81.9 m) dropped
    assert np.all(first.xyz[:, 2] == 0) and first.ring is not None and not first.ring.any()
    r = np.linalg.norm(first.xyz[:, :2], axis=1)
    assert r.max() < 80.0 and r.min() > 0.02 and np.ptp(first.xyz[:, 1]) < 2 * span_m + 60
    stamps = np.array([s.stamp for s in scans])
    assert np.all(np.diff(stamps) > 0) and np.median(np.diff(stamps)) < 0.5


def test_intel_log_counts_every_scan_and_its_odometry():
    src = CarmenSource(shared_path("laser2d", "intel.clf.bz2"))
    assert len(src) == 13631
    stamps = np.array([s.stamp for s in src])
    assert len(stamps) == 13631 and src.odometry.shape == (13631, 3)
    # the log's clock jumps ahead at single lines (631 stamps then look out of order): all
    # scans are kept, in file order, with increasing stamps at the log's 5-12 Hz
    assert np.all(np.diff(stamps) > 0) and 0.05 < np.median(np.diff(stamps)) < 0.25
    assert any("stamps out of order" in note for note in src.notes), src.notes
    # the robot drives a ~ 30 x 30 m lab: odometry spans tens of metres, not kilometres
    assert 10.0 < np.ptp(src.odometry[:, 0]) < 100.0


def test_repaired_stamps_interpolate_a_clock_jump():
    raw = np.array([0.0, 0.1, 0.2, 1.3, 0.4, 0.5, np.nan, 0.7, 0.8])
    fixed = repaired_stamps(raw)
    assert fixed == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8])
    assert repaired_stamps(np.array([5.0, 1.0, 2.0])) == pytest.approx([0.0, 1.0, 2.0])


def test_damaged_line_costs_one_scan(tmp_path):
    good = "FLASER 4 1.0 2.0 3.0 4.0 0 0 0 0 0 0 {t} host {t}\n"
    text = "# comment\nPARAM x 1\n" + good.format(t=1.0) + "FLASER 4 1.0 2.0\n"
    text += good.format(t=1.2) + "FLASER 4 90 90 90 90 0 0 0 0 0 0 1.3 h 1.3\n"
    path = tmp_path / "small.clf"
    path.write_text(text)
    items = list(open_source(path))
    kinds = [type(i).__name__ for i in items]
    assert kinds == ["Scan", "SkippedMessage", "Scan", "SkippedMessage"]
    assert isinstance(items[1], SkippedMessage) and items[1].reason == "corrupt message"
    # every reading of the last line is the log's largest (a SICK's "no return" value)
    assert items[3].reason == "empty message"
    assert len(items[0]) == 4 and items[2].stamp == 1.2


def test_truncated_bz2_log_stops_with_input_error(tmp_path):
    raw = bz2.compress(("FLASER 2 1.0 1.0 0 0 0 0 0 0 5.0 h 5.0\n" * 5000).encode())
    path = tmp_path / "cut.clf.bz2"
    path.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputError, match="cannot read|cut short"):
        for _ in CarmenSource(path):
            pass


def test_a_cut_log_reads_the_scans_before_the_cut(tmp_path):
    full = shared_path("laser2d", "intel.clf.bz2")
    path = tmp_path / "cut.clf.bz2"  # the first bz2 block (~900 kB of text) and part of the next
    path.write_bytes(full.read_bytes()[:150_000])
    src = CarmenSource(path)
    assert len(src) == 746 and "Compressed file ended" in src.cut
    assert src.description.endswith("(746 FLASER scans), cut short after scan 746")
    assert any("cut short" in note and "the 746 FLASER scans" in note for note in src.notes)
    scans = []
    with pytest.raises(InputError, match="cut short after 746 scans"):
        for item in src:
            scans.append(item)
    assert len(scans) == 746 and src.odometry.shape == (746, 3)
    whole = _first(full, 746)  # the same scans as the whole log's first ones
    assert all(np.array_equal(a.xyz, b.xyz) for a, b in zip(scans, whole, strict=True))


def test_a_run_of_a_cut_log_keeps_its_scans_and_exits_2(tmp_path, capsys):
    from slam.cli import main

    lines = bz2.decompress(shared_path("laser2d", "intel.clf.bz2").read_bytes()).splitlines(True)
    laser = [i for i, line in enumerate(lines) if line.startswith(b"FLASER ")]
    raw = bz2.compress(b"".join(lines[: laser[299] + 1]), compresslevel=1)  # 100 kB blocks
    path = tmp_path / "cut.clf.bz2"
    path.write_bytes(raw[: len(raw) * 2 // 3])  # the intel log's first 300 scans, cut short
    assert main(["info", str(path)]) == 0
    assert "(167 FLASER scans), cut short after scan 167" in capsys.readouterr().out
    out = tmp_path / "run"
    assert main(["run", str(path), "--config", "dpcr2d", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "the 167 FLASER scans before the cut are read" in err
    assert f"run stopped early: bad input: {path} is cut short after 167 scans" in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 167 and "cut short after 167 scans" in metrics["stopped_by"]
    rows = [r for r in (out / "trajectory.tum").read_text().splitlines() if r[0] != "#"]
    assert len(rows) == 167


def test_not_a_laser_log(tmp_path):
    path = tmp_path / "odom_only.clf"
    path.write_text("ODOM 0 0 0 0 0 0 1.0 h 1.0\n")
    with pytest.raises(InputError, match="no FLASER"):
        open_source(path)


def test_thinned_fr079_scans_as_a_one_degree_laser(tmp_path):
    """Every second beam of FR079 (360 beams, 0.5 deg): the same points at 1 deg spacing."""
    from slam.bench.degrade import thin_carmen

    src = shared_path("laser2d", "fr079.clf.bz2")
    thin = thin_carmen(src, tmp_path / "fr079.clf.bz2", 2)
    full, half = _first(src, 5), _first(thin, 5)
    for a, b in zip(full, half, strict=True):
        assert b.stamp == a.stamp and np.array_equal(b.odom, a.odom)
        angles_a = np.degrees(np.arctan2(a.xyz[:, 1], a.xyz[:, 0]))
        angles_b = np.degrees(np.arctan2(b.xyz[:, 1], b.xyz[:, 0]))
        assert len(b) == pytest.approx(len(a) / 2, abs=3)
        # every thinned beam sits on a whole degree and is one of the full scan's points
        assert np.abs(angles_b - np.round(angles_b)).max() < 1e-6
        kept = np.isin(np.round(angles_a * 2).astype(int), np.round(angles_b * 2).astype(int))
        assert np.allclose(a.xyz[kept], b.xyz)


def test_skewed_wheels_scale_the_turns_and_keep_the_laser_mount(tmp_path):
    """FR079's wheels with 5 % more turn and 3 % more distance per increment: the heading
    turned over the first 300 scans is 1.05x the log's, the path 1.03x, the laser still
    4 cm behind the robot (its mount) and the scans and stamps untouched."""
    from slam.bench.degrade import skew_carmen_odometry
    from slam.mapping.grid2d import compose2d, inverse2d

    src = shared_path("laser2d", "fr079.clf.bz2")
    same = skew_carmen_odometry(src, tmp_path / "same.clf.bz2")
    skew = skew_carmen_odometry(src, tmp_path / "skew.clf.bz2", 0.05, 0.03)
    full, a, b = _first(src, 300), _first(same, 300), _first(skew, 300)
    for x, y in zip(full, a, strict=True):
        d = compose2d(inverse2d(x.odom), y.odom)
        assert y.stamp == x.stamp and np.allclose(d, 0.0, atol=1e-5)

    def turned_and_path(scans):
        o = np.array([s.odom for s in scans])
        d = np.array([compose2d(inverse2d(p), q) for p, q in zip(o[:-1], o[1:], strict=True)])
        return np.abs(np.arctan2(np.sin(d[:, 2]), np.cos(d[:, 2]))).sum(), np.hypot(
            d[:, 0], d[:, 1]
        ).sum()

    (turn0, path0), (turn1, path1) = turned_and_path(full), turned_and_path(b)
    assert turn0 > 1.0 and path0 > 10.0  # the log turns and moves here
    assert turn1 / turn0 == pytest.approx(1.05, abs=1e-3)
    assert path1 / path0 == pytest.approx(1.03, abs=1e-3)
    for x, y in zip(full, b, strict=True):
        assert np.array_equal(y.xyz, x.xyz) and y.stamp == x.stamp
    src_mount, skew_mount = CarmenSource(src).mount, CarmenSource(skew).mount
    assert np.allclose(skew_mount, src_mount, atol=1e-5)
    assert src_mount[0] == pytest.approx(-0.04, abs=1e-3)
