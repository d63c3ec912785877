"""The Rerun view: a short run recorded to .rrd and read back with rerun's own reader
(entity paths, counts, a pose against the run's odometry), `slam view` replaying a finished
run, the loop / optimisation updates, and the messages when rerun or a display is missing."""

from __future__ import annotations

import builtins
import dataclasses
import json
from collections import defaultdict

import numpy as np
import pytest

from slam.cli import main
from slam.config import load_config
from slam.errors import InputError
from slam.io.trajectory import read_tum
from slam.run import run_one
from slam.viz.rerun_view import RerunObserver, VizConfig, decimate, import_rerun, open_stream

pytestmark = pytest.mark.usefixtures("evo_home")  # tests/conftest.py
FRAMES = 40


def read_rrd(path) -> dict[str, list]:
    """Record batches of an .rrd by entity path, in file order (rerun.chunk.RrdReader)."""
    import rerun.chunk

    out: dict[str, list] = defaultdict(list)
    for chunk in rerun.chunk.RrdReader(path).stream():
        out[chunk.entity_path].append(chunk.to_record_batch())
    return out


def column_rows(batches: list, column: str) -> list:
    """Every row of ``column`` across ``batches`` as Python values, with its frame."""
    rows = []
    for rb in batches:
        frames = rb.column("frame").to_pylist() if "frame" in rb.schema.names else None
        for i, value in enumerate(rb.column(column).to_pylist()):
            if value is not None:
                rows.append((frames[i] if frames else None, value))
    return rows


@pytest.fixture(scope="module")
def recorded(corridor_short, tmp_path_factory):
    """A 40-frame corridor run with loop closure, recorded through the observer."""
    out = tmp_path_factory.mktemp("viz")
    config = load_config("improved_floam_loop")
    config.source = dataclasses.replace(config.source, max_frames=FRAMES)
    rrd = out / "live.rrd"
    obs = RerunObserver(open_stream(rrd), VizConfig(scan_points=500, keyframe_points=300))
    summary = run_one(corridor_short.bag, config, out / "run", quiet=True, observers=[obs])
    obs.close()
    return summary, rrd, read_rrd(rrd)


def test_recording_has_every_entity_and_count(recorded):
    summary, _, data = recorded
    n_kf = summary["keyframes"]
    assert summary["frames"] == FRAMES and n_kf >= 2
    for path in ("/world/sensor", "/world/sensor/scan", "/world/odometry/0000",
                 "/world/local_map", "/world/keyframes"):  # fmt: skip
        assert path in data, sorted(data)
    poses = column_rows(data["/world/sensor"], "Transform3D:translation")
    assert [f for f, _ in poses] == list(range(FRAMES))  # one pose per frame, in order
    scans = column_rows(data["/world/sensor/scan"], "Points3D:positions")
    assert [f for f, _ in scans] == list(range(0, FRAMES, 2))  # every 2nd frame
    assert all(0 < len(pts) <= 500 for _, pts in scans)  # decimated
    local = column_rows(data["/world/local_map"], "Points3D:positions")
    assert all(0 < len(pts) <= 4000 for _, pts in local)
    clouds = [p for p in data if p.startswith("/world/map/kf") and p.endswith("/points")]
    assert len(clouds) == n_kf
    kfs = column_rows(data["/world/keyframes"], "Points3D:positions")
    assert len(kfs[-1][1]) == 1 + 3 * ((n_kf - 1) // 3)  # logged every 3rd keyframe


def test_recorded_pose_is_the_odometry_pose(recorded):
    summary, _, data = recorded
    _, odom = read_tum(summary["out"] / "odometry.tum")
    poses = dict(column_rows(data["/world/sensor"], "Transform3D:translation"))
    k = FRAMES - 1
    np.testing.assert_allclose(np.ravel(poses[k]), odom[k, :3, 3], atol=1e-4)
    assert np.linalg.norm(odom[k, :3, 3] - odom[0, :3, 3]) > 1.0  # the sensor moved


def test_loop_and_optimisation_update_the_view(tmp_path):
    rrd = tmp_path / "loops.rrd"
    obs = RerunObserver(open_stream(rrd))
    cloud = np.random.default_rng(0).normal(size=(2000, 3)).astype(np.float32)
    poses = {}
    for k in range(3):
        T = np.eye(4)
        T[0, 3] = 2.0 * k
        poses[k] = T
        obs.on_keyframe(k, 5 * k, T, cloud)
    obs.on_loop(0, 2)
    moved = {k: T.copy() for k, T in poses.items()}
    moved[2][1, 3] = 0.5  # the loop pulled keyframe 2 sideways; 0 and 1 did not move
    obs.on_optimised(moved)
    obs.close()
    obs.close()  # idempotent
    data = read_rrd(rrd)
    loops = column_rows(data["/world/loops"], "LineStrips3D:strips")
    np.testing.assert_allclose(loops[-1][1][0], [[0, 0, 0], [4.0, 0.5, 0]], atol=1e-6)
    assert len(column_rows(data["/world/map/kf00002"], "Transform3D:translation")) == 2
    assert len(column_rows(data["/world/map/kf00001"], "Transform3D:translation")) == 1
    pts = column_rows(data["/world/map/kf00000/points"], "Points3D:positions")
    assert len(pts[0][1]) == len(decimate(cloud, 800)) == 667  # decimated keyframe clouds
    assert "/world/optimised" in data


def test_cli_run_and_view_record_without_display(corridor_short, tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    run, live, view = tmp_path / "run", tmp_path / "live.rrd", tmp_path / "view.rrd"
    args = ["run", str(corridor_short.bag), "--gt", str(corridor_short.ground_truth),
            "--out", str(run), "--max-frames", "20", "--quiet", "--viz", str(live)]  # fmt: skip
    assert main(args) == 0
    assert len(column_rows(read_rrd(live)["/world/sensor"], "Transform3D:translation")) == 20
    assert main(["view", str(run), "--viz", str(view)]) == 0
    data = read_rrd(view)
    n_map = int(json.loads((run / "metrics.json").read_text())["map_points"])
    [(_, map_pts)] = column_rows(data["/world/map"], "Points3D:positions")
    assert len(map_pts) == n_map
    [(_, strip)] = column_rows(data["/world/trajectory/optimised"], "LineStrips3D:strips")
    _, opt = read_tum(run / "trajectory.tum")
    np.testing.assert_allclose(np.asarray(strip[0])[-1], opt[-1, :3, 3], atol=1e-4)
    assert "/world/trajectory/odometry" in data
    assert len(column_rows(data["/world/sensor"], "Transform3D:translation")) == 20


def test_bare_viz_without_display_says_what_to_do(corridor_short, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code = main(["run", str(corridor_short.bag), "--out", str(tmp_path), "--viz", "--quiet"])
    assert code == 2
    assert "--viz run.rrd" in capsys.readouterr().err
    assert main(["view", str(tmp_path / "nothing")]) == 2
    assert main(["run", str(corridor_short.bag), "--viz", str(tmp_path / "x.txt")]) == 2


def test_missing_rerun_is_an_actionable_error(monkeypatch):
    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("No module named 'rerun'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    with pytest.raises(InputError, match=r"pip install 'pyslam-graph\[viz\]'"):
        import_rerun()


def test_decimate_keeps_at_most_the_limit():
    p = np.arange(3 * 1001, dtype=float).reshape(-1, 3)
    d = decimate(p, 100)
    assert len(d) <= 100 and d.dtype == np.float32
    np.testing.assert_array_equal(d[1], p[11])  # every 11th point
    assert len(decimate(p[:50], 100)) == 50
