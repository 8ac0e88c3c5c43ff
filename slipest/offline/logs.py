"""Which kind of log a file is, and the logs in a folder.

Kinds (:data:`KINDS`):

* ``"slipest"``: the log CSV of :mod:`slipest.io.log_csv` (``t,az,theta[,slip]``);
* ``"can"``: a python-can log file (:mod:`slipest.io.can_log`): ``.asc``,
  ``.blf``, ``.log`` (candump -l), ``.trc``, ``.db``, ``.mf4``, python-can's
  ``.csv`` (told from the slipest CSV by its header), each also gzipped;
* ``"ros2"``: a rosbag2 bag (:mod:`slipest.io.rosbag`): a directory with a
  ``metadata.yaml``, or a ``.mcap`` or ``.db3`` file.

Only names and the first line of a ``.csv`` are looked at; whether the
content is good is for the readers to say.
"""

from __future__ import annotations

import os

from slipest.io.can_log import is_can_log_name
from slipest.io.rosbag import BAG_SUFFIXES, is_bag

__all__ = ["KINDS", "detect_kind", "expand_logs"]

KINDS = ("slipest", "can", "ros2")
#: The first header field of python-can's CSV format.
_CAN_CSV_HEADER = "timestamp,arbitration_id"


def _csv_is_python_can(path: str) -> bool:
    try:
        with open(path, "rb") as fh:
            for raw in fh:
                line = raw.strip()
                if line and not line.startswith(b"#"):
                    return line.replace(b" ", b"").lower().startswith(_CAN_CSV_HEADER.encode())
    except OSError:
        return False  # the slipest reader says what is wrong with the file
    return False


def detect_kind(path) -> str:
    """The kind of the log at ``path`` (a name or an open stream: ``"slipest"``).

    A ``.csv`` is python-can's when its header starts ``timestamp,arbitration_id``;
    any other name that is neither a CAN log nor a bag is read as a slipest log.
    """
    if not isinstance(path, (str, bytes, os.PathLike)):
        return "slipest"
    name = os.fsdecode(path)
    if is_bag(name):
        return "ros2"
    lower = name.lower()
    if lower.endswith(".csv"):
        return "can" if _csv_is_python_can(name) else "slipest"
    if is_can_log_name(name):
        return "can"
    return "slipest"


def _is_log_name(name: str, kinds) -> bool:
    lower = name.lower()
    if "slipest" in kinds and lower.endswith(".csv"):
        return True
    if "can" in kinds and is_can_log_name(lower):
        return True
    return "ros2" in kinds and os.path.splitext(lower)[1] in BAG_SUFFIXES


def expand_logs(paths, kinds=KINDS) -> list[str]:
    """The logs named by ``paths``, in their order, each once: a file or a bag as it is; a folder
    (that is not a bag) by its logs of the given kinds, recursively, in sorted order (a bag directory
    inside counts as one log).  A path that does not exist is kept: reading it gives the error."""
    out: list[str] = []
    for p in paths:
        p = os.fspath(p)
        if not os.path.isdir(p) or ("ros2" in kinds and is_bag(p)):
            out.append(p)
            continue
        for root, dirs, files in os.walk(p):
            dirs.sort()
            if "ros2" in kinds:
                bags = [d for d in dirs if is_bag(os.path.join(root, d))]
                out.extend(os.path.join(root, d) for d in bags)
                dirs[:] = [d for d in dirs if d not in bags]
            out.extend(os.path.join(root, f) for f in sorted(files) if _is_log_name(f, kinds))
    return list(dict.fromkeys(out))
