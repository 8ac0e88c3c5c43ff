"""The ``slipest`` command: one subcommand per module of :mod:`slipest.cli`.

Each subcommand module exposes ``add_parser(subparsers)``, which registers
its options and sets ``func`` to the function that runs it (cantools style).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from slipest import __version__

#: Subcommand modules, in the order ``slipest --help`` lists them.
SUBCOMMANDS = ("demo", "simulate", "replay", "serial_cmd", "can_cmd", "can_server", "diagnose")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slipest",
        description="Online slip estimation for wheel-legged rovers from hub vibration.",
    )
    parser.add_argument("--version", action="version", version=f"slipest {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"slipest.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"slipest.cli.{name}":
                continue  # subcommand not part of this build
            raise
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader of our stdout went away (e.g. `| head`): not an error of ours
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
