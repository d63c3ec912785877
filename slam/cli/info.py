"""``slam info``: topics, message counts, field layout and rate of an input."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from slam.cli.common import EXIT_OK


def add_parser(sub: Any) -> None:
    q = sub.add_parser("info", help="topics, message counts, field layout and rate of a bag")
    q.add_argument("bag")
    q.add_argument("--json", action="store_true")
    q.set_defaults(func=cmd_info)


def cmd_info(args: argparse.Namespace) -> int:
    from slam.io.info import describe

    info = describe(Path(args.bag))
    if args.json:
        print(json.dumps(info, indent=2, default=str))
    else:
        _print_info(info)
    return EXIT_OK


def _print_info(info: dict[str, Any]) -> None:
    for key, value in info.items():
        if key != "topics":
            print(f"{key}: {value}")
    for topic, t in (info.get("topics") or {}).items():
        print(f"{topic}")
        for k, v in t.items():
            if k == "fields":
                print(
                    "    fields: "
                    + ", ".join(
                        f"{f['name']}:{f['datatype']}@{f['offset']}"
                        if isinstance(f, dict)
                        else str(f)
                        for f in v
                    )
                )
            else:
                print(f"    {k}: {v}")
