"""Where a command may write its output: never over one of the files it reads, never into a directory, only
where it can write.

Checked before anything is read or written, so a mistyped ``-o`` costs no
log and no long run (a calibration, a diagnosis).
"""

from __future__ import annotations

import os
import tempfile


def output_problem(output: str | os.PathLike | None, inputs=(), what: str = "-o",
                   makes_dirs: bool = False) -> str | None:
    """Why ``output`` (a path; ``None`` or ``"-"``: stdout, always fine) cannot be written, or None: it is empty,
    one of ``inputs`` (the same file, by any name), an existing directory, in a directory that does not exist
    (unless the command ``makes_dirs``: it creates them), or where this user cannot write (an existing file
    without write permission; a directory, or for ``makes_dirs`` its nearest existing one, where no file can be
    made: tried with a temporary file, removed at once)."""
    if output is None or str(output) == "-":
        return None
    out = os.fspath(output)
    if not out:
        return f"{what} '': name a file"
    if os.path.isdir(out):
        return f"{what} {out} is a directory: name a file"
    parent = os.path.dirname(os.path.abspath(out))
    if not makes_dirs and not os.path.isdir(parent):
        return f"{what} {out}: no directory {parent}"
    existing = parent
    while not os.path.isdir(existing) and os.path.dirname(existing) != existing:
        existing = os.path.dirname(existing)
    try:
        fd, probe = tempfile.mkstemp(dir=existing, prefix=".slipest-write-check-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return f"{what} {out}: cannot write in {existing} ({exc.strerror or exc})"
    if os.path.isfile(out) and not os.access(out, os.W_OK):
        return f"{what} {out}: no permission to write it"
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


def table_inputs(logs, output, columns) -> tuple[list[str], list[str]]:
    """The logs a table command (``replay`` or ``diagnose --per-log`` of many logs) reads when it writes its
    table to ``output`` (None or ``"-"``: stdout), and the ones it leaves out: a log that is ``output`` and
    holds the command's own earlier table (:func:`slipest.offline.many.is_table` with ``columns``: a folder's
    ``table.csv`` from the last run). ``ValueError`` (:func:`output_problem`'s words) when ``output`` cannot
    be written, e.g. it is one of the other logs: call it before any work."""
    from slipest.offline.many import is_table

    logs = [str(log) for log in logs]
    left_out = []
    if output is not None and str(output) != "-" and os.path.isfile(output):
        left_out = [log for log in logs if os.path.isfile(log) and os.path.samefile(log, output)
                    and is_table(log, columns)]
    kept = [log for log in logs if log not in left_out]
    problem = output_problem(output, kept)
    if problem:
        raise ValueError(problem)
    return kept, left_out
