"""Live estimation on a rover: a device's stream in, one estimate per leg cycle out.

What a rover program needs, without :mod:`slipest.cli`::

    from slipest.io.serial_source import SerialSource   # or slipest.io.can_source.CanSource
    from slipest.live import LiveEstimation, StopConditions, run_live

    source = SerialSource("/dev/ttyUSB0")
    live = LiveEstimation(source, on_estimate=lambda wheel, est, info: print(wheel, est.slip))
    live.warmup()                       # before data comes
    source.start(wait_open=5)
    result = run_live(source, live, StopConditions(duration=600))
    print(result.reason, result.estimation)

Modules:

* :mod:`slipest.live.estimation`: :class:`LiveEstimation`, each wheel's
  frames -> samples -> estimator -> the estimate callback; counters, latencies;
* :mod:`slipest.live.recording`: :class:`Recorder`, one log CSV per wheel;
* :mod:`slipest.live.loop`: :func:`run_live`, the loop around a source with
  its stop conditions, signals and result.

The links themselves are :class:`~slipest.io.source.Source` s
(:mod:`slipest.io.serial_source`, :mod:`slipest.io.can_source`).
"""

from slipest.live.estimation import LiveEstimation
from slipest.live.loop import LoopState, RunResult, StopConditions, run_live
from slipest.live.recording import Recorder, record_path

__all__ = ["LiveEstimation", "LoopState", "Recorder", "RunResult", "StopConditions", "record_path", "run_live"]
