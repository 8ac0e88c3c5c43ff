"""Live serial source: read a port in a thread, decode frames, hand them on.

:class:`SerialSource` owns the I/O and nothing else, in the style of
``serial.threaded.ReaderThread``: a reader thread reads the port with
pyserial and feeds the bytes to a protocol object (a
:class:`~slipest.io.serial_frames.FrameDecoder`), which never sees the port;
decoded frames are queued with the time they arrived (host monotonic clock)
for the consumer (:meth:`SerialSource.get`).

Unlike ``ReaderThread`` it survives the port going away: when the device
disappears (a USB adapter unplugged, a pseudo-terminal's master closed: the
read raises ``SerialException("device reports readiness to read but
returned no data ...")`` and ``/dev/pts/N`` vanishes) it closes the port,
forgets the partial frame, and tries to open the same path again every
``reopen_interval`` seconds until it is back.  Everything is counted
(:meth:`SerialSource.counters`): the decoder's counters plus ``opens``,
``disconnects``, ``reopen_attempts`` and ``read_errors``.
"""

from __future__ import annotations

import queue
import threading
import time

import serial

from slipest.io.serial_frames import FRAME_IMU_SAMPLE, FrameDecoder
from slipest.io.source_batch import SourceBatch, drain

__all__ = ["SourceBatch", "SerialSource"]  # SourceBatch re-exported from slipest.io.source_batch


class SerialSource:
    """Frames from a serial port (any pyserial URL), read in a background thread.

    ``baudrate`` matters for real UARTs only (a pseudo-terminal ignores it).
    ``reopen``: keep trying to reopen a port that went away (default), else
    stop.  The port is first opened by :meth:`start`, which raises
    ``serial.SerialException`` if it cannot be opened then (with
    ``wait_open`` seconds of retries).
    """

    def __init__(self, port: str, baudrate: int = 921600, *, reopen: bool = True,
                 reopen_interval: float = 0.1, decoder: FrameDecoder | None = None):
        self.port = port
        self.baudrate = baudrate
        self.reopen = reopen
        self.reopen_interval = reopen_interval
        self.decoder = decoder or FrameDecoder()
        self._q: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ser = None
        self.connected = threading.Event()
        self.ended = threading.Event()  # the reader stopped for good
        self.events: queue.Queue = queue.Queue()  # human-readable notices (disconnects, reopens)
        self.c = {"opens": 0, "disconnects": 0, "reopen_attempts": 0, "read_errors": 0}
        self.last_error: str | None = None

    # -- life cycle --------------------------------------------------------------
    def _open(self) -> None:
        ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.2)
        self._ser = ser
        self.c["opens"] += 1
        self.connected.set()

    def start(self, wait_open: float = 0.0) -> "SerialSource":
        deadline = time.monotonic() + wait_open
        while True:
            try:
                self._open()
                break
            except (serial.SerialException, OSError) as exc:
                if time.monotonic() >= deadline:
                    raise serial.SerialException(f"cannot open {self.port}: {exc}") from None
                time.sleep(self.reopen_interval)
        self._thread = threading.Thread(target=self._run, name=f"serial-reader {self.port}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        ser = self._ser
        if ser is not None:
            try:
                ser.cancel_read()
            except Exception:
                pass
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:
                pass
            self._ser = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- reader thread -------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                ser = self._ser
                if ser is None:
                    if not self.reopen:
                        return
                    self.c["reopen_attempts"] += 1
                    try:
                        self._open()
                        self.events.put(f"{self.port}: reopened")
                    except (serial.SerialException, OSError):
                        self._stop.wait(self.reopen_interval)
                    continue
                try:
                    data = ser.read(ser.in_waiting or 1)
                except (serial.SerialException, OSError, TypeError) as exc:
                    # TypeError: pyserial on a port closed under it
                    self._lost(exc)
                    continue
                if data:
                    intake = time.monotonic()
                    self._deliver(intake, self.decoder.feed(data))
        finally:
            self.ended.set()

    def _lost(self, exc: Exception) -> None:
        if self._stop.is_set():
            return
        self.c["disconnects"] += 1
        self.c["read_errors"] += 1
        self.last_error = str(exc)
        self.connected.clear()
        self.events.put(f"{self.port}: disconnected ({exc}); reopening")
        try:
            self._ser.close()
        except Exception:
            pass
        self._ser = None
        self.decoder.reset()  # the partial frame is gone; counters are kept

    def _deliver(self, intake: float, frames: list) -> None:
        if not frames:
            return
        imu = []
        refs = []
        for f in frames:
            if f.kind == FRAME_IMU_SAMPLE:
                imu.append((f.wheel, f.seq, f.t_us, f.az, f.theta))
            else:
                refs.append((f.wheel, f.seq, f.t_us, f.slip))
        self._q.put(SourceBatch(intake, imu, refs))

    # -- consumer side -------------------------------------------------------------
    def get(self, timeout: float = 0.1) -> list[SourceBatch]:
        """Batches that arrived (waits up to ``timeout`` s for the first one)."""
        return drain(self._q, timeout)

    def notices(self) -> list[str]:
        """Events waiting now (never blocks)."""
        return drain(self.events, 0)

    def counters(self) -> dict:
        c = self.decoder.counters()
        c.update(self.c)
        return c
