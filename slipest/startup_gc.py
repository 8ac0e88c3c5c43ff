"""Keep Python's full garbage collections short in a live process.

A live estimator process holds about 120k objects once it has started
(imports, python-can and cantools, the compiled code, the estimator's
model). CPython's generation-2 collection walks all of them: 26-38 ms on
the 2-core development machine when quiet, and one of 55.8 ms was caught
in ``tools/bench_hil.py`` holding up the intake of 54 frames (the stall of
about one per 10-minute CAN run: device to server 0.1 ms, server to intake
54 ms, the collection overlapping it).

:func:`freeze_startup_objects`, called once start-up is over, collects the
start-up garbage and moves every object left to the permanent generation
(:func:`gc.freeze`): later collections walk only the objects made while
running (a full one then takes microseconds instead of tens of
milliseconds). The frozen objects are never freed, which is what start-up
objects of a long-running process are anyway; what the process makes
afterwards is collected as usual.
"""

from __future__ import annotations

import gc


def freeze_startup_objects() -> int:
    """Collect the start-up garbage, then freeze every object left; returns how many are frozen.

    Process-wide: call it once the process has done its start-up (imports,
    model loading, warm-up), before real-time work begins.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


__all__ = ["freeze_startup_objects"]
