"""A live run's end: a second signal loses nothing, frames read before the stop are kept, a quiet link is reported."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pytest

import slipest.live.loop as loop
from slipest.io.log_csv import read_log
from slipest.io.source import Source, SourceBatch
from slipest.live import LiveEstimation, StopConditions, run_live
from slipest.live.loop import StopSignals
from tools.check_double_signal import trial


@pytest.mark.parametrize("sig,delay", [(signal.SIGINT, 0.0), (signal.SIGINT, 0.03), (signal.SIGTERM, 0.01),
                                       (signal.SIGTERM, 0.05)]
                         + ([(signal.SIGHUP, 0.02)] if hasattr(signal, "SIGHUP") else []))
def test_a_second_signal_while_stopping_loses_nothing(sig, delay, tmp_path):
    """`slipest serial --record --report` on a 2-wheel firmware-sim pty, two real signals `delay` s apart: exit
    status 0, the report written, every wheel's record complete (tools/check_double_signal.py: 20 trials each).
    Under ``nohup`` (SIGHUP ignored, inherited by the commands, which then leave it alone by design) the SIGHUP
    case is run with SIGHUP's default disposition for the commands it starts."""
    hup = getattr(signal, "SIGHUP", None)
    restore = None
    if sig == hup and signal.getsignal(hup) is signal.SIG_IGN:
        restore = signal.signal(hup, signal.SIG_DFL)  # an ignored signal is inherited across exec, a default one too
    try:
        r = trial(sig, delay, wheels=2, speed=4.0, seed=3, tmp=str(tmp_path), stream_for=0.8)
    finally:
        if restore is not None:
            signal.signal(hup, restore)
    assert r["problems"] == [] and r["rc"] == 0
    assert len(r["rows"]) == 2 and min(r["rows"]) > 1000


def test_stop_signals_count_the_later_ones_and_restore_the_handlers():
    before = signal.getsignal(signal.SIGTERM)
    with StopSignals() as signals:
        assert signals.installed
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handlers run in this (the main) thread between bytecodes
        assert signals.stop == "SIGTERM" and signals.ignored == 2
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no SIGHUP on this platform")
def test_a_hang_up_stops_a_run_unless_it_is_ignored_as_under_nohup():
    """SIGHUP (the terminal or ssh session went away) stops a run as SIGTERM does; a process started under nohup
    (SIGHUP ignored) keeps ignoring it."""
    before = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        with StopSignals(status=False) as signals:
            os.kill(os.getpid(), signal.SIGHUP)
            assert signals.stop == "SIGHUP"
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        with StopSignals(status=False) as signals:
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)
            assert signals.stop is None
    finally:
        signal.signal(signal.SIGHUP, before)


def test_a_platform_without_sigusr1_still_gets_stop_signals(monkeypatch):
    """Windows has no SIGUSR1 (and a SIGBREAK): only the signals that exist are installed."""
    monkeypatch.setattr(loop, "STATUS_SIGNAL", None)
    usr1 = signal.getsignal(signal.SIGUSR1)
    with StopSignals(status=True) as signals:
        assert signal.getsignal(signal.SIGUSR1) is usr1  # left alone
        assert signal.getsignal(signal.SIGINT) == signals._on_stop
        assert not signals.take_status()
    assert set(loop.STOP_SIGNALS) >= {signal.SIGINT, signal.SIGTERM}


class _ListSource(Source):
    """A link of our own (as a rover program would write one): frames of one wheel at 1 kHz in batches of 100,
    ``n_batches`` of them, then silence; its reader hands on one more batch while it is being stopped (read
    from the wire just before the stop)."""

    seq_modulus = 1 << 16
    time_unit = 1e-6

    def __init__(self, n_batches: int, pause_after: int | None = None, pause: float = 0.0):
        super().__init__()
        self.n_batches = n_batches
        self.pause_after = pause_after
        self.pause = pause
        self.sent = 0  # frames handed on
        self._k = 0

    def describe(self) -> str:
        return "list"

    def counters(self) -> dict:
        return {"frames_ok": self.sent}

    def _open(self, wait: float) -> None:
        pass

    def _batch(self) -> SourceBatch:
        i = np.arange(self._k * 100, self._k * 100 + 100)
        self._k += 1
        self.sent += 100
        theta = np.mod(0.63 * i * 1e-3 + np.pi, 2 * np.pi) - np.pi
        az = 9.81 + np.random.default_rng(self._k).normal(0, 0.1, 100)
        return SourceBatch(time.monotonic(), list(zip([0] * 100, i.tolist(), (i * 1000).tolist(), az.tolist(),
                                                      theta.tolist())), [])

    def _read(self):
        if self._k < self.n_batches:
            self._put(self._batch())
            if self._k == self.pause_after:
                self._stop.wait(self.pause)
            else:
                self._stop.wait(0.01)
        else:
            self._stop.wait(0.05)

    def _interrupt(self) -> None:
        if self._k <= self.n_batches:  # once
            self._k = self.n_batches
            self._put(self._batch())


def test_frames_read_before_the_stop_are_recorded_and_estimated(tmp_path):
    source = _ListSource(n_batches=20)
    live = LiveEstimation(source, record=str(tmp_path / "run.csv"))
    source.start()
    result = run_live(source, live, StopConditions(duration=0.6), handle_signals=False)
    assert source.sent == 21 * 100  # the reader's last batch came while it was being stopped
    wc = result.estimation["wheel0"]
    assert wc["samples_in"] == wc["rows_recorded"] == len(read_log(tmp_path / "run.csv")) == source.sent


def test_the_stop_is_said_once_before_the_shutdown():
    """on_stopping hears the reason RunResult carries, once, while the estimation is still open: a second
    Ctrl-C sent after it is one that comes while the run stops."""
    source = _ListSource(n_batches=5)
    live = LiveEstimation(source)
    heard = []
    source.start()
    result = run_live(source, live, StopConditions(duration=0.3), handle_signals=False,
                      on_stopping=lambda reason: heard.append((reason, live._closed, source.ended.is_set())))
    assert heard == [(result.reason, False, False)] and result.reason == "duration 0.3 s reached"


def test_a_quiet_link_is_reported_once_and_data_coming_back_too(tmp_path):
    source = _ListSource(n_batches=10, pause_after=5, pause=1.2)
    live = LiveEstimation(source)
    notices = []
    source.start()
    result = run_live(source, live, StopConditions(duration=2.5), handle_signals=False, quiet_notice=0.5,
                      on_notice=notices.append)
    quiet = [n for n in notices if n.startswith("no data")]
    assert len(quiet) == 2, notices  # the pause, and the silence after the last batch (once each)
    assert quiet[0].startswith("no data for") and "it stops at 2.5 s" in quiet[0]
    assert sum(n.startswith("data again after") for n in notices) == 1
    assert result.reason == "duration 2.5 s reached"


def test_waiting_for_a_first_frame_is_reported():
    source = _ListSource(n_batches=0)
    notices = []
    source.start()
    run_live(source, LiveEstimation(source), StopConditions(duration=0.8), handle_signals=False, quiet_notice=0.3,
             on_notice=notices.append)
    assert notices and notices[0].startswith("no data yet after 0.3 s: waiting for the device")
    assert not any(n.startswith(("first data", "data again")) for n in notices)


def test_the_first_data_after_a_wait_is_said():
    class Slow(_ListSource):
        """Silent for 0.6 s from the run's first poll (not from its start: run_live's start-up, a full garbage
        collection, took longer than that in a loaded test worker, and the data were there before the loop)."""

        def __init__(self, n_batches):
            super().__init__(n_batches)
            self.polled = threading.Event()

        def get(self, timeout=0.1):
            self.polled.set()
            return super().get(timeout)

        def _read(self):
            if self._k == 0:
                self.polled.wait(30.0)
                self._stop.wait(0.6)
            return super()._read()

    source = Slow(n_batches=3)
    notices = []
    source.start()
    run_live(source, LiveEstimation(source), StopConditions(duration=1.0), handle_signals=False, quiet_notice=0.3,
             on_notice=notices.append)
    assert notices[0].startswith("no data yet after 0.3 s") and notices[1].startswith("first data after 0.")


def test_a_late_start_is_a_notice_and_a_counter():
    class Late(_ListSource):
        def __init__(self):
            super().__init__(n_batches=30)
            self._k = 22  # the device had sent 2200 frames before we listened

    source = Late()
    live = LiveEstimation(source)
    notices = []
    source.start()
    result = run_live(source, live, StopConditions(duration=0.3), handle_signals=False, on_notice=notices.append)
    assert result.estimation["wheel0"]["frames_missed_at_start"] == 2200
    assert result.estimation["wheel0"]["frames_lost"] == 0
    assert any(n.startswith("wheel 0: first frame has counter 2200") for n in notices)


def test_signals_are_only_installed_from_the_main_thread():
    got = {}

    def other():
        with StopSignals() as signals:
            got["installed"] = signals.installed

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert got == {"installed": False}


def test_no_module_names_sigusr1_where_it_may_not_exist():
    """SIGUSR1 (and SIGBREAK) exist on some platforms only: the package and the virtual device look them up
    with getattr (loop.STATUS_SIGNAL, loop.STOP_SIGNALS), never as signal.SIGUSR1, which fails on Windows."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    named = [str(p.relative_to(root)) for d in ("slipest", "firmware_sim") for p in sorted((root / d).rglob("*.py"))
             if any(f"signal.{name}" in p.read_text() for name in ("SIGUSR1", "SIGUSR2", "SIGBREAK", "SIGHUP"))]
    assert named == []
