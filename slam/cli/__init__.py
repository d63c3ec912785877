"""The ``slam`` command: one entry point, sub-commands. Only this package prints and exits.

Each sub-command lives in its own module with ``add_parser(sub)`` and its handler; this
module builds the parser and turns errors into exit codes: 0 ok, 1 unexpected failure,
2 bad input or config, 130 interrupted.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from slam.cli import compare, configs, demo, evaluate, info, run, simulate, sweep, view
from slam.cli.common import EXIT_BAD_INPUT, EXIT_FAIL, EXIT_INTERRUPTED, EXIT_OK, eprint
from slam.errors import ConfigError, InputError, SlamError

# the order of ``slam --help``
COMMANDS = (run, view, compare, simulate, evaluate, info, demo, sweep, configs)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="slam", description="Factor-graph LiDAR SLAM: run, compare, evaluate, simulate."
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def _restore_interrupt() -> None:
    """Let SIGINT interrupt a run that was started with it ignored (a job put in the
    background by a non-interactive shell inherits SIG_IGN): `kill -INT` then stops it
    cleanly with every output written, as Ctrl-C does in the foreground."""
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    ):
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _drop_stdout() -> None:
    """The reader of our stdout went away (``slam configs | head``): send the rest of the
    output, and the flush at exit, to /dev/null instead of a BrokenPipeError traceback."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    _restore_interrupt()
    try:
        code = args.func(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return code
    except BrokenPipeError:
        _drop_stdout()
        return EXIT_OK
    except KeyboardInterrupt:
        eprint("interrupted")
        return EXIT_INTERRUPTED
    except SystemError as exc:  # Ctrl-C inside compiled code (numba loading a kernel)
        from slam.interrupts import caused_by_interrupt

        if not caused_by_interrupt(exc):
            raise
        eprint("interrupted")
        return EXIT_INTERRUPTED
    except (InputError, ConfigError) as exc:
        eprint(f"error: {exc}")
        return EXIT_BAD_INPUT
    except SlamError as exc:
        eprint(f"error: {exc}")
        return EXIT_FAIL
