"""How estimates are printed, as CSV or JSON lines: one row per leg cycle, the same columns everywhere.

The columns are the fields of :class:`slipest.online.Estimate`
(:data:`slipest.online.ESTIMATE_FIELDS`), in that order, as ``slipest
replay`` writes them; the live commands (``slipest serial``, ``slipest
can``) put the wheel index first::

    wheel,cycle,t_end,delta_a,slip,slip_std,dphi,dphi_std,kS,kS_std,phiS,phiS_std,change_prob,slip_ref,n_samples,quality

Values: integers as integers, times (``t_*`` columns, seconds) to the
microsecond, other floats with 6 significant digits, NaN (a cycle not
estimated) as ``nan``, booleans as 1/0.  The same formatting as
``slipest replay``'s CSV (a test compares a live run with a replay of its
recording, row by row).

``--format jsonl`` writes one JSON object per line instead
(:func:`json_row`), with the same keys in the same order (the live
commands' ``wheel`` first), full float precision, and ``null`` for NaN.
"""

from __future__ import annotations

import json
import math

import numpy as np

from slipest.online import ESTIMATE_FIELDS

#: Columns of an estimate row, in order (without the live commands' leading ``wheel``).
COLUMNS = ESTIMATE_FIELDS


def format_value(v, column: str = "") -> str:
    """One value as written in a row (``column``: its name; times get microseconds)."""
    if isinstance(v, (bool, np.bool_)):
        return "1" if v else "0"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if v != v:
            return "nan"
        return f"{v:.6f}" if column.startswith("t_") else f"{v:.6g}"
    return str(v)


def header(prefix: tuple[str, ...] = ()) -> str:
    """The header line (without newline); ``prefix``: leading columns, e.g. ``("wheel",)``."""
    return ",".join(tuple(prefix) + COLUMNS)


def row(estimate, prefix: tuple = ()) -> str:
    """One estimate as a CSV row (without newline); ``prefix``: values of the leading columns."""
    return ",".join([format_value(p) for p in prefix] + [format_value(getattr(estimate, c), c) for c in COLUMNS])


def _json_value(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def json_row(estimate, prefix: dict | None = None) -> str:
    """One estimate as a JSON object on one line (without newline): the items of ``prefix`` first
    (e.g. ``{"wheel": 0}``), then the columns; NaN and infinities as ``null``."""
    obj = dict(prefix or {})
    obj.update((c, _json_value(getattr(estimate, c))) for c in COLUMNS)
    return json.dumps(obj, allow_nan=False)


def parse_rows(lines, prefix: tuple[str, ...] = ()) -> list[dict]:
    """Rows printed by :func:`row` after a :func:`header` line, as dicts of strings (other lines skipped)."""
    names = tuple(prefix) + COLUMNS
    out = []
    for line in lines:
        parts = line.rstrip("\n").split(",")
        if len(parts) == len(names) and parts[0] != names[0]:
            out.append(dict(zip(names, parts)))
    return out
