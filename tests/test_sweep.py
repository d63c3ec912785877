"""Sweep grid parsing, job layout and the heat map."""

from pathlib import Path

import pytest

from slam.errors import ConfigError
from slam.sweep import grid_points, make_jobs, parse_grid, plot_heatmap, write_table


def test_parse_grid_and_points():
    grid = parse_grid(["frontend.sor.k=5,10", "frontend.sor.alpha=0.5,1.0,2.0"])
    assert grid == {"frontend.sor.k": [5, 10], "frontend.sor.alpha": [0.5, 1.0, 2.0]}
    points = grid_points(grid)
    assert len(points) == 6 and points[0] == {"frontend.sor.k": 5, "frontend.sor.alpha": 0.5}
    with pytest.raises(ConfigError):
        parse_grid(["frontend.sor.k"])


def test_jobs_cover_inputs_times_grid(tmp_path):
    grid = parse_grid(["a.b=1,2", "c.d=x,y"])
    jobs = make_jobs([("s1.bag", "g1"), ("s2.bag", "g2")], grid, "floam", tmp_path, ["e.f=3"])
    assert len(jobs) == 8
    assert jobs[0].overrides == ("e.f=3", "a.b=1", "c.d=x")
    assert len({j.out for j in jobs}) == 8


def test_heatmap_and_table_written(tmp_path):
    grid = parse_grid(["k=5,10", "alpha=0.5,1.0"])
    rows = [
        {"input": "s", "k": str(k), "alpha": str(a), "ape_rmse": 0.01 * k * a}
        for k in (5, 10)
        for a in (0.5, 1.0)
    ]
    png = plot_heatmap(rows, grid, tmp_path / "h.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    write_table(rows, tmp_path / "t.csv")
    assert Path(tmp_path / "t.csv").read_text().count("\n") == 5


def test_sweep_runs_grid_points_with_diagnostics(corridor_short, tmp_path):
    """Two SOR strictness levels on a real (simulated) bag: both run, the stricter one keeps
    fewer points, and every row carries accuracy and the front end's per-frame means."""
    from slam.sweep import run_sweep

    grid = {"frontend.sor.alpha": [0.3, 3.0]}
    jobs = make_jobs(
        [(str(corridor_short.bag), str(corridor_short.ground_truth))],
        grid,
        "improved_floam",
        tmp_path,
        max_frames=12,
    )
    rows = run_sweep(jobs, workers=1)
    assert [r["error"] for r in rows] == ["", ""]
    strict, lenient = rows
    assert 0.0 < strict["ape_rmse"] < 0.05 and 0.0 < lenient["ape_rmse"] < 0.05
    assert 80.0 < strict["kept_pct"] < lenient["kept_pct"] <= 100.0
    assert strict["sor_ms"] > 0 and strict["n_planes"] > 50 and strict["frames"] == 12
    metrics = (Path(jobs[0].out) / "metrics.json").read_text()
    assert '"frontend_means"' in metrics and '"n_after_sor"' in metrics
