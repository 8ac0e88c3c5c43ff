"""The loop of a live run: a source's batches into the estimation until told to stop.

:func:`run_live` reads a started :class:`~slipest.io.source.Source` and
feeds :class:`~slipest.live.estimation.LiveEstimation` until a stop
condition holds (:class:`StopConditions`: duration, cycles, idle time, or
any condition of the caller's), the source ends, or SIGTERM/SIGINT arrives;
then it closes the source and the estimation (the recording is complete:
written, flushed, closed) and returns a :class:`RunResult` with the reason
and the final counters.  While it runs it writes the recording every 0.1 s,
passes the source's notices (disconnections, reconnections) to
``on_notice`` and calls ``on_status`` on SIGUSR1.

Signals (main thread only; the previous handlers are restored on return):
SIGTERM and SIGINT set a flag the loop checks every ``poll`` seconds, so no
batch is ever half handled; a second one stops at once (the recording is
still closed).  Before streaming, the start-up objects are frozen out of
the garbage collector (:func:`~slipest.startup_gc.freeze_startup_objects`).
"""

from __future__ import annotations

import logging
import signal
import time
from dataclasses import dataclass
from typing import Callable

from slipest.startup_gc import freeze_startup_objects

__all__ = ["LoopState", "RunResult", "StopConditions", "run_live"]

log = logging.getLogger(__name__)


@dataclass
class LoopState:
    """Where a run is: ``started``, ``now`` and ``last_data`` (the last batch; None before the
    first) on the host's monotonic clock [s]."""

    started: float
    now: float
    last_data: float | None


@dataclass
class StopConditions:
    """When :func:`run_live` stops (any that holds; None: not that one).

    ``duration`` [s] after the loop started; ``cycles``: every wheel seen
    has closed that many leg cycles; ``idle_timeout`` [s] without a batch,
    counted from the first one; ``until(state)``: the caller's own
    condition, given a :class:`LoopState`, returns the reason to stop (a
    non-empty string) or None.
    """

    duration: float | None = None
    cycles: int | None = None
    idle_timeout: float | None = None
    until: Callable[[LoopState], str | None] | None = None

    def reason(self, state: LoopState, live) -> str | None:
        """Why to stop now, or None to go on."""
        if self.duration is not None and state.now - state.started >= self.duration:
            return f"duration {self.duration:g} s reached"
        if self.cycles is not None and live.wheels and live.min_cycles() >= self.cycles:
            return f"{self.cycles} cycles reached"
        if (self.idle_timeout is not None and state.last_data is not None
                and state.now - state.last_data >= self.idle_timeout):
            return f"no data for {self.idle_timeout:g} s"
        return self.until(state) if self.until is not None else None


@dataclass
class RunResult:
    """How a run ended: ``reason`` (e.g. ``"duration 60 s reached"``, ``"interrupted (SIGTERM)"``),
    ``interrupted`` (by a signal or KeyboardInterrupt), ``elapsed_s``, and the counters at the end:
    ``source`` (the source's), ``estimation`` and ``latency`` (the estimation's)."""

    reason: str
    interrupted: bool
    elapsed_s: float
    source: dict
    estimation: dict
    latency: dict

    def report(self) -> dict:
        """The run as a JSON-ready dict: reason, source, estimation, latency, elapsed_s."""
        return {"reason": self.reason, "source": self.source, "estimation": self.estimation,
                "latency": self.latency, "elapsed_s": self.elapsed_s}


def _install(handlers: dict) -> dict:
    old = {}
    for sig, handler in handlers.items():
        try:
            old[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread: no signal handling
            break
    return old


def run_live(source, live, stop: StopConditions | None = None, *, on_notice: Callable[[str], None] | None = None,
             on_status: Callable[[], None] | None = None, handle_signals: bool = True,
             poll: float = 0.05) -> RunResult:
    """Run ``live`` on ``source`` (started) until a stop condition (see the module docstring).

    ``on_notice(text)``: each notice of the source (default: logged at INFO level).
    ``on_status()``: called on SIGUSR1 (None: SIGUSR1 is left alone).
    ``handle_signals``: catch SIGTERM/SIGINT (and SIGUSR1) while running.
    ``poll`` [s]: longest wait for data before the conditions are checked again.
    Exceptions of the estimation's callbacks propagate, after the source and
    the estimation are closed.
    """
    stop = stop or StopConditions()
    on_notice = on_notice or (lambda text: log.info("%s", text))
    flags = {"status": False, "stop": None}

    def _stop(signum, frame):
        # a flag, checked every `poll` s: an exception raised at an arbitrary point
        # could fall between taking samples off the queue and writing them
        if flags["stop"] is not None:
            raise KeyboardInterrupt  # a second signal: stop at once (the recording is still closed)
        flags["stop"] = signal.Signals(signum).name

    def _status(signum, frame):
        flags["status"] = True

    handlers = {}
    if handle_signals:
        handlers = {signal.SIGTERM: _stop, signal.SIGINT: _stop}
        if on_status is not None:
            handlers[signal.SIGUSR1] = _status
    old = _install(handlers)
    # start-up is over: a full garbage collection walking its objects would stall the stream 30-60 ms
    freeze_startup_objects()
    state = LoopState(time.monotonic(), time.monotonic(), None)
    interrupted = False
    try:
        while True:
            ended = source.ended.is_set()  # before get: every batch of an ended source is then in this one
            batches = source.get(poll)
            state.now = time.monotonic()
            if batches:
                live.feed(batches)
                state.last_data = state.now
            live.flush()
            for text in source.notices():
                on_notice(text)
            if flags["status"]:
                flags["status"] = False
                on_status()
            if flags["stop"] is not None:
                reason, interrupted = f"interrupted ({flags['stop']})", True
                break
            reason = stop.reason(state, live)
            if reason:
                break
            if ended and not batches:
                reason = "the source ended" + (f" ({source.last_error})" if source.last_error else "")
                break
    except KeyboardInterrupt:
        reason, interrupted = "interrupted", True
    finally:
        try:
            source.close()
        finally:
            try:
                live.close()
            finally:
                for sig, handler in old.items():
                    signal.signal(sig, handler)
    return RunResult(reason, interrupted, time.monotonic() - state.started, source.counters(), live.counters(),
                     live.latency())
