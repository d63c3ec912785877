"""One self-contained HTML report: inline CSS, tables, base64-embedded PNG plots.

No scripts, fonts or links to fetch: the file opens offline and can be mailed as is.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from slam.errors import InputError

CSS = """
body { font-family: -apple-system, "Segoe UI", Helvetica, Arial, sans-serif; margin: 2em auto;
       max-width: 1100px; color: #222; line-height: 1.4; padding: 0 1em; }
h1 { border-bottom: 2px solid #2c6fbb; padding-bottom: .2em; }
h2 { margin-top: 1.6em; color: #2c6fbb; }
table { border-collapse: collapse; margin: .8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: .3em .7em; }
th { background: #eef3fa; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr:nth-child(even) td { background: #fafafa; }
figure { margin: 1em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: .9em; color: #555; }
pre { background: #f6f6f6; padding: .6em; overflow-x: auto; }
.meta td:first-child { font-weight: 600; }
"""

_NUM_TD = '<td class="num">'
_NUM = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?%?$")


def _split_row(line: str) -> list[str]:
    line = line.strip()
    if line.startswith("|"):
        line = line[1:]
    if line.endswith("|") and not line.endswith("\\|"):
        line = line[:-1]
    cells = re.split(r"(?<!\\)\|", line)
    return [c.strip().replace("\\|", "|") for c in cells]


def markdown_table_to_html(text: str) -> str:
    """A pipe table (header, ``---`` rule, rows) as an HTML table; other text as <pre>."""
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    rule = re.compile(r"^\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?$")
    if len(lines) < 2 or "|" not in lines[0] or not rule.match(lines[1].strip()):
        return f"<pre>{html.escape(text)}</pre>"
    head = "".join(f"<th>{html.escape(c)}</th>" for c in _split_row(lines[0]))
    body = []
    for ln in lines[2:]:
        tds = "".join(
            (_NUM_TD if _NUM.match(c) else "<td>") + html.escape(c) + "</td>"
            for c in _split_row(ln)
        )
        body.append(f"<tr>{tds}</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _table_html(content: str) -> str:
    """HTML fragments (starting with '<') pass through; markdown pipe tables are converted."""
    return content if content.lstrip().startswith("<") else markdown_table_to_html(content)


def _meta_html(meta: Mapping[str, Any]) -> str:
    rows = []
    for key, value in meta.items():
        if isinstance(value, (dict, list, tuple)):
            shown = f"<pre>{html.escape(json.dumps(value, indent=1, default=str))}</pre>"
        else:
            shown = html.escape(str(value))
        rows.append(f"<tr><td>{html.escape(str(key))}</td><td>{shown}</td></tr>")
    return f'<table class="meta"><tbody>{"".join(rows)}</tbody></table>'


def _image_html(path: Path) -> str:
    data = path.read_bytes()
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise InputError(f"report images must be PNG files: {path}")
    b64 = base64.b64encode(data).decode("ascii")
    name = html.escape(path.stem.replace("_", " "))
    return (
        f'<figure><img src="data:image/png;base64,{b64}" alt="{name}">'
        f"<figcaption>{name}</figcaption></figure>"
    )


def write_report(
    path: str | Path,
    *,
    title: str,
    tables: Mapping[str, str] | None = None,
    images: Sequence[str | Path] = (),
    meta: Mapping[str, Any] | None = None,
    figures: Mapping[str, Sequence[str | Path]] | None = None,
    lead: Sequence[str | Path] = (),
) -> Path:
    """Write one offline HTML file: title, ``lead`` figures (the point of the page, above
    everything else), ``meta`` key/values, ``tables`` (name -> markdown pipe table or HTML
    fragment), ``figures`` (section name -> PNGs, e.g. the map), then ``images`` (PNG
    files under "Plots"); every PNG is base64-embedded."""
    path = Path(path)
    images = [Path(p) for p in images]
    lead = [Path(p) for p in lead]
    sections = {name: [Path(p) for p in pngs] for name, pngs in (figures or {}).items()}
    for img in [*lead, *images, *(p for pngs in sections.values() for p in pngs)]:
        if not img.is_file():
            raise InputError(f"report image not found: {img}")
    stamp = _dt.datetime.now().isoformat(timespec="seconds")
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f'<p class="generated">Generated {stamp}</p>',
    ]
    parts += [_image_html(img) for img in lead]
    for name, content in (tables or {}).items():
        parts += [f"<h2>{html.escape(name)}</h2>", _table_html(content)]
    for name, pngs in sections.items():
        if pngs:
            parts.append(f"<h2>{html.escape(name)}</h2>")
            parts += [_image_html(img) for img in pngs]
    if meta:
        parts += ["<h2>Run</h2>", _meta_html(meta)]
    if images:
        parts.append("<h2>Plots</h2>")
        parts += [_image_html(img) for img in images]
    parts.append("</body></html>")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(parts) + "\n", encoding="utf-8")
    return path
