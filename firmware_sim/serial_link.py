"""Serial links of the virtual device: a pseudo-terminal it creates, or a given port.

:class:`PtyLink` creates a pseudo-terminal pair itself (``os.openpty`` +
``tty.setraw``), closes its own slave end and announces the slave's path for
the receiver to open, as ``socat -d -d pty,raw,echo=0 ...`` does.  With
``link_path`` it also keeps a symbolic link to the current slave (socat's
``link=``), so a receiver can reopen one stable name across reconnections.
It knows whether a reader is there: the master polls ``POLLHUP`` while no
slave is open; frames are sent once a reader has had the port open for
``settle`` seconds (pyserial empties the input buffer right after opening).
A disconnection closes the master (``/dev/pts/N`` disappears and the reader
gets "device reports readiness to read but returned no data"); the
reconnection creates a new pair and announces it.

:class:`PortLink` writes to an existing port with pyserial (a real UART, or
one end of a ``socat`` pair); a disconnection closes and reopens it.

Both derive from :class:`SerialLink`: frames of :mod:`slipest.io.serial_frames`
(the device's wire format), one ``bytes`` item per frame, delimiter included.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import struct
import time
from typing import Callable

import numpy as np
import serial

from firmware_sim.link import Link, LinkDown
from slipest.io.serial_frames import encode_frame, encode_imu_sample, encode_slip_reference

#: Type byte of the frames sent as "unknown" traffic (no such frame type exists).
UNKNOWN_FRAME_TYPE = 0x7F


def unknown_frames(n: int, rng: np.random.Generator) -> bytes:
    """``n`` CRC-valid frames of an unknown type, of lengths no known type has."""
    out = []
    for _ in range(n):
        size = int(rng.choice([6, 10, 12, 26, 30]))
        payload = bytes([UNKNOWN_FRAME_TYPE, 0]) + rng.integers(0, 256, size - 2, dtype=np.uint8).tobytes()
        out.append(encode_frame(payload))
    return b"".join(out)


class SerialLink(Link):
    """A link carrying serial frames: items are ``bytes`` (faults may corrupt them)."""

    corrupts = True
    encode_imu = staticmethod(encode_imu_sample)
    encode_reference = staticmethod(encode_slip_reference)

    def send_unknown(self, n: int, rng: np.random.Generator) -> int:
        """``n`` CRC-valid frames of an unknown type (:func:`unknown_frames`), in one write."""
        self.send([unknown_frames(n, rng)])
        return n


class PtyLink(SerialLink):
    """A pseudo-terminal pair created by the device; the receiver opens :attr:`path`."""

    def __init__(self, link_path: str | None = None, settle: float = 0.5, stall_timeout: float = 2.0,
                 announce: Callable[[str], None] | None = None, drain_timeout: float = 0.5):
        super().__init__(announce)
        self.link_path = link_path
        self.settle = settle
        self.stall_timeout = stall_timeout
        self.drain_timeout = drain_timeout
        self.master: int | None = None
        self.path: str | None = None
        self._peer_since: float | None = None
        self._poll = None
        #: bytes written but never read, discarded by disconnections (should stay 0)
        self.bytes_discarded_at_disconnect = 0
        #: frames whose end was among those bytes
        self.frames_discarded_at_disconnect = 0
        #: disconnections where the unread bytes could not be probed
        self.drains_unverified = 0

    @property
    def name(self) -> str:
        return self.link_path or self.path or "pty"

    def open(self) -> None:
        import tty  # POSIX only, like pseudo-terminals (PortLink works on Windows too)

        master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)  # the master sees POLLHUP until a reader opens the slave
        os.set_blocking(master, False)
        self.master = master
        self._poll = select.poll()
        self._poll.register(master, select.POLLOUT | select.POLLHUP)
        self._peer_since = None
        if self.link_path:
            tmp = f"{self.link_path}.{os.getpid()}.tmp"
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            try:
                os.symlink(self.path, tmp)
                os.replace(tmp, self.link_path)
            except OSError as exc:  # (the command line checked the directory before the run)
                where = os.path.dirname(os.path.abspath(self.link_path))
                raise OSError(exc.errno, f"--link {self.link_path}: cannot make the link to {self.path} in "
                                         f"{where}: {exc.strerror or exc}") from None
        self.announce(f"serial device {self.path}" + (f" (link {self.link_path})" if self.link_path else ""))

    def ready(self) -> bool:
        if self.master is None:
            return False
        events = self._poll.poll(0)
        hup = any(ev & select.POLLHUP for _, ev in events)
        if hup:
            self._peer_since = None
            return False
        now = time.monotonic()
        if self._peer_since is None:
            self._peer_since = now
        return now - self._peer_since >= self.settle

    def send(self, items) -> int:
        if self.master is None:
            raise LinkDown("pty closed")
        data = memoryview(b"".join(items))
        total = len(data)
        deadline = None
        while data:
            try:
                k = os.write(self.master, data)
                data = data[k:]
                deadline = None
            except BlockingIOError:
                now = time.monotonic()
                if deadline is None:
                    deadline = now + self.stall_timeout
                elif now > deadline:
                    raise LinkDown(f"the reader of {self.path} stopped reading ({len(data)} bytes unsent)") from None
                select.select([], [self.master], [], 0.05)
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF):
                    raise LinkDown(f"{self.path}: {exc.strerror}") from None
                raise
        return total

    def _close_master(self) -> None:
        if self.master is not None:
            try:
                os.close(self.master)
            except OSError:
                pass
            self.master = None
            self._peer_since = None

    def _open_slave(self) -> int | None:
        """A descriptor of our own on the slave (to look at the reader's queue), or None."""
        if self.master is None or self.path is None:
            return None
        try:
            return os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return None

    @staticmethod
    def _pending(fd: int) -> int:
        """Bytes written to the master that the reader has not read yet, in flight included.

        A write to a pty master returns once its bytes are in the slave's flip
        buffer; a kernel worker (``flush_to_ldisc``) moves them to the line
        discipline later (under load, milliseconds later), and FIONREAD counts
        only what the line discipline holds.  ``poll()`` on the slave first
        waits for that worker when the line discipline is empty (``n_tty_poll``
        calls ``tty_buffer_flush_work``), so bytes in flight are not taken for
        bytes read.
        """
        import fcntl
        import termios

        p = select.poll()
        p.register(fd, select.POLLIN)
        p.poll(0)
        return struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    @staticmethod
    def _take_unread(fd: int) -> tuple[int, int]:
        """Read what the reader left (it dies with the master): (bytes, frames).

        A frame counts as discarded when its delimiter is (the device writes
        whole frames, so whatever the reader left ends on one).  A
        non-blocking read waits for the bytes in flight before saying EAGAIN.
        """
        nbytes = nframes = 0
        while True:
            try:
                data = os.read(fd, 65536)
            except OSError:  # EAGAIN: nothing left; EIO: the slave went with the master
                break
            if not data:
                break
            nbytes += len(data)
            nframes += data.count(0)
        return nbytes, nframes

    def _drain_then_close(self) -> None:
        """Let the reader take what was already sent, then close the master.

        A frame the device counted as sent must not vanish with the master: the
        injected disconnection starts after the last sent byte.  Whatever the
        reader still leaves unread after :attr:`drain_timeout` s is taken out and counted
        in :attr:`bytes_discarded_at_disconnect` and
        :attr:`frames_discarded_at_disconnect`, and reported.
        """
        if self.master is None:
            return
        fd = self._open_slave()
        if fd is None:
            self.drains_unverified += 1  # could not look at the reader's queue
            self._close_master()
            return
        try:
            deadline = time.monotonic() + self.drain_timeout
            unread = self._pending(fd)
            while unread and time.monotonic() < deadline:
                time.sleep(0.002)
                unread = self._pending(fd)
            if unread:
                nbytes, nframes = self._take_unread(fd)
                self.bytes_discarded_at_disconnect += nbytes
                self.frames_discarded_at_disconnect += nframes
        except OSError:
            self.drains_unverified += 1
        finally:
            os.close(fd)
        self._close_master()

    def disconnect(self) -> None:
        """Close the master: the slave node disappears and the reader gets an error."""
        self._drain_then_close()

    def reconnect(self) -> None:
        """A new pseudo-terminal pair (announced; the link path follows it)."""
        self._drain_then_close()
        self.open()

    def close(self) -> None:
        """End of the run: the reader gets what was sent (or it is counted as discarded), then the
        pair and the link path go."""
        self._drain_then_close()
        if self.link_path:
            try:
                if os.path.islink(self.link_path):
                    os.unlink(self.link_path)
            except OSError:
                pass

    def describe(self) -> dict:
        return {
            "type": "pty",
            "path": self.path,
            "link": self.link_path,
            "bytes_discarded_at_disconnect": self.bytes_discarded_at_disconnect,
            "frames_discarded_at_disconnect": self.frames_discarded_at_disconnect,
            "drains_unverified": self.drains_unverified,
        }


class PortLink(SerialLink):
    """An existing serial port (pyserial ``serial_for_url``): a UART, a socat pty end..."""

    def __init__(self, port: str, baudrate: int = 921600, write_timeout: float = 2.0,
                 announce: Callable[[str], None] | None = None):
        super().__init__(announce)
        self.port = port
        self.baudrate = baudrate
        self.write_timeout = write_timeout
        self.ser = None
        self._down = False  # a planned outage: no reopening until reconnect()
        self._next_try = 0.0
        self._last_error = "?"

    @property
    def name(self) -> str:
        return self.port

    def _try_open(self) -> bool:
        now = time.monotonic()
        if now < self._next_try:
            return False
        self._next_try = now + 0.25
        try:
            self.ser = serial.serial_for_url(self.port, baudrate=self.baudrate, write_timeout=self.write_timeout)
        except (serial.SerialException, OSError, ValueError) as exc:
            self.ser = None
            self._last_error = str(exc)
            return False
        self.announce(f"serial port {self.port} open")
        return True

    def open(self) -> None:
        self._down = False
        if not self._try_open():
            raise OSError(f"cannot open {self.port}: {self._last_error}")

    def ready(self) -> bool:
        if self.ser is not None:
            return True
        if self._down:
            return False
        return self._try_open()

    def send(self, items) -> int:
        if self.ser is None:
            raise LinkDown(f"{self.port} closed")
        data = b"".join(items)
        try:
            self.ser.write(data)
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise LinkDown(f"{self.port}: {exc}") from None
        return len(data)

    def disconnect(self) -> None:
        self.close()
        self._down = True

    def reconnect(self) -> None:
        self._down = False
        self._next_try = 0.0
        self._try_open()

    def close(self) -> None:
        ser, self.ser = self.ser, None
        if ser is not None:
            with contextlib.suppress(serial.SerialException, OSError):  # the port is gone either way
                ser.close()

    def describe(self) -> dict:
        return {"type": "port", "port": self.port, "baudrate": self.baudrate}
