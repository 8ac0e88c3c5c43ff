"""The seam between a live link (serial port, CAN bus, ...) and the estimation runtime.

A :class:`Source` reads a device's frames in a background thread and hands
them on in :class:`SourceBatch` es through a queue: the interface every link
implements, as python-can's ``BusABC`` is for buses, and a reader thread
feeding a decoder, as in pyserial's ``serial.threaded``.  A source also
declares the facts of its wire format that a consumer needs to turn frames
into a continuous stream (:class:`~slipest.io.device_stream.WheelStream`):

* ``seq_modulus``: each wheel's frames carry a sequence counter modulo this
  (serial 2**16, CAN 256; 0: no counter);
* ``time_unit`` [s]: one unit of a batch's time field (serial: 1e-6, the
  frames carry microseconds; CAN: 1.0, seconds);
* ``time_modulus`` [s]: device timestamps wrap with this period (CAN's
  ``TimeMod``: 0.65536 s); None: they are absolute;
* ``reorder_window``: frames of a wheel up to this many counter steps late
  are put back in counter order (CAN: 4; 0: the link keeps the order).

A subclass implements :meth:`Source.describe`, :meth:`Source.counters`,
``_open(wait)`` (open the link, retrying for up to ``wait`` seconds; an
``OSError`` when it cannot) and ``_read()`` (one step of the reader thread:
wait at most about 0.2 s for data, hand frames on with ``_put`` and events
with ``_notice``; False to end the thread), and may override
``_interrupt()`` (wake a blocked read) and ``_release()`` (close the link).

Notices are for people: one line each (a library's embedded traceback is
cut off: :func:`one_line`), and those of one ``kind`` (a link that goes
down and comes back, again and again) are rate-limited
(:mod:`slipest.io.notice_limit`: three at once, then one per ten seconds,
the next one saying how many were left out; ``notices_suppressed``; the
link's own counters count every event).
"""

from __future__ import annotations

import abc
import logging
import queue
import threading
from dataclasses import dataclass

from slipest.io.notice_limit import NoticeLimiter

__all__ = ["Source", "SourceBatch", "drain", "one_line", "one_line_logs"]



def one_line(text: str) -> str:
    """``text`` on one line for people: without the tracebacks embedded in it (python-can's socketcand
    client puts ``traceback.format_exc()`` into its error messages: the block from ``Traceback (most
    recent call last):`` to its exception line goes, what follows stays), whitespace runs as one space."""
    kept = []
    rest = text
    while True:
        head, found, tail = rest.partition("Traceback (most recent call last):")
        kept.append(head)
        if not found:
            break
        lines = tail.split("\n")
        i = 1
        while i < len(lines) and (lines[i][:1] in (" ", "\t") or not lines[i].strip()):
            i += 1  # the frames of the traceback
        rest = "\n".join(lines[i + 1:])  # past its exception line
    return " ".join("".join(kept).split()).replace(" ;", ";")


class _OneLineRecords(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str) and "Traceback (most recent call last)" in record.msg:
            record.msg, record.args = one_line(record.getMessage()), ()
        return True


_ONE_LINE = _OneLineRecords()


def one_line_logs(logger_name: str) -> None:
    """Records of the logger ``logger_name`` whose message embeds a traceback are cut to one line (e.g.
    python-can's socketcand client logs ``Failed to receive: ... Traceback ...`` when its server dies)."""
    logger = logging.getLogger(logger_name)
    if _ONE_LINE not in logger.filters:
        logger.addFilter(_ONE_LINE)


@dataclass
class SourceBatch:
    """Frames that arrived together.  ``intake`` [s]: host monotonic time of
    arrival; ``imu``: ``(wheel, seq, t, az, theta)`` tuples; ``refs``:
    ``(wheel, seq, t, slip, at)`` tuples; both in arrival order, ``t`` in the
    source's ``time_unit``, ``az`` [m/s^2], ``theta`` [rad, wrapped by the
    device], ``slip`` [-] (a reference), ``at`` the number of the batch's
    ``imu`` frames that arrived before the reference (it holds for the
    samples after them)."""

    intake: float
    imu: list
    refs: list


def drain(q: queue.Queue, timeout: float = 0.1) -> list:
    """Every item waiting in ``q`` (waits up to ``timeout`` s for the first one; 0: never blocks)."""
    out = []
    try:
        out.append(q.get(timeout=timeout) if timeout else q.get_nowait())
    except queue.Empty:
        return out
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


class Source(abc.ABC):
    """Frames of a live link, read in a background thread (see the module docstring).

    Use: ``source.start(wait_open)``, then :meth:`get` batches and
    :meth:`notices` until :meth:`close` (also a context manager, closing on
    exit).  ``ended`` is set once the reader thread has stopped.
    """

    #: Each wheel's sequence counter runs modulo this (0: frames carry no counter).
    seq_modulus: int = 0
    #: [s] per unit of a :class:`SourceBatch`'s time field.
    time_unit: float = 1.0
    #: [s] device timestamps wrap with this period; None: absolute.
    time_modulus: float | None = None
    #: Frames of a wheel up to this many counter steps late are put back in counter order (0: none).
    reorder_window: int = 0

    def __init__(self) -> None:
        self._batches: queue.Queue = queue.Queue()
        self._notices: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.ended = threading.Event()
        self.last_error: str | None = None
        self._limiter = NoticeLimiter()

    # -- what a link implements -------------------------------------------------------
    @abc.abstractmethod
    def describe(self) -> str:
        """The link, for people and recordings (e.g. ``serial:/dev/ttyUSB0``)."""

    @abc.abstractmethod
    def counters(self) -> dict:
        """What was received, rejected and why, and the link's failures (counts)."""

    @abc.abstractmethod
    def _open(self, wait: float) -> None:
        """Open the link, retrying for up to ``wait`` s; OSError when it cannot be opened."""

    @abc.abstractmethod
    def _read(self) -> bool | None:
        """One step of the reader thread (see the module docstring); False ends the thread."""

    def _interrupt(self) -> None:
        """Wake a read blocked in the reader thread (called by :meth:`close`)."""

    def _release(self) -> None:
        """Close the link (called by :meth:`close` once the reader thread has stopped)."""

    # -- for the link's reader thread ---------------------------------------------------
    def _put(self, batch: SourceBatch) -> None:
        self._batches.put(batch)

    def _notice(self, text: str, kind: str | None = None) -> None:
        """A notice for people (one line); ``kind``: rate-limited with the others of that kind."""
        text = one_line(text)
        if kind is not None:
            text = self._limiter.admit(text, kind)
            if text is None:
                return
        self._notices.put(text)

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self._read() is False:
                    return
        except Exception as exc:  # a bug in the reader: reported to the consumer, then raised (traceback)
            self.last_error = f"{type(exc).__name__}: {exc}"
            self._notice(f"{self.describe()}: reader stopped: {self.last_error}")
            raise
        finally:
            self.ended.set()

    # -- for the consumer ----------------------------------------------------------------
    @property
    def started(self) -> bool:
        """:meth:`start` has opened the link (it may have been closed since)."""
        return self._thread is not None

    def start(self, wait_open: float = 0.0) -> "Source":
        """Open the link (retrying for up to ``wait_open`` s) and start reading; OSError when it cannot be opened."""
        if self._thread is not None:
            raise RuntimeError(f"{self.describe()}: already started")
        self._open(wait_open)
        self._thread = threading.Thread(target=self._run, name=f"reader {self.describe()}", daemon=True)
        self._thread.start()
        return self

    def get(self, timeout: float = 0.1) -> list[SourceBatch]:
        """The batches that arrived, in order (waits up to ``timeout`` s for the first one)."""
        return drain(self._batches, timeout)

    def notices(self) -> list[str]:
        """Events for people (disconnections, reconnections), waiting now; never blocks."""
        return drain(self._notices, 0)

    def stop_reading(self) -> None:
        """Stop the reader thread, the link left open (what it read is still in :meth:`get`; :meth:`publish`
        and the like still work): the end of a run, before its last estimates are sent; notices left out are
        summed up (one per kind). Idempotent."""
        self._stop.set()
        self._interrupt()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for text in self._limiter.left_out():
            self._notices.put(text)

    @property
    def notices_suppressed(self) -> int:
        """Notices left out by the rate limit so far (:mod:`slipest.io.notice_limit`)."""
        return self._limiter.suppressed

    def close(self) -> None:
        """Stop reading (:meth:`stop_reading`) and close the link (idempotent)."""
        self.stop_reading()
        self._release()

    def __enter__(self) -> "Source":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
