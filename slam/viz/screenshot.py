"""A screenshot of a report in headless Chromium: what a user sees when opening it.

``python -m slam.viz.screenshot RUN/report.html OUT.png [--width 1200] [--height 4000]``
needs a Chromium (Debian: ``apt-get install -y chromium``). Chromium runs with a fresh
profile folder and every background service off (no network traffic, no first-run UI).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from slam.errors import InputError

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "chrome")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
)


def find_browser() -> str:
    """The path of a Chromium on PATH, or an InputError saying how to install one."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    raise InputError("no Chromium found for the screenshot: apt-get install -y chromium")


def screenshot(html: Path, png: Path, width: int = 1200, height: int = 4000) -> Path:
    """Render ``html`` at ``width`` x ``height`` CSS pixels into ``png``; returns ``png``."""
    html, png = Path(html).resolve(), Path(png).resolve()
    if not html.is_file():
        raise InputError(f"report not found: {html}")
    png.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="slam-chromium-") as profile:
        cmd = [
            find_browser(),
            *FLAGS,
            f"--user-data-dir={profile}",
            f"--window-size={width},{height}",
            f"--screenshot={png}",
            html.as_uri(),
        ]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    if res.returncode != 0 or not png.is_file():
        raise InputError(f"chromium could not take the screenshot: {res.stderr.strip()[-500:]}")
    return png


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("html")
    p.add_argument("png")
    p.add_argument("--width", type=int, default=1200)
    p.add_argument("--height", type=int, default=4000)
    args = p.parse_args(argv)
    try:
        out = screenshot(Path(args.html), Path(args.png), args.width, args.height)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
