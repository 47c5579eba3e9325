"""Command-line interface: one argparse sub-command per module in app/commands/.

Each command module defines ``register(subparsers)`` which adds its parser and sets
``func`` (called with the parsed namespace, returning an exit code). Errors the user
can fix (bad files, bad arguments) are raised as ``UserError`` and exit with code 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from fileio import OutputFileError

# Order here is the order shown in --help.
COMMAND_MODULES = [
    "app.commands.race",
    "app.commands.batch",
    "app.commands.demo",
    "app.commands.solve",
    "app.commands.scenario",
    "app.commands.bench",
    "app.commands.calibrate",
    "app.commands.calibrate_camera", "app.commands.make_board", "app.commands.mocap_calibrate",
    "app.commands.review",
    "app.commands.link_decode",
    "app.commands.check",
    "app.commands.sysid",
    "app.commands.track",
    "app.commands.track_tools",
    "app.commands.measure_marker",
]


class UserError(Exception):
    """An input problem the user can fix; printed without a traceback, exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m app",
        description="RD3G racing stack: game solver, simulator, race loop and tools.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # validation errors from the packages name the field at fault
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OutputFileError as exc:  # one line naming the path; the helper left no partial file
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.filename is None:
            raise
        print(f"error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # commands that keep results on Ctrl-C handle it themselves
        print("interrupted", file=sys.stderr)
        return 130
