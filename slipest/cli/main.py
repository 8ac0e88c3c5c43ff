"""The ``slipest`` command (also ``python -m slipest``): one subcommand per module of :mod:`slipest.cli`.

Each subcommand module exposes ``add_parser(subparsers)``, which registers
its options and sets ``func`` to the function that runs it (cantools style).
A command with ``--config`` reads its options from that TOML file too
(:mod:`slipest.cli.config_file`); a command with the logging options
(:func:`slipest.cli.command.add_logging_arguments`) logs to stderr, and
its fatal errors are logged at ERROR level.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import re
import sys

from slipest import __version__

#: The "slipest serial: " a command's error message starts with (the logger's name says it).
_COMMAND_PREFIX = re.compile(r"^slipest(?: [\w-]+)?: ")

#: Subcommand modules, in the order ``slipest --help`` lists them.
SUBCOMMANDS = ("demo", "simulate", "replay", "serial_cmd", "can_cmd", "can_server", "diagnose", "calibrate")


def _build() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
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
    return parser, sub.choices


def build_parser() -> argparse.ArgumentParser:
    return _build()[0]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line parsed, with the options of its ``--config`` file where it has one
    (SystemExit with a message naming the file and key when the file cannot be used)."""
    parser, commands = _build()
    args = parser.parse_args(argv)
    if getattr(args, "config", None):
        from slipest.cli.config_file import ConfigFileError, parse_with_config_file

        command_parser = commands[args.command]
        try:
            args = parse_with_config_file(parser, command_parser, argv, args)
        except ConfigFileError as exc:
            command_parser.exit(2, f"{command_parser.prog}: error: {exc}\n")
    if not getattr(args, "func", None):
        parser.print_help()
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not getattr(args, "func", None):
        return 2  # no command: the help was printed
    logs = hasattr(args, "log_level")
    if logs:
        from slipest.cli.command import configure_logging

        configure_logging(args)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader of our stdout went away (e.g. `| head`): not an error of ours
        sys.stderr.close()
        return 0
    except SystemExit as exc:
        if logs and isinstance(exc.code, str):  # a command's fatal error: logged like its other messages
            logging.getLogger(f"slipest.{args.command}").error("%s", _COMMAND_PREFIX.sub("", exc.code, count=1))
            return 1
        raise


if __name__ == "__main__":
    sys.exit(main())
