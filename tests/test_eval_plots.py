"""Figures drawn by evo.tools.plot carry the data they show (slam/eval/plots.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_eval_report import synthetic

from slam.errors import InputError
from slam.eval import plots

pytestmark = pytest.mark.usefixtures("evo_home")  # tests/conftest.py


@pytest.fixture(scope="module")
def res():
    return synthetic(0.1)


@pytest.fixture
def close():
    """Collects figures and closes them after the test."""
    import matplotlib.pyplot as plt

    figs = []
    yield figs.append
    for f in figs:
        plt.close(f)


def lines_by_label(ax) -> dict:
    return {line.get_label(): line.get_xydata() for line in ax.get_lines()}


@pytest.mark.parametrize("plane,cols", [("xy", [0, 1]), ("xz", [0, 2])])
def test_trajectory_axes_hold_ground_truth_and_estimate(res, close, plane, cols):
    fig = plots.trajectory_figure(res, plane)
    close(fig)
    lines = lines_by_label(fig.axes[0])
    assert lines["ground truth"].shape == lines["estimate"].shape == (res.n_matched, 2)
    np.testing.assert_allclose(lines["ground truth"], res.gt_poses[:, cols, 3])
    np.testing.assert_allclose(lines["estimate"], res.est_poses[:, cols, 3])
    assert fig.axes[0].get_xlabel() == "$x$ (m)"


def test_colormap_colours_are_the_ape_values(res, close):
    from matplotlib import colormaps
    from matplotlib.colors import Normalize

    fig = plots.ape_colormap_figure(res)
    close(fig)
    ax, cax = fig.axes
    (lc,) = ax.collections
    err = res.ape_errors
    assert np.ptp(err) > 0.1  # the colours below really differ along the path
    cmap = colormaps[plots.evo_plot().SETTINGS.plot_trajectory_cmap]
    expected = cmap(Normalize(err.min(), err.max())(err))
    segs = lc.get_segments()
    assert len(segs) == res.n_matched - 1
    np.testing.assert_allclose(np.array(segs)[:, 0], res.est_poses[:-1, :2, 3])
    np.testing.assert_allclose(lc.get_colors()[: len(segs)], expected[: len(segs)], atol=1e-12)
    np.testing.assert_allclose(cax.get_ylim(), (err.min(), err.max()))
    gt = lines_by_label(ax)["ground truth"]
    np.testing.assert_allclose(gt, res.gt_poses[:, :2, 3])


def test_ape_over_time_line_and_statistics(res, close):
    fig = plots.ape_figure(res)
    close(fig)
    lines = lines_by_label(fig.axes[0])
    np.testing.assert_allclose(lines["APE"][:, 0], res.stamps - res.stamps[0])
    np.testing.assert_allclose(lines["APE"][:, 1], res.ape_errors)
    for key in ("rmse", "mean", "median"):
        np.testing.assert_allclose(lines[key][:, 1], res.ape_trans[key])


def test_xyz_and_rpy_over_time(res, close):
    from scipy.spatial.transform import Rotation

    fig = plots.xyz_figure(res)
    close(fig)
    assert len(fig.axes) == 3
    for k, ax in enumerate(fig.axes):
        lines = lines_by_label(ax)
        np.testing.assert_allclose(lines["estimate"][:, 1], res.est_poses[:, k, 3])
        np.testing.assert_allclose(lines["ground truth"][:, 1], res.gt_poses[:, k, 3])
        np.testing.assert_allclose(lines["estimate"][:, 0], res.stamps - res.stamps[0])
    fig = plots.rpy_figure(res)
    close(fig)
    rpy = Rotation.from_matrix(res.gt_poses[:, :3, :3]).as_euler("xyz")  # evo's sxyz
    rpy = np.degrees(np.unwrap(rpy, axis=0))
    assert np.ptp(rpy[:, 2]) > 350  # a whole turn of yaw, through +-180 deg
    for k, ax in enumerate(fig.axes):
        lines = lines_by_label(ax)
        np.testing.assert_allclose(lines["ground truth"][:, 1], rpy[:, k], atol=1e-9)
        est = lines["estimate"][:, 1]
        assert np.abs(np.diff(est)).max() < 10  # no jump at +-180 deg
        assert np.abs(est - rpy[:, k]).max() < 1  # same branch as the ground truth
        assert ax.get_ylim()[1] >= rpy[:, k].max()  # rescaled to the unwrapped data


def test_speed_is_distance_over_time(res, close):
    fig = plots.speed_figure(res)
    close(fig)
    lines = lines_by_label(fig.axes[0])
    v = np.linalg.norm(np.diff(res.gt_poses[:, :3, 3], axis=0), axis=1) / np.diff(res.stamps)
    np.testing.assert_allclose(lines["ground truth"][:, 1], v)
    assert lines["estimate"][:, 1].mean() > v.mean()  # noise adds apparent speed


def test_loop_edges_join_the_right_poses(res, close):
    seg = plots._loop_segments(res, [(3, 145), (10, 130)], None)
    fig = plots.loops_figure(res, seg)
    close(fig)
    ax = fig.axes[0]
    edges = [c for c in ax.collections if c.get_label().startswith("loop closures (2)")]
    (lc,) = edges
    got = np.array(lc.get_segments())
    np.testing.assert_allclose(got, res.est_full[[[3, 145], [10, 130]]][:, :, :2, 3])
    assert lines_by_label(ax)["estimate"].shape == (res.n_est, 2)


def test_overlay_names_every_run_with_its_rmse(close):
    results = {"floam": synthetic(0.3), "improved": synthetic(0.1)}
    fig = plots.overlay_figure(results)
    close(fig)
    lines = lines_by_label(fig.axes[0])
    for name, r in results.items():
        np.testing.assert_allclose(
            lines[f"{name} (RMSE {r.ape_trans['rmse']:.3f} m)"], r.est_poses[:, :2, 3]
        )
    fig = plots.ape_overlay_figure(results)
    close(fig)
    lines = lines_by_label(fig.axes[0])
    np.testing.assert_allclose(lines["floam"][:, 1], results["floam"].ape_errors)
    assert not np.allclose(lines["floam"][:, 1], lines["improved"][:, 1])


def test_bad_plane_is_an_input_error(res):
    with pytest.raises(InputError, match="plane"):
        plots.trajectory_figure(res, "ab")


def test_plot_all_leaves_no_open_figure(res, tmp_path):
    import matplotlib.pyplot as plt

    before = set(plt.get_fignums())
    plots.plot_all(res, tmp_path)
    assert set(plt.get_fignums()) == before


SCRIPT = """
import matplotlib
from test_eval_report import synthetic  # tests/ on the child's PYTHONPATH
from slam.eval.plots import plot_all
files = plot_all(synthetic(0.1, n=40), {out!r})
print(matplotlib.get_backend(), len(files))
"""


def test_fresh_interpreter_with_a_gui_backend_in_evo_settings_draws_with_agg(tmp_path):
    """A user whose ~/.evo asks for TkAgg, with no display, gets PNGs and no window; evo's
    "Updated outdated ~/.evo/settings.json" line does not reach stdout."""
    from evo.tools.settings_template import DEFAULT_SETTINGS_DICT

    evo_dir = tmp_path / "home" / ".evo"
    evo_dir.mkdir(parents=True)
    (evo_dir / "assets_version").write_text("0.0.1")  # outdated: evo rewrites and prints
    settings = {**DEFAULT_SETTINGS_DICT, "plot_backend": "TkAgg"}
    (evo_dir / "settings.json").write_text(json.dumps(settings))
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "MPLBACKEND")}
    env["HOME"] = str(tmp_path / "home")
    env["PYTHONPATH"] = str(Path(__file__).parent)
    script = SCRIPT.format(out=str(tmp_path / "out"))
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["agg", "7"]
    assert len(list((tmp_path / "out").glob("*.png"))) == 7
    assert (evo_dir / "assets_version").read_text() != "0.0.1"  # evo did run its update
    assert json.loads((evo_dir / "settings.json").read_text())["plot_backend"] == "TkAgg"


def test_odometry_vs_loop_figure_shows_both_estimates_and_the_loops(close):
    odom, closed = synthetic(0.4, seed=3), synthetic(0.1, seed=4)
    loop_pos = [closed.est_full[[5, 140], :3, 3], closed.est_full[[20, 120], :3, 3]]
    fig = plots.odometry_vs_loop_figure(odom, closed, loop_pos)
    close(fig)
    traj_ax, zoom_ax, ape_ax = fig.axes
    lines = lines_by_label(traj_ax)
    odom_key = next(k for k in lines if k.startswith("odometry only"))
    loop_key = next(k for k in lines if k.startswith("loop closed"))
    assert f"{odom.ape_trans['rmse']:.2f} m" in odom_key
    np.testing.assert_allclose(lines[odom_key], odom.est_poses[:, :2, 3])
    np.testing.assert_allclose(lines[loop_key], closed.est_poses[:, :2, 3])
    np.testing.assert_allclose(lines["ground truth"], closed.gt_poses[:, :2, 3])
    (edges,) = [c for c in traj_ax.collections if c.get_label().startswith("loop closures")]
    assert edges.get_label() == "loop closures (2)"
    A = closed.alignment  # loop positions are in the run's frame: aligned like the estimate
    aligned = loop_pos[0] @ A[:3, :3].T + A[:3, 3]
    np.testing.assert_allclose(edges.get_segments()[0], aligned[:, :2], atol=1e-9)
    ape = lines_by_label(ape_ax)
    np.testing.assert_allclose(ape["odometry only"][:, 1], odom.ape_errors)
    np.testing.assert_allclose(ape["loop closed"][:, 1], closed.ape_errors)
    assert ape["loop closed"][-1, 0] == pytest.approx(closed.path_length, rel=0.05)
    assert len(lines_by_label(zoom_ax)) == 4  # the same lines, zoomed on the worst odometry
    centre = np.array([np.mean(zoom_ax.get_xlim()), np.mean(zoom_ax.get_ylim())])
    mids = [(seg[0, :2] + seg[1, :2]) / 2 for seg in edges.get_segments()]
    assert min(np.linalg.norm(centre - m) for m in mids) < 1.0  # on a revisit: both passes
    assert "revisit" in zoom_ax.get_title()
    assert fig.get_size_inches() * fig.dpi == pytest.approx((1900, 650))
    no_loops = plots.odometry_vs_loop_figure(odom, closed)  # without loops: the worst pose
    close(no_loops)
    zoom = no_loops.axes[1]
    worst = odom.gt_poses[np.argmax(odom.ape_errors), :2, 3]
    assert np.mean(zoom.get_xlim()) == pytest.approx(worst[0])
    assert np.mean(zoom.get_ylim()) == pytest.approx(worst[1])


def test_legend_lengths_keep_centimetre_results_apart():
    from slam.eval.plots import _length

    assert _length(0.0112) == "1.1 cm" and _length(0.0149) == "1.5 cm"
    assert _length(0.7183) == "0.72 m"
