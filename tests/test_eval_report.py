"""Plots (PNG files), the papers' table and the self-contained HTML report."""

from __future__ import annotations

import base64
import csv
import io
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam.errors import InputError
from slam.eval.metrics import EvalOptions, evaluate_arrays
from slam.eval.plots import plot_all
from slam.eval.report import markdown_table_to_html, write_report
from slam.eval.tables import ape_table, format_table

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SINGLE = ["trajectory_xy", "trajectory_xz", "ape_over_time", "ape_heatmap", "xyz", "rpy", "speed"]
PIXELS = {  # (width, height) of each plot: figure size x DPI, never cropped to the data
    "trajectory_xy": (800, 700),
    "trajectory_xz": (800, 700),
    "ape_heatmap": (800, 700),
    "loops": (800, 700),
    "overlay_xy": (800, 700),
    "overlay_xz": (800, 700),
    "ape_over_time": (900, 450),
    "speed": (900, 450),
    "ape_overlay": (900, 450),
    "xyz": (900, 750),
    "rpy": (900, 750),
}


def synthetic(noise: float, n: int = 150, seed: int = 1):
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 2 * np.pi, n)
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, 3] = np.column_stack([10 * np.cos(s), 6 * np.sin(s), 0.3 * np.sin(2 * s)])
    gt[:, :3, :3] = Rotation.from_euler("z", (s + np.pi / 2)[:, None]).as_matrix()
    est = gt.copy()
    est[:, :3, 3] += rng.normal(0, noise, (n, 3))
    stamps = np.arange(n) * 0.1
    return evaluate_arrays(stamps, est, stamps, gt, EvalOptions())


pytestmark = pytest.mark.usefixtures("evo_home")  # tests/conftest.py


@pytest.fixture(scope="module")
def results():
    return {"floam": synthetic(0.3), "improved": synthetic(0.1)}


@pytest.fixture(scope="module")
def single_plots(results, tmp_path_factory) -> list[Path]:
    out = tmp_path_factory.mktemp("plots")
    res = results["improved"]
    loop_pos = [res.est_full[[5, 140], :3, 3]]  # already aligned: alignment is ~identity
    return plot_all(res, out, loops=[(3, 145), (10, 130)], loop_positions=loop_pos, prefix="run_")


def assert_png(path: Path, prefix: str) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    assert len(data) > 20_000, (path, len(data))
    assert data[12:16] == b"IHDR"
    size = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert size == PIXELS[path.stem.removeprefix(prefix)], path


def test_plot_all_single_writes_every_plot(single_plots):
    names = [p.stem for p in single_plots]
    assert names == [f"run_{n}" for n in SINGLE] + ["run_loops"]
    for p in single_plots:
        assert_png(p, "run_")


def test_plot_all_several_results_adds_overlays(results, tmp_path):
    files = plot_all(results, tmp_path, prefix="cmp_", per_result=False)
    assert [p.stem for p in files] == ["cmp_overlay_xy", "cmp_overlay_xz", "cmp_ape_overlay"]
    for p in files:
        assert_png(p, "cmp_")
    assert sorted(tmp_path.iterdir()) == sorted(files)


def test_plot_bad_loops_raise(results, tmp_path):
    with pytest.raises(InputError, match="outside"):
        plot_all(results["floam"], tmp_path, loops=[(0, 10_000)])
    with pytest.raises(InputError, match="dict"):
        plot_all(results, tmp_path, loops=[(0, 1)])
    with pytest.raises(InputError, match="outside"):
        plot_all(results, tmp_path, loops={"improved": [(0, 150)]})
    with pytest.raises(InputError, match=r"\(2,3\)"):
        plot_all(results["floam"], tmp_path, loop_positions=[np.zeros(3)])
    assert list(tmp_path.iterdir()) == []  # validated before anything was drawn


def test_ape_table_values_and_improvement():
    base = {"max": 2.0, "mean": 1.0, "median": 0.9, "min": 0.1, "rmse": 1.2, "sse": 9.0, "std": 0.5}
    better = {
        "max": 1.5,
        "mean": 0.8,
        "median": 0.9,
        "min": 0.0,
        "rmse": 0.9,
        "sse": 4.0,
        "std": 0.6,
    }
    rows = ape_table({"floam": {"ape_trans": base}, "improved": better})
    assert [r["Config"] for r in rows] == ["floam", "improved", "% improvement improved vs floam"]
    assert list(rows[0]) == ["Config", "Max", "Mean", "Median", "Min", "RMSE", "Std"]
    imp = rows[2]
    assert imp["Max"] == pytest.approx(25.0)
    assert imp["Mean"] == pytest.approx(20.0)
    assert imp["Median"] == pytest.approx(0.0)
    assert imp["Min"] == pytest.approx(100.0)
    assert imp["RMSE"] == pytest.approx(25.0)
    assert imp["Std"] == pytest.approx(-20.0)
    rows_b = ape_table({"floam": base, "improved": better}, baseline="improved")
    assert rows_b[2]["Config"] == "% improvement floam vs improved"
    assert rows_b[2]["Max"] == pytest.approx(-100 / 3)
    with pytest.raises(InputError):
        ape_table({"x": {"rmse": 1.0}})


def test_ape_table_from_results(results):
    rows = ape_table(results)
    assert rows[1]["RMSE"] == pytest.approx(results["improved"].ape_trans["rmse"])
    assert rows[2]["RMSE"] > 50  # 3x less noise: about 67 % better


def test_format_table_text_markdown_csv():
    rows = [
        {"Config": "a", "RMSE": 1.23456, "Std": None},
        {"Config": "b|c", "RMSE": 2.0, "Std": 0.5},
    ]
    text = format_table(rows, "text", precision=2).splitlines()
    assert text[0].split() == ["Config", "RMSE", "Std"]
    assert text[2].split() == ["a", "1.23", "-"]
    md = format_table(rows, "markdown", precision=3).splitlines()
    assert md[0] == "| Config | RMSE | Std |"
    assert md[2] == "| a | 1.235 | - |"
    assert md[3] == "| b\\|c | 2.000 | 0.500 |"
    parsed = list(csv.reader(io.StringIO(format_table(rows, "csv"))))
    assert parsed == [["Config", "RMSE", "Std"], ["a", "1.2346", "-"], ["b|c", "2.0000", "0.5000"]]
    with pytest.raises(InputError):
        format_table(rows, "latex")


class Collector(HTMLParser):
    def __init__(self):
        super().__init__()
        self.imgs: list[str] = []
        self.cells: list[str] = []
        self.tags: list[str] = []
        self.urls: list[str] = []
        self._in_cell = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if tag == "img":
            self.imgs.append(a["src"])
        for key in ("href", "src"):
            if key in a and not a[key].startswith("data:"):
                self.urls.append(a[key])
        self._in_cell = tag in ("td", "th")

    def handle_endtag(self, tag):
        self._in_cell = False

    def handle_data(self, data):
        if self._in_cell:
            self.cells.append(data)


def test_report_is_self_contained(results, single_plots, tmp_path):
    rows = ape_table(results)
    md = format_table(rows, "markdown")
    html_table = "<table><tr><th>Segments</th></tr><tr><td>42</td></tr></table>"
    path = write_report(
        tmp_path / "sub" / "report.html",
        title="Demo <run>",
        tables={"APE (m)": md, "KITTI": html_table},
        images=single_plots,
        meta={"bag": "demo.bag", "options": results["floam"].to_dict()["options"]},
    )
    text = path.read_text(encoding="utf-8")
    parser = Collector()
    parser.feed(text)
    assert "<title>Demo &lt;run&gt;</title>" in text
    assert "<script" not in text and "<link" not in text and parser.urls == []
    assert len(parser.imgs) == len(single_plots) == 8
    for src, png in zip(parser.imgs, single_plots, strict=True):
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1]) == png.read_bytes()
    for col in ("Config", "Max", "Mean", "Median", "Min", "RMSE", "Std", "Segments", "42"):
        assert col in parser.cells
    assert f"{rows[1]['RMSE']:.4f}" in parser.cells
    assert "% improvement improved vs floam" in parser.cells
    assert "demo.bag" in parser.cells
    assert parser.tags.count("table") == 3  # meta, APE (from markdown), KITTI (html)


def test_report_rejects_missing_or_non_png(tmp_path):
    with pytest.raises(InputError, match="not found"):
        write_report(tmp_path / "r.html", title="t", images=[tmp_path / "none.png"])
    (tmp_path / "x.png").write_bytes(b"GIF89a....")
    with pytest.raises(InputError, match="PNG"):
        write_report(tmp_path / "r.html", title="t", images=[tmp_path / "x.png"])


def test_markdown_conversion_falls_back_to_pre():
    assert markdown_table_to_html("just <text>") == "<pre>just &lt;text&gt;</pre>"
    out = markdown_table_to_html("| a | b |\n|---|---:|\n| x | 1.5 |\n")
    assert out.count("<th>") == 2 and '<td class="num">1.5</td>' in out


def test_report_lead_figure_first_then_tables_sections_and_meta(single_plots, tmp_path):
    lead, mapping, plot = single_plots[0], single_plots[1], single_plots[2]
    path = write_report(
        tmp_path / "report.html",
        title="t",
        lead=[lead],
        tables={"APE": "| a |\n|---|\n| 1 |\n"},
        figures={"Map": [mapping], "Empty": []},
        images=[plot],
        meta={"bag": "x.bag"},
    )
    text = path.read_text(encoding="utf-8")
    parser = Collector()
    parser.feed(text)
    decoded = [base64.b64decode(src.split(",", 1)[1]) for src in parser.imgs]
    assert decoded == [p.read_bytes() for p in (lead, mapping, plot)]
    order = [text.index(s) for s in ("<img", "<h2>APE", "<h2>Map", "<h2>Run", "<h2>Plots")]
    assert order == sorted(order)
    assert "<h2>Empty" not in text  # a section without pictures is left out
    with pytest.raises(InputError, match="not found"):
        write_report(tmp_path / "r.html", title="t", figures={"Map": [tmp_path / "no.png"]})
