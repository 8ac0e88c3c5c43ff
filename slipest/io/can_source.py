"""Live CAN source: receive the DBC's messages on any python-can bus, publish estimates back.

:class:`CanSource` owns the bus and nothing else: a reader thread receives
with a :class:`~slipest.io.bus_args.ReconnectingBus` (errors are reported
and counted, a dead socketcand server is reconnected when it is back),
decodes with :class:`~slipest.io.can_messages.CanDecoder` (unknown IDs and
bad frames counted and skipped) and queues the samples with the time they
arrived (host monotonic clock).  :meth:`CanSource.publish` sends one
SlipEstimate message per leg cycle (ID 0x110 + wheel): an estimated cycle
with Quality 0, a flagged one (not estimated) with Quality 15 (INVALID).

Samples carry the device time modulo 0.65536 s and an 8-bit counter; the
consumer unwraps both (:class:`~slipest.io.device_stream.WheelStream` with
``seq_modulus=256, time_modulus=TIME_MOD_PERIOD``).
"""

from __future__ import annotations

import math
import queue
import threading
import time

from slipest.io.bus_args import BusConfig, ReconnectingBus
from slipest.io.can_messages import (
    QUALITY_INVALID,
    QUALITY_OK,
    CanDecoder,
    ImuMessage,
    SlipReferenceMessage,
    encode_slip_estimate,
)
from slipest.io.source_batch import SourceBatch, drain

__all__ = ["CanSource", "estimate_message"]


def estimate_message(wheel: int, estimate):
    """The SlipEstimate message of one cycle's estimate (Quality 0, or 15 when not estimated)."""
    quality = str(getattr(estimate, "quality", "ok"))
    values = [float(getattr(estimate, k, math.nan)) for k in ("slip", "slip_std", "dphi", "dphi_std")]
    code = QUALITY_OK if quality == "ok" and all(v == v for v in values) else QUALITY_INVALID
    return encode_slip_estimate(wheel, int(getattr(estimate, "cycle", 0)), *values, quality=code)


class CanSource:
    """Samples from a CAN bus, read in a background thread (see the module docstring)."""

    def __init__(self, config: BusConfig, *, decoder: CanDecoder | None = None, max_batch: int = 512):
        self.config = config
        self.decoder = decoder or CanDecoder()
        self.max_batch = max_batch
        self.events: queue.Queue = queue.Queue()
        self.bus = ReconnectingBus(config, on_event=self.events.put)
        self._q: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.c = {"published": 0, "publish_failed": 0, "references_invalid": 0}
        self._lock = threading.Lock()

    def start(self, wait_open: float = 0.0) -> "CanSource":
        if not self.bus.open(wait=wait_open):
            raise OSError(self.bus.last_error or f"cannot open CAN bus {self.config.describe()}")
        self._thread = threading.Thread(target=self._run, name="can-reader", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- reader thread ----------------------------------------------------------------
    def _run(self) -> None:
        bus = self.bus
        decode = self.decoder.decode
        while not self._stop.is_set():
            msg = bus.recv(0.05)
            if msg is None:
                continue
            intake = time.monotonic()
            imu = []
            refs = []
            n = 0
            while msg is not None:
                with self._lock:
                    rec = decode(msg)
                if isinstance(rec, ImuMessage):
                    imu.append((rec.wheel, rec.counter, rec.time_mod, rec.az, rec.theta))
                elif isinstance(rec, SlipReferenceMessage):
                    if rec.slip == rec.slip:
                        refs.append((rec.wheel, rec.counter, rec.time_mod, rec.slip))
                    else:
                        self.c["references_invalid"] += 1
                n += 1
                if n >= self.max_batch:
                    break
                msg = bus.recv(0)
            if imu or refs:
                self._q.put(SourceBatch(intake, imu, refs))

    # -- consumer side ------------------------------------------------------------------
    def get(self, timeout: float = 0.1) -> list[SourceBatch]:
        """Batches that arrived (waits up to ``timeout`` s for the first one)."""
        return drain(self._q, timeout)

    def publish(self, wheel: int, estimate) -> bool:
        """Send the SlipEstimate message of one cycle; False when the bus is down (counted)."""
        ok = self.bus.send(estimate_message(wheel, estimate))
        self.c["published" if ok else "publish_failed"] += 1
        return ok

    def notices(self) -> list[str]:
        """Events waiting now (never blocks)."""
        return drain(self.events, 0)

    def counters(self) -> dict:
        with self._lock:
            c = self.decoder.counters()
        c.pop("counter_gaps_by_wheel", None)
        c.update(self.c)
        c.update(self.bus.counters())
        return c
