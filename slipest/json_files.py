"""Reading the project's JSON documents: shipped package data or a file the user names.

One place for the errors a user sees when such a file is missing,
unreadable or not JSON (the calibration of :mod:`slipest.calibration`);
each caller validates the document's contents itself and raises its own
error class.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def json_number(x) -> float | None:
    """A JSON-safe float: NaN and infinities become None (JSON has no literal for them)."""
    x = float(x)
    return x if math.isfinite(x) else None


def json_numbers(a) -> list:
    """A JSON-safe flat list of floats (NaN and infinities become None)."""
    return [json_number(v) for v in np.asarray(a, dtype=float).ravel()]


def read_json(path, shipped: str, what: str, regenerate: str, error: type[Exception]) -> tuple[object, str]:
    """The parsed document and a description of where it came from (for the caller's messages).

    path: a file, or None for the package's ``slipest/data/<shipped>``.
    what: what the document is ("calibration", "inverse model").
    regenerate: how to make the shipped file when it is missing (a command).
    error: raised, with the source in its message, when the file is
    missing, cannot be read or is not valid JSON.
    """
    if path is None:
        from importlib import resources

        source = f"shipped {what} slipest/data/{shipped}"
        try:
            text = resources.files("slipest").joinpath(f"data/{shipped}").read_text(encoding="utf-8")
        except FileNotFoundError as exc:
            raise error(f"{source} is missing: run {regenerate}") from exc
    else:
        source = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except FileNotFoundError as exc:
            raise error(f"{what} file {source} not found") from exc
        except (OSError, UnicodeDecodeError) as exc:
            raise error(f"{what} file {source} cannot be read ({exc})") from exc
    try:
        return json.loads(text), source
    except json.JSONDecodeError as exc:
        raise error(f"{source}: not valid JSON ({exc})") from exc
