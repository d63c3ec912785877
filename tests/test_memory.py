"""Memory of a run: keyframe clouds stored once (float32, shared), the map streamed into a
voxel-centroid accumulator, per-frame work that does not grow with the run."""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import open3d as o3d
import pytest

from slam.config import SlamConfig
from slam.io.maps import VoxelCentroidMap, voxel_centroids, write_points
from slam.outputs import build_map, write_outputs
from slam.pipeline import Pipeline, keyframe_cloud, resolved_config, scalar_extras
from slam.types import FrameDiagnostics, Odometry, Scan, TrackingStatus


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[0, 3] = x
    return T


class CloudFrontend:
    """Moves 1 m per frame (every frame a keyframe) and returns a float32 cloud of a
    10 x 10 x 2 m box around the sensor, its diagnostics and a ground plane."""

    def __init__(self, n_points: int = 2000, dtype=np.float32, step: float = 1.0):
        self.n_points, self.dtype, self.step = n_points, dtype, step
        self.clouds: list[np.ndarray] = []

    def process(self, scan: Scan) -> Odometry:
        rng = np.random.default_rng(scan.index)
        cloud = (rng.uniform(-5, 5, (self.n_points, 3)) * [1, 1, 0.2]).astype(self.dtype)
        self.clouds.append(cloud)
        i = scan.index
        T = _pose(self.step * i, 0.01 * i)
        rel = (
            np.eye(4) if i == 0 else np.linalg.solve(_pose(self.step * (i - 1), 0.01 * (i - 1)), T)
        )
        diag = FrameDiagnostics(counts={"n_points": self.n_points, "fitness": 0.01})
        odom = Odometry(scan.stamp, T, True, rel, np.eye(6) * 1e4, cloud, diagnostics=diag)
        odom.status, odom.ground_plane = TrackingStatus.TRACKED, np.array([0.0, 0, 1, 1.7])
        return odom


def _scans(n: int):
    for i in range(n):
        yield Scan(stamp=10.0 + 0.1 * i, xyz=np.zeros((1, 3)), index=i)


def _run(n: int = 30, **fe) -> tuple[Pipeline, CloudFrontend]:
    front = CloudFrontend(**fe)
    pipe = Pipeline(SlamConfig(), frontend=front)
    pipe.run(_scans(n))
    return pipe, front


def test_keyframe_cloud_is_the_front_ends_float32_array_shared_read_only():
    pipe, front = _run(5)
    for kf, given in zip(pipe.state.keyframes, front.clouds, strict=True):
        assert kf.cloud.dtype == np.float32 and kf.cloud.shape == given.shape
        assert np.shares_memory(kf.cloud, given)  # stored once: no copy
        assert not kf.cloud.flags.writeable
        assert pipe.view.cloud(kf.id) is kf.cloud  # plugins read the same array
        # the typed fields of the frame, the plane a copy (nothing of the front end's held)
        assert kf.diagnostics.counts == {"n_points": 2000, "fitness": 0.01}
        assert kf.status is TrackingStatus.TRACKED and kf.ground_plane.tolist() == [0, 0, 1, 1.7]
    with pytest.raises(ValueError):
        pipe.state.keyframes[0].cloud[0, 0] = 1.0


def test_float64_clouds_are_converted_once_and_empty_clouds_are_empty_float32():
    pipe, front = _run(3, dtype=np.float64)
    kf = pipe.state.keyframes[1]
    assert kf.cloud.dtype == np.float32 and not np.shares_memory(kf.cloud, front.clouds[1])
    np.testing.assert_allclose(kf.cloud, front.clouds[1], atol=1e-6)
    assert keyframe_cloud(None).shape == (0, 3) and keyframe_cloud(None).dtype == np.float32
    assert scalar_extras({"a": np.float32(1.0), "b": np.ones(3), "_c": 1}) == {"a": 1.0}


def test_streamed_voxel_map_equals_the_one_shot_reference():
    rng = np.random.default_rng(0)
    clouds = [rng.normal(0, 3, (5000, 3)) + [0.5 * i, 0, 0] for i in range(12)]
    clouds[3][7] = np.nan  # ignored like any non-finite point
    ref = voxel_centroids(np.concatenate(clouds), 0.4)
    for chunk in (1, 7000, 10**7):  # merge after every cloud, every few, only at the end
        acc = VoxelCentroidMap(0.4, chunk_points=chunk)
        for c in clouds:
            acc.add(c)
        got = acc.centroids()
        assert got.shape == ref.shape and len(acc) == len(ref)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)
    # every centroid lies in its own voxel; voxels hold the points' mean
    cells = np.floor(ref / 0.4)
    assert len(np.unique(cells, axis=0)) == len(ref)
    assert acc.points_added == 12 * 5000 - 1


def test_voxel_map_keeps_all_points_without_voxel_and_drops_run_away_points():
    acc = VoxelCentroidMap(0.0)
    acc.add(np.ones((10, 3)))
    acc.add_transformed(np.ones((5, 3), np.float32), _pose(2.0))
    assert acc.centroids().shape == (15, 3) and len(acc) == 15
    far = VoxelCentroidMap(0.1)
    far.add(np.array([[0.0, 0.0, 0.0], [1e6, 0.0, 0.0]]))  # 10^7 voxels out: a run-away pose
    assert len(far.centroids()) == 1 and far.dropped == 1


def test_written_map_reads_back_with_open3d(tmp_path):
    pts = np.random.default_rng(1).uniform(-50, 50, (1234, 3))
    for name in ("map.pcd", "map.ply"):
        assert write_points(tmp_path / name, pts) == 1234
        back = np.asarray(o3d.io.read_point_cloud(str(tmp_path / name)).points)
        np.testing.assert_allclose(back, pts, atol=1e-5)  # float32 on disk


def test_run_map_is_the_voxel_map_of_the_transformed_keyframe_clouds(tmp_path):
    pipe, _ = _run(20)
    st = pipe.state
    parts = [
        kf.cloud.astype(float) @ st.estimates[kf.id][:3, :3].T + st.estimates[kf.id][:3, 3]
        for kf in st.keyframes
    ]
    ref = voxel_centroids(np.concatenate(parts), pipe.config.output.map_voxel)
    np.testing.assert_allclose(build_map(pipe), ref, atol=1e-6)
    written = write_outputs(pipe, tmp_path, resolved_config=resolved_config(pipe.config))
    back = np.asarray(o3d.io.read_point_cloud(str(written["map"])).points)
    np.testing.assert_allclose(back, ref, atol=1e-4)
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["map_points"] == len(ref) and m["seconds"]["map"] >= 0
    assert m["keyframe_cloud_mb"] == pytest.approx(20 * 2000 * 12 / 2**20, abs=0.01)
    assert m["path_length_m"] == pytest.approx(19.0, abs=1e-6)  # 1 m per frame
    for k in ("frame_ms_first100", "frame_ms_last100", "frame_ms_max", "backend_ms_max"):
        assert m[k] > 0
    assert m["backend_ms_max"] >= m["backend_ms_last100"]
    assert {"frontend", "backend", "factor:prior", "factor:odometry"} <= set(m["stage_ms_max"])


def test_streaming_the_map_peaks_far_below_the_concatenated_clouds():
    """100 keyframes of 20k points in nearly the same 10 x 10 x 2 m box: the old map (all
    clouds stacked in float64) needed 48 MB before the writer's copies; the stream holds the
    box's ~19k voxels (0.25 m, turning) and one chunk (measured: 21 MiB)."""
    from types import SimpleNamespace

    from slam.config import OutputConfig
    from slam.types import Keyframe

    cloud = keyframe_cloud(CloudFrontend(n_points=20000).process(Scan(0.0, np.zeros((1, 3)))).cloud)
    kfs = [Keyframe(i, 0.1 * i, i, _pose(0.01 * i, 0.01 * i), np.eye(4), np.eye(6), cloud)
           for i in range(100)]  # fmt: skip
    state = SimpleNamespace(keyframes=kfs, estimates={k.id: k.pose_odom for k in kfs})
    pipe = SimpleNamespace(state=state, config=SlamConfig(output=OutputConfig(map_voxel=0.25)))
    stacked = 100 * 20000 * 3 * 8
    tracemalloc.start()
    try:
        pts = build_map(pipe)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert 10000 < len(pts) < 30000
    assert peak < stacked / 2, f"map peak {peak / 2**20:.0f} MiB"


class CountingBackend:
    """Wraps a back end and counts the calls the pipeline makes per keyframe."""

    def __init__(self, inner):
        self.inner, self.pose_calls, self.estimate_calls = inner, 0, 0

    def update(self, *a, **k):
        return self.inner.update(*a, **k)

    def pose(self, kf_id):
        self.pose_calls += 1
        return self.inner.pose(kf_id)

    def estimate(self):
        self.estimate_calls += 1
        return self.inner.estimate()

    def finalize(self):
        return self.inner.finalize()

    def graph(self):
        return self.inner.graph()


def test_per_frame_work_does_not_look_at_the_whole_graph():
    from backends.isam2 import Isam2Backend

    backend = CountingBackend(Isam2Backend())
    pipe = Pipeline(SlamConfig(), frontend=CloudFrontend(n_points=10), backend=backend)
    pipe.run(_scans(60))
    # one single-pose look-up per keyframe (the previous one, for the initial guess), never
    # the whole estimate while running: cost per frame independent of the run's length
    assert backend.pose_calls == 59 and backend.estimate_calls == 0
    assert len(pipe.state.frame_seconds) == 60 and len(pipe.state.backend_seconds) == 60


class StatsPlugin:
    """A factor plugin that reports its own timings (as the loop plugin does)."""

    def __init__(self):
        self.calls = 0

    def on_keyframe(self, kf, graph):
        self.calls += 1
        assert graph.cloud(kf.id) is kf.cloud
        return []

    def stats(self):
        return {"calls": self.calls, "detect_ms_mean": np.float64(1.23456)}


def test_metrics_carry_each_factor_plugins_stats(tmp_path):
    from slam.pipeline import FactorSource

    pipe = Pipeline(
        SlamConfig(),
        frontend=CloudFrontend(n_points=10),
        factor_sources=[FactorSource("mine", StatsPlugin())],
    )
    pipe.run(_scans(7))
    write_outputs(pipe, tmp_path, resolved_config={})
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["factor_stats"] == {"mine": {"calls": 7, "detect_ms_mean": 1.2346}}
    assert m["seconds"]["factor:mine"] >= 0 and "factor:mine" in m["stage_ms_max"]


def test_memory_per_km_is_the_peak_growth_after_the_first_100_frames(tmp_path):
    pipe = Pipeline(SlamConfig(), frontend=CloudFrontend(n_points=10, step=2.0))
    pipe.run(_scans(160))  # 2 m per frame: 120 m after the reference frame
    peak0, path0 = pipe.state.memory_reference
    assert path0 == pytest.approx(198.0) and peak0 > 0
    write_outputs(pipe, tmp_path, resolved_config={})
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["memory_mb_per_km"] >= 0.0 and m["path_length_m"] == pytest.approx(318.0)
    short, _ = _run(20)
    assert short.state.memory_reference is None


def test_accumulator_writes_its_centroids_block_by_block(tmp_path):
    rng = np.random.default_rng(2)
    acc = VoxelCentroidMap(0.5, chunk_points=3000)
    for _ in range(5):
        acc.add(rng.uniform(-20, 20, (2000, 3)))
    ref = acc.centroids()
    for name in ("m.pcd", "m.ply"):
        assert acc.write(tmp_path / name, block=777) == len(ref)
        back = np.asarray(o3d.io.read_point_cloud(str(tmp_path / name)).points)
        np.testing.assert_allclose(back, ref, atol=1e-5)
    assert VoxelCentroidMap(0.5).write(tmp_path / "empty.pcd") == 0
    assert "POINTS 0" in (tmp_path / "empty.pcd").read_text()
