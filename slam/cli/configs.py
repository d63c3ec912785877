"""``slam configs``: the built-in recipes and the installed plugins of each group."""

from __future__ import annotations

import argparse
from typing import Any

from slam.cli.common import EXIT_OK


def add_parser(sub: Any) -> None:
    q = sub.add_parser("configs", help="list built-in configs and installed plugins")
    q.set_defaults(func=cmd_configs)


def cmd_configs(args: argparse.Namespace) -> int:
    from slam import plugins
    from slam.config import available_configs

    print("configs: " + ", ".join(available_configs()))
    for group in plugins.GROUPS:
        print(f"{group}: " + ", ".join(plugins.available(group)))
    return EXIT_OK
