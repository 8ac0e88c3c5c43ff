"""Live serial source: read a port in a thread, decode frames, hand them on.

:class:`SerialSource` is the :class:`~slipest.io.source.Source` of a serial
link: its reader thread reads the port with pyserial and feeds the bytes to
a protocol object (a :class:`~slipest.io.serial_frames.FrameDecoder`),
which never sees the port; decoded frames are queued with the time they
arrived (host monotonic clock).  Wire facts: 16-bit counters, timestamps in
microseconds, never wrapped.

It survives the port going away: when the device disappears (a USB adapter
unplugged, a pseudo-terminal's master closed: the read raises
``SerialException("device reports readiness to read but returned no data
...")`` and ``/dev/pts/N`` vanishes) it closes the port, forgets the partial
frame, and tries to open the same path again every ``reopen_interval``
seconds until it is back.  Except a pseudo-terminal opened by its own node
(:func:`pty_node`: ``/dev/pts/N``, not a link to it): a pair that went away
never comes back, and the next pseudo-terminal any program opens gets its
number, so reopening it would read another device's frames as this one's
(taken for a restart of it); the source ends instead, saying why.  A device
that re-creates its pseudo-terminal keeps a stable link to it
(``firmware-sim --link``, socat's ``link=``), which is reopened.
A SLIP_REFERENCE frame whose slip lies outside [0, 1) (percent, a negative
sign convention: :func:`~slipest.io.log_csv.slip_out_of_range`) is never
used: counted (``references_out_of_range``) and skipped, as CAN's are.
Everything is counted (:meth:`SerialSource.counters`): the decoder's counters plus ``opens``,
``disconnects``, ``reopen_attempts``, ``read_errors``, ``references_out_of_range`` and
``notices_suppressed``.  A port that keeps going away and coming back
(a device that opens and closes, a path that points at a dead pty) says so
three times, then once per ten seconds with the number left out
(:meth:`~slipest.io.source.Source._notice`).
"""

from __future__ import annotations

import os
import re
import time

import serial

from slipest.io.log_csv import slip_out_of_range
from slipest.io.serial_frames import FRAME_IMU_SAMPLE, SEQ_MODULUS, FrameDecoder
from slipest.io.source import Source, SourceBatch

__all__ = ["SerialSource", "pty_node"]

#: A pseudo-terminal's slave node: Linux's /dev/pts/N, macOS's /dev/ttysNNN.
_PTY_NODE = re.compile(r"/dev/(pts/\d+|ttys\d+)")


def pty_node(port: str) -> bool:
    """Whether ``port`` names a pseudo-terminal's slave node itself (``/dev/pts/N``, ``/dev/ttysNNN``), not a link
    to one nor any other port or pyserial URL: the number of a pseudo-terminal that went away goes to the next one
    any program opens."""
    return not os.path.islink(port) and _PTY_NODE.fullmatch(os.path.normpath(os.path.abspath(port))) is not None


class SerialSource(Source):
    """Frames from a serial port (any pyserial URL), read in a background thread.

    ``baudrate`` matters for real UARTs only (a pseudo-terminal ignores it).
    ``reopen``: keep trying to reopen a port that went away (default; never a
    :func:`pty_node`), else end.  :meth:`start` raises
    ``serial.SerialException`` (an ``OSError``) when the port cannot be opened
    within ``wait_open`` seconds.
    """

    seq_modulus = SEQ_MODULUS
    time_unit = 1e-6
    time_modulus = None

    def __init__(self, port: str, baudrate: int = 921600, *, reopen: bool = True,
                 reopen_interval: float = 0.1, decoder: FrameDecoder | None = None):
        super().__init__()
        self.port = port
        self.baudrate = baudrate
        self.reopen = reopen
        self.reopen_interval = reopen_interval
        self.decoder = decoder or FrameDecoder()
        self._ser = None
        self._pty_gone = False  # the pseudo-terminal node we read went away: never reopened
        self.c = {"opens": 0, "disconnects": 0, "reopen_attempts": 0, "read_errors": 0, "references_out_of_range": 0}

    def describe(self) -> str:
        return f"serial:{self.port}"

    def counters(self) -> dict:
        c = self.decoder.counters()
        c.update(self.c)
        c["notices_suppressed"] = self.notices_suppressed
        return c

    # -- the link ----------------------------------------------------------------------
    def _open_once(self) -> None:
        self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.2)
        self.c["opens"] += 1

    def _open(self, wait: float) -> None:
        deadline = time.monotonic() + wait
        while True:
            try:
                self._open_once()
                return
            except (serial.SerialException, OSError) as exc:
                if time.monotonic() >= deadline:
                    raise serial.SerialException(f"cannot open {self.port}: {exc}") from None
                time.sleep(self.reopen_interval)

    def _read(self) -> bool | None:
        ser = self._ser
        if ser is None:
            if not self.reopen or self._pty_gone:
                return False
            self.c["reopen_attempts"] += 1
            try:
                self._open_once()
                self._notice(f"{self.port}: reopened", kind="reopened")
            except (serial.SerialException, OSError):
                self._stop.wait(self.reopen_interval)
            return None
        try:
            data = ser.read(ser.in_waiting or 1)
        except (serial.SerialException, OSError, TypeError) as exc:
            # TypeError: pyserial on a port closed under it
            self._lost(exc)
            return None
        if data:
            self._deliver(time.monotonic(), self.decoder.feed(data))
        return None

    def _lost(self, exc: Exception) -> None:
        if self._stop.is_set():
            return
        self.c["disconnects"] += 1
        self.c["read_errors"] += 1
        self.last_error = str(exc)
        if self.reopen and pty_node(self.port):
            self._pty_gone = True
            self.last_error = (f"{exc}; a pseudo-terminal that went away is not reopened: its number goes to the next "
                               "one any program opens (a device that re-creates its pseudo-terminal keeps a stable "
                               "link to it, e.g. firmware-sim --link, socat link=, and that link is reopened)")
            self._notice(f"{self.port}: disconnected ({self.last_error})", kind="disconnected")
        else:
            self._notice(f"{self.port}: disconnected ({exc})" + ("; reopening" if self.reopen else ""),
                         kind="disconnected")
        self._release()
        self.decoder.reset()  # the partial frame is gone; counters are kept

    def _deliver(self, intake: float, frames: list) -> None:
        if not frames:
            return
        imu = []
        refs = []
        for f in frames:
            if f.kind == FRAME_IMU_SAMPLE:
                imu.append((f.wheel, f.seq, f.t_us, f.az, f.theta))
            elif slip_out_of_range(f.slip):
                self.c["references_out_of_range"] += 1
            else:
                refs.append((f.wheel, f.seq, f.t_us, f.slip, len(imu)))
        self._put(SourceBatch(intake, imu, refs))

    def _interrupt(self) -> None:
        ser = self._ser
        if ser is not None:
            try:
                ser.cancel_read()
            except (serial.SerialException, OSError):  # already closed: nothing to wake
                pass

    def _release(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):  # a vanished device may fail to close; it is gone
                pass
