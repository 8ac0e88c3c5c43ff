"""Running ``slipest`` commands in the test's own process, for runs refused before any work: the CLI's code
path without a new interpreter's start-up (about 2 s of numba loading a command)."""

from __future__ import annotations

import sys

from slipest.cli.main import main


def slipest_in_process(capsys, *argv) -> tuple[int, str]:
    """``slipest ARGV`` in this process: (exit status, stderr). A SystemExit is taken as ``python -m slipest``
    would exit on it: a message on stderr and status 1, or its status (0 for None)."""
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
            rc = 1
        else:
            rc = 0 if exc.code is None else exc.code
    return rc, capsys.readouterr().err
