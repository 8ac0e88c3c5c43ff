"""How a ``slipest`` subcommand declares itself (one way for every module of :mod:`slipest.cli`)."""

from __future__ import annotations

import argparse


def add_command(sub, name: str, summary: str, doc: str) -> argparse.ArgumentParser:
    """Register subcommand ``name`` and return its parser.

    ``summary``: its line in ``slipest --help``; ``doc``: its module's
    docstring, whose text after the first paragraph is the command's
    description in ``slipest NAME --help`` (line breaks kept).
    """
    return sub.add_parser(name, help=summary, description=doc.split("\n\n", 1)[1],
                          formatter_class=argparse.RawDescriptionHelpFormatter)
