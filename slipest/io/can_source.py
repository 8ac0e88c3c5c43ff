"""Live CAN source: receive the DBC's messages on any python-can bus, publish estimates back.

:class:`CanSource` is the :class:`~slipest.io.source.Source` of a CAN
bus: a reader thread receives with a
:class:`~slipest.io.bus_args.ReconnectingBus` (errors are reported and
counted, a dead socketcand server is reconnected when it is back; each
such event is one notice line, rate-limited as
:meth:`~slipest.io.source.Source._notice` says),
decodes with :class:`~slipest.io.can_messages.CanDecoder` (unknown IDs and
bad frames counted and skipped) and queues the samples with the time they
arrived (host monotonic clock); a SlipReference flagged invalid or outside
[0, 1) is never used: counted (``references_invalid``,
``references_out_of_range``) and skipped.  :meth:`CanSource.publish` sends one
SlipEstimate message per leg cycle (ID 0x110 + wheel): an estimated cycle
with Quality 0, a flagged one (not estimated) with Quality 15 (INVALID).
:meth:`CanSource.add_listener` hands every frame received, as python-can
gave it (ours or not, decodable or not), to a python-can style listener in
the reader thread, before decoding: a log of the raw traffic
(:class:`slipest.live.recording.FrameRecorder`) loses nothing.

Wire facts (:class:`~slipest.io.source.Source`): samples carry an 8-bit
counter and the device time in seconds modulo 0.65536 s (``TimeMod``); the
consumer unwraps both.
"""

from __future__ import annotations

import math
import threading
import time

from slipest.io.bus_args import BusConfig, ReconnectingBus
from slipest.io.can_messages import (
    COUNTER_MODULUS,
    REORDER_FRAMES,
    QUALITY_INVALID,
    QUALITY_MISFIT,
    QUALITY_OK,
    QUALITY_REPAIRED,
    QUALITY_REPAIRED_MISFIT,
    TIME_MOD_PERIOD,
    CanDecoder,
    ImuMessage,
    SlipReferenceMessage,
    encode_slip_estimate,
)
from slipest.io.log_csv import slip_out_of_range
from slipest.io.source import Source, SourceBatch, one_line_logs

__all__ = ["CanSource", "add_record", "estimate_message", "SOCKETCAND_LOGGER"]

#: The logger of python-can's socketcand client (its receive errors embed a traceback: cut to one line).
SOCKETCAND_LOGGER = "can.interfaces.socketcand.socketcand"


def estimate_message(wheel: int, estimate):
    """The SlipEstimate message of one cycle's estimate: Quality OK, REPAIRED (estimated without a few
    samples), MISFIT (the model did not explain the cycle: ``misfit > 1``), REPAIRED_MISFIT, or INVALID
    when not estimated."""
    quality = str(getattr(estimate, "quality", "ok"))
    values = [float(getattr(estimate, k, math.nan)) for k in ("slip", "slip_std", "dphi", "dphi_std")]
    if not getattr(estimate, "ok", quality == "ok") or not all(v == v for v in values):
        code = QUALITY_INVALID
    else:
        misfit = float(getattr(estimate, "misfit", math.nan)) > 1.0
        code = ((QUALITY_REPAIRED_MISFIT if misfit else QUALITY_REPAIRED) if quality == "repaired"
                else (QUALITY_MISFIT if misfit else QUALITY_OK))
    return encode_slip_estimate(wheel, int(getattr(estimate, "cycle", 0)), *values, quality=code)


def add_record(rec, imu: list, refs: list) -> str | None:
    """File one decoded frame where a :class:`~slipest.io.source.SourceBatch` takes it: an
    :class:`ImuMessage` as ``(wheel, counter, time_mod, az, theta)`` in ``imu``, a usable
    :class:`SlipReferenceMessage` as ``(wheel, counter, time_mod, slip, len(imu))`` in ``refs`` (its
    place among the IMU frames); anything else (None, estimates) is left out.  A reference that cannot
    be used is left out too, and the counter the caller adds one to is returned: ``"references_invalid"``
    (flagged invalid: NaN slip) or ``"references_out_of_range"`` (a slip outside [0, 1), e.g. a negative
    one, which the signed DBC field carries: :func:`~slipest.io.log_csv.slip_out_of_range`); None otherwise."""
    if isinstance(rec, ImuMessage):
        imu.append((rec.wheel, rec.counter, rec.time_mod, rec.az, rec.theta))
    elif isinstance(rec, SlipReferenceMessage):
        if rec.slip != rec.slip:
            return "references_invalid"
        if slip_out_of_range(rec.slip):
            return "references_out_of_range"
        refs.append((rec.wheel, rec.counter, rec.time_mod, rec.slip, len(imu)))
    return None


class CanSource(Source):
    """Samples from a CAN bus, read in a background thread (see the module docstring).

    :meth:`start` raises ``OSError`` when the bus cannot be opened within
    ``wait_open`` seconds.  ``max_batch``: most messages in one batch.
    """

    seq_modulus = COUNTER_MODULUS
    reorder_window = REORDER_FRAMES
    time_unit = 1.0
    time_modulus = TIME_MOD_PERIOD

    def __init__(self, config: BusConfig, *, decoder: CanDecoder | None = None, max_batch: int = 512):
        super().__init__()
        self.config = config
        self.decoder = decoder or CanDecoder()
        self.max_batch = max_batch
        self.bus = ReconnectingBus(config, on_event=lambda text: self._notice(text, kind="bus"))
        one_line_logs(SOCKETCAND_LOGGER)
        self.c = {"published": 0, "publish_failed": 0, "references_invalid": 0, "references_out_of_range": 0}
        self._lock = threading.Lock()
        self._listeners: list = []

    def add_listener(self, listener) -> None:
        """Give every frame received from now on to ``listener.on_message_received(msg)`` (a
        ``can.Listener``), in the reader thread, in arrival order, before decoding.  Add listeners before
        :meth:`start`; a listener must be quick and must not raise (it holds up the reader)."""
        self._listeners.append(listener)

    def describe(self) -> str:
        return f"can:{self.config.describe()}"

    def counters(self) -> dict:
        with self._lock:
            c = self.decoder.counters()
        c.pop("counter_gaps_by_wheel", None)
        c.update(self.c)
        c.update(self.bus.counters())
        c["notices_suppressed"] = self.notices_suppressed
        return c

    def publish(self, wheel: int, estimate) -> bool:
        """Send the SlipEstimate message of one cycle; False when the bus is down (counted)."""
        ok = self.bus.send(estimate_message(wheel, estimate))
        self.c["published" if ok else "publish_failed"] += 1
        return ok

    # -- the link ------------------------------------------------------------------------
    def _open(self, wait: float) -> None:
        if not self.bus.open(wait=wait):
            raise OSError(self.bus.last_error or f"cannot open CAN bus {self.config.describe()}")

    def _read(self) -> None:
        bus = self.bus
        msg = bus.recv(0.05)
        if msg is None:
            return
        intake = time.monotonic()
        listeners = self._listeners
        msgs = []
        while msg is not None:
            for listener in listeners:
                listener.on_message_received(msg)
            msgs.append(msg)
            if len(msgs) >= self.max_batch:
                break
            msg = bus.recv(0)
        with self._lock:
            recs = self.decoder.decode_many(msgs)  # a burst's ImuSample frames decoded together
        imu = []
        refs = []
        for rec in recs:
            unusable = add_record(rec, imu, refs)
            if unusable:
                self.c[unusable] += 1
        if imu or refs:
            self._put(SourceBatch(intake, imu, refs))

    def _release(self) -> None:
        self.bus.shutdown()
