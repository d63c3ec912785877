"""Evaluation: evo APE/RPE, KITTI devkit drift, the papers' tables, plots and an HTML report.

``plot_all`` imports matplotlib, so it is loaded on first use only.
"""

from __future__ import annotations

from typing import Any

from slam.eval.kitti import kitti_metric, kitti_metric_scaled
from slam.eval.metrics import EvalOptions, EvalResult, evaluate, evaluate_arrays, read_trajectory
from slam.eval.report import write_report
from slam.eval.tables import ape_table, format_table

__all__ = [
    "EvalOptions",
    "EvalResult",
    "ape_table",
    "evaluate",
    "evaluate_arrays",
    "format_table",
    "kitti_metric",
    "kitti_metric_scaled",
    "plot_all",
    "read_trajectory",
    "write_report",
]


def __getattr__(name: str) -> Any:
    if name == "plot_all":
        from slam.eval.plots import plot_all

        return plot_all
    raise AttributeError(f"module 'slam.eval' has no attribute {name!r}")
