"""Where a command may write its output: never over one of the files it reads, never into a directory.

Checked before anything is read or written, so a mistyped ``-o`` costs no
log and no long run (a calibration, a diagnosis).
"""

from __future__ import annotations

import os


def output_problem(output: str | os.PathLike | None, inputs=(), what: str = "-o",
                   makes_dirs: bool = False) -> str | None:
    """Why ``output`` (a path; ``None`` or ``"-"``: stdout, always fine) cannot be written, or None: it is one
    of ``inputs`` (the same file, by any name), an existing directory, or in a directory that does not exist
    (unless the command ``makes_dirs``: it creates them)."""
    if output is None or str(output) == "-":
        return None
    out = os.fspath(output)
    if os.path.isdir(out):
        return f"{what} {out} is a directory: name a file"
    parent = os.path.dirname(os.path.abspath(out))
    if not makes_dirs and not os.path.isdir(parent):
        return f"{what} {out}: no directory {parent}"
    if os.path.exists(out):
        for name in inputs:
            name = os.fspath(name)
            try:
                same = name != "-" and os.path.exists(name) and os.path.samefile(out, name)
            except OSError:
                same = False
            if same:
                return f"{what} {out} is one of the files read ({name}): refusing to write over it"
    return None
