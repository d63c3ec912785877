"""Bird's-eye pictures of the map (slam/viz/birdseye.py): the raster holds the highest point
per cell, a run's report shows its map.pcd, the map before / after loop closure moves the
clouds by the optimised poses, and map.pgm is shown pixel for pixel."""

from __future__ import annotations

import base64
import dataclasses
import re
from types import SimpleNamespace

import numpy as np
import pytest

from slam.config import load_config
from slam.run import run_one
from slam.viz import birdseye
from slam.viz.birdseye import Grid, HeightRaster

pytestmark = pytest.mark.usefixtures("evo_home")  # tests/conftest.py


def test_raster_keeps_the_highest_point_of_each_cell():
    grid = Grid(x0=0.0, y0=0.0, cell=1.0, nx=4, ny=3)
    r = HeightRaster(grid)
    r.add(np.array([[0.5, 0.5, 1.0], [0.7, 0.2, 3.0], [3.5, 2.5, -1.0], [9.0, 0.5, 7.0]]))
    r.add(np.array([[0.1, 0.9, 2.0]]))
    img = r.image()
    assert img.shape == (3, 4) and r.filled == 2
    assert img[0, 0] == 3.0 and img[2, 3] == -1.0  # row 0 is y0 (the bottom)
    assert np.isnan(img).sum() == 10  # the point at x = 9 m is outside: left out
    assert grid.extent == (0.0, 4.0, 0.0, 3.0)


def test_grid_frames_the_trajectory_and_shrinks_to_the_points():
    xy = np.array([[0.0, 0.0], [100.0, 20.0]])
    g = Grid.around(xy, margin=25.0, pixels=500)
    assert g.extent[0] == -25.0 and g.extent[1] >= 125.0 and g.cell == pytest.approx(0.3)
    pts = np.random.default_rng(0).uniform([-5, -3, 0], [105, 23, 5], (5000, 3))
    small = Grid.around(xy, points=pts)
    assert -7.0 < small.extent[0] < -4.0 and 104.0 < small.extent[1] < 108.0


def colour_fraction(png) -> float:
    """Fraction of the picture's pixels that are neither grey nor white (the map's colours)."""
    import matplotlib.image

    rgb = matplotlib.image.imread(png)[:, :, :3]
    return float((np.ptp(rgb, axis=2) > 0.15).mean())


@pytest.fixture(scope="module")
def run_dir(corridor_short, tmp_path_factory):
    out = tmp_path_factory.mktemp("mapview") / "run"
    config = load_config("improved_floam")
    config.source = dataclasses.replace(config.source, max_frames=40)
    run_one(corridor_short.bag, config, out, gt=corridor_short.ground_truth, quiet=True)
    return out


def test_report_shows_the_map_of_the_run(run_dir):
    png = run_dir / "plots" / birdseye.MAP_PNG
    assert png.is_file()
    text = (run_dir / "report.html").read_text()
    assert "<h2>Map</h2>" in text
    srcs = re.findall(r'src="data:image/png;base64,([^"]+)"', text)
    assert base64.b64decode(srcs[0]) == png.read_bytes()  # the first picture is the map
    assert colour_fraction(png) > 0.08  # the map's colours, not an empty axis
    points = birdseye.read_map_points(run_dir / "map.pcd")
    assert len(points) > 1000


def test_map_pgm_is_shown_as_it_is(tmp_path):
    import matplotlib.image

    img = (np.arange(12 * 7) * 3 % 256).astype(np.uint8).reshape(7, 12)
    pgm = tmp_path / "map.pgm"
    pgm.write_bytes(b"P5\n12 7\n255\n" + img.tobytes())
    png = birdseye.pgm_png(pgm, tmp_path / "map.png")
    shown = matplotlib.image.imread(png)
    assert shown.shape[:2] == (7, 12)
    np.testing.assert_allclose(shown[:, :, 0] * 255, img, atol=0.5)
    assert birdseye.map_images(tmp_path) == [tmp_path / "plots" / birdseye.MAP_PGM_PNG]


def fake_pipeline():
    """Two passes along a wall 8 m north: the odometry of the second pass drifted 1.5 m
    north, the optimised poses put it back; one accepted loop joins the passes."""
    wall = np.column_stack([np.linspace(-15, 15, 600), np.full(600, 8.0), np.full(600, 2.0)])
    keyframes, odom, est = [], {}, {}
    for k, (x, drift) in enumerate([(0.0, 0.0), (10.0, 0.0), (0.0, 1.5)]):
        T_true = np.eye(4)
        T_true[0, 3] = x
        T_odom = T_true.copy()
        T_odom[1, 3] += drift
        cloud = (wall - T_true[:3, 3]).astype(np.float32)  # the wall seen from the true pose
        keyframes.append(SimpleNamespace(id=k, cloud=cloud, pose_odom=T_odom))
        odom[k], est[k] = T_odom, T_true
    frames = [odom[k] for k in (0, 1, 2)]
    state = SimpleNamespace(
        keyframes=keyframes,
        estimates=est,
        odom_poses=frames,
        trajectory=lambda: np.stack([est[k] for k in (0, 1, 2)]),
        loop_pairs=[(0, 2)],  # the loop edge in the graph
    )
    return SimpleNamespace(state=state, factor_sources=[])


def test_map_before_and_after_loop_closure(close_figures):
    pipeline = fake_pipeline()
    before, after, odom_xy, opt_xy = birdseye.keyframe_maps(pipeline)
    rows_before = np.flatnonzero(np.isfinite(before.image()).any(axis=1))
    rows_after = np.flatnonzero(np.isfinite(after.image()).any(axis=1))
    cell = before.grid.cell
    assert (rows_before.max() - rows_before.min()) * cell > 1.3  # the wall seen twice
    assert (rows_after.max() - rows_after.min()) * cell < 0.5  # one wall again
    np.testing.assert_allclose(odom_xy[2], [0.0, 1.5])
    fig = birdseye.loop_map_figure(pipeline)
    close_figures(fig)
    left, right = fig.axes[:2]
    (edges_before,) = [c for c in left.collections if c.get_label().startswith("loop")]
    (edges_after,) = [c for c in right.collections if c.get_label().startswith("loop")]
    np.testing.assert_allclose(edges_before.get_segments()[0], [[0, 0], [0, 1.5]])
    np.testing.assert_allclose(edges_after.get_segments()[0], [[0, 0], [0, 0]])
    assert "before" in left.get_title() and "after" in right.get_title()


@pytest.fixture
def close_figures():
    import matplotlib.pyplot as plt

    figs = []
    yield figs.append
    for f in figs:
        plt.close(f)


def test_a_2d_run_shows_its_grid_in_metres_under_the_trajectory(tmp_path):
    import matplotlib.image

    img = np.full((40, 60), 254, dtype=np.uint8)
    img[5, :] = 0  # a wall along the top row: y = -1 + (40 - 5.5) * 0.1 = 2.45 m
    (tmp_path / "map.pgm").write_bytes(b"P5\n60 40\n255\n" + img.tobytes())
    (tmp_path / "map.yaml").write_text(
        "image: map.pgm\nresolution: 0.100000\norigin: [-2.000000, -1.000000, 0.0]\n"
    )
    rows = [f"{0.1 * k} {0.1 * k} 0.5 0 0 0 0 1" for k in range(20)]
    (tmp_path / "trajectory.tum").write_text("\n".join(rows) + "\n")
    fig = birdseye.grid_figure(tmp_path / "map.pgm", np.column_stack([np.arange(20) * 0.1] * 2))
    ax = fig.axes[0]
    assert ax.images[0].get_extent() == [-2.0, 4.0, -1.0, 3.0]
    assert ax.get_ylim()[1] >= 2.45 + 2.0 - 1e-9  # the wall and a margin are in view
    out = birdseye.map_images(tmp_path)
    assert out == [tmp_path / "plots" / birdseye.MAP_PNG, tmp_path / "plots" / birdseye.MAP_PGM_PNG]
    assert matplotlib.image.imread(out[0]).shape[1] > 500
