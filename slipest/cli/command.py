"""How a ``slipest`` subcommand declares itself (one way for every module of :mod:`slipest.cli`).

:func:`add_command` registers a subcommand; :func:`add_logging_arguments`
gives a command ``-v``/``-q``/``--log-level``, which :func:`configure_logging`
turns into :mod:`logging` on stderr with time and level (what a service's
journal needs), the command's data staying on stdout.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading


def add_command(sub, name: str, summary: str, doc: str) -> argparse.ArgumentParser:
    """Register subcommand ``name`` and return its parser.

    ``summary``: its line in ``slipest --help``; ``doc``: its module's
    docstring, whose text after the first paragraph is the command's
    description in ``slipest NAME --help`` (line breaks kept).
    """
    return sub.add_parser(name, help=summary, description=doc.split("\n\n", 1)[1],
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def whole_number(what: str, least: int):
    """An argparse type: a whole number >= ``least``, else the error ``'TEXT' is not WHAT (a whole number >= N)``."""

    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            n = least - 1
        if n < least:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what} (a whole number >= {least})")
        return n

    parse.__name__ = what.replace(" ", "_")
    return parse


#: ``--legs``: a whole number of legs >= 1.
leg_count = whole_number("a number of legs", 1)
#: ``--jobs``: a whole number of worker processes >= 1.
job_count = whole_number("a number of worker processes", 1)
#: ``--seed``: a whole number >= 0, as numpy's generators take.
seed_number = whole_number("a seed", 0)


def interrupt_on_sigterm():
    """Make SIGTERM raise KeyboardInterrupt, as Ctrl-C does, so a command stopped either way cleans up; returns
    the handler to restore (``signal.signal(signal.SIGTERM, it)``), or None off the main thread, where no
    handler can be set."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def _term(signum, frame):
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, _term)


#: Log levels ``--log-level`` takes.
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
#: How a message looks on stderr: time to the millisecond, level, logger, text.
LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
LOG_DATE_FORMAT = "%Y-%m-%d %H:%M:%S"


def add_logging_arguments(p: argparse.ArgumentParser) -> None:
    """Add ``-v``/``-q``/``--log-level``: how much a command says on stderr (through :mod:`logging`);
    its data stays on stdout."""
    g = p.add_argument_group("messages (stderr, with time and level)")
    g.add_argument("-v", "--verbose", action="count", default=0,
                   help="more messages: debugging details, python-can's included")
    g.add_argument("-q", "--quiet", action="count", default=0,
                   help="fewer messages: -q warnings and errors only, -qq errors only")
    g.add_argument("--log-level", type=str.upper, choices=LOG_LEVELS, default=None,
                   help="the level itself (overrides -v/-q; default INFO)")


def log_level(args: argparse.Namespace) -> int:
    """The level the logging options of ``args`` ask for (INFO when none is given)."""
    if getattr(args, "log_level", None):
        return getattr(logging, args.log_level)
    steps = getattr(args, "quiet", 0) - getattr(args, "verbose", 0)
    return min(max(logging.INFO + 10 * steps, logging.DEBUG), logging.ERROR)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is when a record comes (a test may have replaced it since)."""

    def __init__(self):
        logging.Handler.__init__(self)

    @property
    def stream(self):
        return sys.stderr


def configure_logging(args: argparse.Namespace) -> int:
    """Send log records of ``log_level(args)`` and above to stderr, with time and level (one handler on
    the root logger, replacing the one an earlier call added); returns the level."""
    level = log_level(args)
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _StderrHandler)]:
        root.removeHandler(handler)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(LOG_FORMAT, LOG_DATE_FORMAT))
    root.addHandler(handler)
    root.setLevel(level)
    return level
