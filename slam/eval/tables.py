"""The papers' accuracy table: Max, Mean, Median, Min, RMSE, Std per configuration,
plus "% improvement vs <baseline>" rows (positive = smaller error than the baseline)."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

from slam.errors import InputError

COLUMNS: tuple[tuple[str, str], ...] = (
    ("Max", "max"),
    ("Mean", "mean"),
    ("Median", "median"),
    ("Min", "min"),
    ("RMSE", "rmse"),
    ("Std", "std"),
)
FORMATS = ("text", "markdown", "csv")


def _stats_of(result: Any, metric: str) -> Mapping[str, float]:
    """The statistics dict of ``metric`` from an EvalResult, its ``to_dict()`` or a stats dict."""
    if hasattr(result, "to_dict") and not isinstance(result, Mapping):
        result = result.to_dict()
    if not isinstance(result, Mapping):
        raise InputError(f"table input must be a result or a dict, got {type(result).__name__}")
    stats = result.get(metric, result)
    if not isinstance(stats, Mapping) or any(key not in stats for _, key in COLUMNS):
        raise InputError(
            f"no {metric} statistics ({', '.join(k for _, k in COLUMNS)}) in table input"
        )
    return stats


def ape_table(
    results: Mapping[str, Any], metric: str = "ape_trans", baseline: str | None = None
) -> list[dict]:
    """Rows ``{"Config", "Max", ..., "Std"}`` per configuration in insertion order, then one
    ``"% improvement <name> vs <baseline>"`` row per other configuration.

    ``results`` maps a configuration name to an ``EvalResult``, its ``to_dict()`` or a plain
    stats dict. ``baseline`` defaults to the first configuration; improvement is
    ``(baseline - value) / baseline * 100`` (``None`` when the baseline value is 0).
    """
    if not results:
        raise InputError("ape_table needs at least one result")
    stats = {name: _stats_of(res, metric) for name, res in results.items()}
    base = baseline if baseline is not None else next(iter(stats))
    if base not in stats:
        raise InputError(f"baseline {base!r} not among {list(stats)}")
    rows = [
        {"Config": name, **{col: float(s[key]) for col, key in COLUMNS}}
        for name, s in stats.items()
    ]
    for name, s in stats.items():
        if name == base:
            continue
        row: dict = {"Config": f"% improvement {name} vs {base}"}
        for col, key in COLUMNS:
            b = float(stats[base][key])
            row[col] = None if b == 0 else (b - float(s[key])) / b * 100.0
        rows.append(row)
    return rows


def _cell(value: Any, precision: int) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return f"{value:.{precision}f}"
    return str(value)


def format_table(rows: Sequence[Mapping[str, Any]], fmt: str = "text", precision: int = 4) -> str:
    """Render rows (dicts sharing keys; columns in first-seen order) as text, markdown or csv."""
    if fmt not in FORMATS:
        raise InputError(f"table format must be one of {FORMATS}, got {fmt!r}")
    header: list[str] = []
    for row in rows:
        header.extend(k for k in row if k not in header)
    cells = [[_cell(row.get(k), precision) for k in header] for row in rows]
    if fmt == "csv":
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(cells)
        return buf.getvalue()
    if fmt == "markdown":
        lines = ["| " + " | ".join(header) + " |"]
        lines.append("|" + "|".join(":---" if i == 0 else "---:" for i in range(len(header))) + "|")
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in cells]
        return "\n".join(lines) + "\n"
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]

    def line(items: Sequence[str]) -> str:
        return "  ".join(
            s.ljust(w) if i == 0 else s.rjust(w)
            for i, (s, w) in enumerate(zip(items, widths, strict=True))
        ).rstrip()

    out = [line(header), line(["-" * w for w in widths])] + [line(r) for r in cells]
    return "\n".join(out) + "\n"
