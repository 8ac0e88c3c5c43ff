"""The loop of a live run: a source's batches into the estimation until told to stop.

:func:`run_live` reads a started :class:`~slipest.io.source.Source` and
feeds :class:`~slipest.live.estimation.LiveEstimation` until a stop
condition holds (:class:`StopConditions`: duration, cycles, idle time, or
any condition of the caller's), the source ends, or SIGTERM/SIGINT arrives;
then it closes the source, hands on the frames it had already read, closes
the estimation (the recording is complete: written, flushed, closed) and
returns a :class:`RunResult` with the reason and the final counters.  While
it runs it writes the recording every 0.1 s, passes the notices of the
source (disconnections, reconnections) and of the estimation (a device
restart, frames a late start missed) to ``on_notice``, says when no data
came for ``quiet_notice`` seconds (and when it comes back), and calls
``on_status`` on SIGUSR1.

Signals (:class:`StopSignals`, main thread only): SIGTERM, SIGINT and
SIGHUP (a lost terminal or ssh session; left alone where it is ignored, as
under ``nohup``), and SIGBREAK where it exists (Windows' Ctrl-Break), set a
flag the loop checks
every ``poll`` seconds, so no batch is ever half handled; further ones are
counted and ignored, so that nothing interrupts the shutdown (a double
Ctrl-C loses nothing: the records and the report are complete).  The loop
says when it has taken the stop (``on_stopping``), before the shutdown.  SIGUSR1,
where the platform has it (not on Windows), asks for ``on_status``.  A
caller that writes more after the run (a report) keeps the handlers
installed around its own code by passing a :class:`StopSignals` it entered.
Before streaming, the start-up objects are frozen out of the garbage
collector (:func:`~slipest.startup_gc.freeze_startup_objects`).
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable

from slipest.startup_gc import freeze_startup_objects

__all__ = ["LoopState", "RunResult", "StopConditions", "StopSignals", "run_live"]

log = logging.getLogger(__name__)

#: Signals that stop a run: SIGTERM, SIGINT, SIGHUP (the terminal or the ssh session that started it went away;
#: not where it is ignored, as under nohup) and, on Windows, SIGBREAK (Ctrl-Break).
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP", "SIGBREAK")
                     if hasattr(signal, name))
#: The signal that asks for the counters (None where the platform has no SIGUSR1, e.g. Windows).
STATUS_SIGNAL = getattr(signal, "SIGUSR1", None)


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

    def what_ends(self) -> str:
        """What will end a run that gets no data, for people."""
        ends = []
        if self.idle_timeout is not None:
            ends.append(f"after {self.idle_timeout:g} s without data")
        if self.duration is not None:
            ends.append(f"at {self.duration:g} s")
        return "it stops " + " or ".join(ends) if ends else "Ctrl-C or SIGTERM stops it"


@dataclass
class RunResult:
    """How a run ended: ``reason`` (e.g. ``"duration 60 s reached"``, ``"interrupted (SIGTERM)"``),
    ``interrupted`` (by a signal or KeyboardInterrupt), ``elapsed_s``, and the counters at the end:
    ``source`` (the source's), ``estimation`` and ``latency`` (the estimation's);
    ``signals_ignored``: stop signals that came after the first (ignored, counted)."""

    reason: str
    interrupted: bool
    elapsed_s: float
    source: dict
    estimation: dict
    latency: dict
    signals_ignored: int = 0

    def report(self) -> dict:
        """The run as a JSON-ready dict: reason, source, estimation, latency, elapsed_s, signals_ignored."""
        return {"reason": self.reason, "source": self.source, "estimation": self.estimation,
                "latency": self.latency, "elapsed_s": self.elapsed_s, "signals_ignored": self.signals_ignored}


class StopSignals:
    """Stop and status signals turned into flags, for the time of a ``with`` block.

    The first of :data:`STOP_SIGNALS` handled sets :attr:`stop` (its name); further
    ones only count (:attr:`ignored`).  Handled, not sent: signals that are pending together (sent
    while the process was not running) are delivered lowest number first (SIGINT before SIGTERM),
    whatever order they were sent in.  Nothing is raised, so no write or
    flush is ever interrupted halfway.  With ``status``, SIGUSR1 (where it
    exists) sets a flag :meth:`take_status` returns once.  The handlers only
    set flags (printing from a handler could re-enter a stream the main
    thread is writing).  Installed from the main thread only (elsewhere the
    block runs without them: :attr:`installed` is False).  On exit the
    previous handlers come back; with ``restore=False`` the stop signals are
    left ignored instead, for a process that exits right after (a signal
    during the interpreter's exit would otherwise still kill it).
    """

    def __init__(self, *, status: bool = True, restore: bool = True):
        self.status = status
        self.restore = restore
        self.stop: str | None = None
        self.ignored = 0
        self.installed = False
        self._status_flag = False
        self._old: dict = {}

    def _on_stop(self, signum, frame) -> None:
        if self.stop is None:
            self.stop = signal.Signals(signum).name
        else:
            self.ignored += 1

    def _on_status(self, signum, frame) -> None:
        self._status_flag = True

    def take_status(self) -> bool:
        """Whether a status signal came since the last call."""
        flag, self._status_flag = self._status_flag, False
        return flag

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is not threading.main_thread():
            return self
        handlers = {sig: self._on_stop for sig in STOP_SIGNALS if signal.getsignal(sig) is not signal.SIG_IGN
                    or sig in (signal.SIGINT, signal.SIGTERM)}  # (a hang-up ignored on purpose stays so: nohup)
        if self.status and STATUS_SIGNAL is not None:
            handlers[STATUS_SIGNAL] = self._on_status
        for sig, handler in handlers.items():
            self._old[sig] = signal.signal(sig, handler)
        self.installed = True
        return self

    def __exit__(self, *exc) -> None:
        if not self.installed:
            return
        for sig, old in self._old.items():
            if self.restore or sig == STATUS_SIGNAL:
                signal.signal(sig, old)
            else:
                signal.signal(sig, signal.SIG_IGN)
        self._old = {}
        self.installed = False


class _QuietNotices:
    """Says when no data came for ``after`` s (again every minute of silence), and when data comes back."""

    def __init__(self, after: float | None, stop: StopConditions, on_notice: Callable[[str], None]):
        self.after = after
        self.stop = stop
        self.on_notice = on_notice
        self._next = after  # quiet time [s] of the next notice
        self._said = False
        self._seen = False  # data came before

    def check(self, state: LoopState, quiet_since: float, got_data: bool) -> None:
        """After each poll: ``quiet_since`` [s] the last batch before this poll (or the start)."""
        if self.after is None:
            return
        quiet = state.now - quiet_since
        if got_data:
            if self._said:
                again = f"data again after {quiet:.1f} s without"
                self.on_notice(again if self._seen else f"first data after {quiet:.1f} s")
            self._said = False
            self._seen = True
            self._next = self.after
        elif quiet >= self._next:
            if not self._seen:
                what = f"no data yet after {quiet:.1f} s: waiting for the device"
            else:
                what = f"no data for {quiet:.1f} s (the device stopped, or the link went quiet); waiting"
            self.on_notice(f"{what} ({self.stop.what_ends()})")
            self._said = True
            self._next = quiet + max(60.0, self.after)


def run_live(source, live, stop: StopConditions | None = None, *, on_notice: Callable[[str], None] | None = None,
             on_status: Callable[[], None] | None = None, on_stopping: Callable[[str], None] | None = None,
             handle_signals: bool = True, signals: StopSignals | None = None, poll: float = 0.05,
             quiet_notice: float | None = 5.0) -> RunResult:
    """Run ``live`` on ``source`` (started) until a stop condition (see the module docstring).

    ``on_notice(text)``: each notice of the source and of the estimation, and the quiet-link
    notices (default: logged at INFO level).
    ``on_status()``: called on SIGUSR1 (None: SIGUSR1 is left alone).
    ``on_stopping(reason)``: called once a stop condition holds or a stop signal was taken (within
    ``poll`` s of it), with the reason :class:`RunResult` will carry, before the shutdown (the last
    batches, the last cycles, the recording): a user who pressed Ctrl-C hears it was taken, and a
    further signal from then on is counted and ignored.
    ``handle_signals``: catch the stop signals (and SIGUSR1) while running; ``signals``: a
    :class:`StopSignals` the caller entered (used instead, left installed on return).
    ``poll`` [s]: longest wait for data before the conditions are checked again.
    ``quiet_notice`` [s]: say so when no data came for this long (None: never).
    Exceptions of the estimation's callbacks propagate, after the source and
    the estimation are closed.
    """
    stop = stop or StopConditions()
    on_notice = on_notice or (lambda text: log.info("%s", text))
    own = None
    if signals is None and handle_signals:
        own = signals = StopSignals(status=on_status is not None).__enter__()
    quiet = _QuietNotices(quiet_notice, stop, on_notice)
    # start-up is over: a full garbage collection walking its objects would stall the stream 30-60 ms
    freeze_startup_objects()
    state = LoopState(time.monotonic(), time.monotonic(), None)
    interrupted = False

    def notices():
        for text in source.notices():
            on_notice(text)
        for text in getattr(live, "notices", list)():  # (an estimation of the caller's may have none)
            on_notice(text)

    try:
        while True:
            ended = source.ended.is_set()  # before get: every batch of an ended source is then in this one
            batches = source.get(poll)
            state.now = time.monotonic()
            quiet_since = state.started if state.last_data is None else state.last_data
            if batches:
                live.feed(batches)
                state.last_data = state.now
            live.flush()
            notices()
            quiet.check(state, quiet_since, bool(batches))
            if signals is not None and signals.take_status() and on_status is not None:
                on_status()
            if signals is not None and signals.stop is not None:
                reason, interrupted = f"interrupted ({signals.stop})", True
                break
            reason = stop.reason(state, live)
            if reason:
                break
            if ended and not batches:
                reason = "the source ended" + (f" ({source.last_error})" if source.last_error else "")
                break
        if on_stopping is not None:
            on_stopping(reason)
        source.stop_reading()
        rest = source.get(0)  # read before the reader stopped: recorded and estimated like the others
        if rest:
            live.feed(rest)
        live.close()  # the last cycles, estimated and handed on while the link is still open (CAN: published)
        notices()
    except KeyboardInterrupt:  # without signal handling (handle_signals=False): Ctrl-C's default
        reason, interrupted = "interrupted", True
    finally:
        try:
            source.close()
        finally:
            try:
                live.close()
            finally:
                if own is not None:
                    own.__exit__(None, None, None)
    return RunResult(reason, interrupted, time.monotonic() - state.started, source.counters(), live.counters(),
                     live.latency(), signals.ignored if signals is not None else 0)
