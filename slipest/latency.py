"""Summary figures of a set of delays (latencies, lateness)."""

from __future__ import annotations

from typing import Iterable

import numpy as np


def latency_summary(parts: Iterable[np.ndarray]) -> dict:
    """Median, 99th percentile and maximum of delays given in seconds, in milliseconds.

    :param parts: arrays of delays [s], concatenated; NaN and infinite values
        (delays that could not be measured) are left out.
    :returns: ``{"n": count, "median_ms", "p99_ms", "max_ms"}``, or ``{"n": 0}``
        when there is no finite delay.
    """
    parts = [np.ravel(p) for p in parts]
    v = np.concatenate(parts) if parts else np.empty(0)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"n": 0}
    return {"n": int(v.size), "median_ms": float(np.median(v) * 1e3), "p99_ms": float(np.percentile(v, 99) * 1e3),
            "max_ms": float(v.max() * 1e3)}
