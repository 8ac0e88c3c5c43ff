"""Notices for people, rate-limited per kind: a link that keeps going away, a device that keeps restarting.

Three of one kind at once, then one per ten seconds; the next one said
tells how many were left out, and :meth:`NoticeLimiter.left_out` sums up
the rest at the end (one line per kind). The counters of the link or the
stream count every event. Thread-safe (notices come from a reader thread
and from the caller's).
"""

from __future__ import annotations

import threading
import time

__all__ = ["NOTICE_BURST", "NOTICE_INTERVAL", "NoticeLimiter"]

#: Notices of one kind: this many at once, then one per :data:`NOTICE_INTERVAL` seconds.
NOTICE_BURST = 3
#: [s] see :data:`NOTICE_BURST`.
NOTICE_INTERVAL = 10.0


class NoticeLimiter:
    """A token bucket per kind (:data:`NOTICE_BURST` tokens, one more every :data:`NOTICE_INTERVAL` s)."""

    def __init__(self, clock=time.monotonic):
        self._clock = clock
        self._budget: dict[str, list] = {}  # kind -> [tokens, time, left out, last left out]
        self._lock = threading.Lock()
        self.suppressed = 0  # notices left out so far

    def admit(self, text: str, kind: str) -> str | None:
        """``text`` to say now (with how many like it were left out since the last one said), or None: left
        out."""
        with self._lock:
            now = self._clock()
            budget = self._budget.setdefault(kind, [float(NOTICE_BURST), now, 0, ""])
            budget[0] = min(float(NOTICE_BURST), budget[0] + (now - budget[1]) / NOTICE_INTERVAL)
            budget[1] = now
            if budget[0] < 1.0:
                budget[2] += 1
                budget[3] = text
                self.suppressed += 1
                return None
            budget[0] -= 1.0
            left_out, budget[2] = budget[2], 0
        return f"{text} ({left_out} more like it not shown)" if left_out else text

    def left_out(self) -> list[str]:
        """One line per kind with notices left out since the last said (then forgotten): the end of a run."""
        out = []
        with self._lock:
            for budget in self._budget.values():
                if budget[2]:
                    out.append(f"{budget[2]} more like this not shown, the last: {budget[3]}")
                    budget[2] = 0
        return out
