"""What a live source (serial port, CAN bus) hands the estimator: batches of frames, through a queue."""

from __future__ import annotations

import queue
from dataclasses import dataclass


@dataclass
class SourceBatch:
    """Frames that arrived together.  ``intake`` [s]: host monotonic time of
    arrival; ``imu``: ``(wheel, seq, t_us, az, theta)`` tuples; ``refs``:
    ``(wheel, seq, t_us, slip)`` tuples; both in arrival order."""

    intake: float
    imu: list
    refs: list


def drain(q: queue.Queue, timeout: float = 0.1) -> list:
    """Every item waiting in ``q`` (waits up to ``timeout`` s for the first one; 0: never blocks)."""
    out = []
    try:
        out.append(q.get(timeout=timeout))
    except queue.Empty:
        return out
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out
