"""Recording a live run: its samples in a log CSV, its raw CAN frames in python-can logs.

Two kinds of recording, chosen by the file name as ``slipest replay`` reads
it back (:func:`record_kind`):

* the **samples** (a ``.csv``, or any name that is not a python-can log):
  :class:`Recorder` writes what each wheel's estimator was given (the
  samples of :class:`~slipest.io.device_stream.WheelStream`) in the log
  format ``slipest replay`` reads: ``t`` (device time [s]), ``az``
  [m/s^2], ``theta`` [rad, unwrapped], ``slip`` (reference [-], NaN when
  none).  A lost frame is a row with ``az = nan`` (a dropout, as the
  estimator saw it); every received sample is written as received.  Wheel
  0 goes to the path given, wheel k to ``STEM.wheelK.EXT`` (or to the path
  with ``{wheel}`` replaced, when it contains it: :func:`record_path`).
* the **raw CAN frames** (a python-can log name: ``.asc``, ``.blf``,
  ``.log`` (candump -l), ``.trc``, ``.db``, ``.mf4`` with asammdf, the text
  ones also gzipped, ``.asc.gz``...; python-can's own ``.csv`` when asked
  for frames explicitly): :class:`FrameRecorder` writes every frame the bus
  delivered (every wheel, unknown IDs, frames that failed to decode, error
  frames: nothing is lost) with python-can's writer for the suffix
  (``can.Logger``), so ``slipest replay`` of the log gives the estimates of
  the live run, bit for bit.  Only a source of CAN frames has them
  (:class:`~slipest.io.can_source.CanSource`); a serial link's frames are
  not CAN frames, and asking for a CAN log of one is an error (why:
  ``docs/live-view.md``).

Both are flushed as they go: samples are buffered and written at most every
``interval`` seconds (unless forced), then flushed to the operating system;
frames are written as they arrive and flushed every ``interval`` seconds (a
BLF in containers of :data:`BLF_CONTAINER_BYTES`, so little waits in
memory).  A process killed between two flushes loses at most that much;
``close`` writes the rest and completes the file (a BLF's header).  A file
that exists is never overwritten unless told (``FileExistsError``).
:class:`Recording` is what a live run records: one samples recording and
any number of frame logs, from a list of paths.
"""

from __future__ import annotations

import os
import threading
import time

from slipest.extras import MissingExtra, import_extra
from slipest.io.device_stream import WheelSamples
from slipest.io.log_csv import LogWriter

__all__ = ["BLF_CONTAINER_BYTES", "FrameRecorder", "Recorder", "Recording", "record_kind", "record_path"]

#: A BLF's frames are compressed and written in containers of this many bytes (python-can's default,
#: 128 KiB, would keep about 2700 frames in memory; this keeps about 85, 0.1 s of a 1 kHz wheel).
BLF_CONTAINER_BYTES = 4096


def record_kind(path: str) -> str:
    """``"frames"`` for a name ``slipest replay`` reads as a python-can log (``.asc``, ``.blf``,
    ``.log``, ``.trc``, ``.db``, ``.mf4``, also gzipped: ``.asc.gz``, ``.csv.gz``...), else
    ``"samples"`` (``.csv`` and any other name: the slipest log CSV)."""
    from slipest.io.can_log import is_can_log_name

    name = os.fspath(path).lower()
    return "frames" if is_can_log_name(name) and not name.endswith(".csv") else "samples"


def record_path(template: str, wheel: int) -> str:
    """Where wheel ``wheel`` is recorded for the path ``template``."""
    if "{wheel}" in template:
        return template.replace("{wheel}", str(wheel))
    if wheel == 0:
        return template
    stem, ext = os.path.splitext(template)
    return f"{stem}.wheel{wheel}{ext}"


class Recorder:
    """Per-wheel log CSVs of a live run (see the module docstring).

    ``template``: the path (see :func:`record_path`); ``n_legs`` and
    ``source`` (a description of the link) go into each file's metadata.
    Raises ``FileExistsError`` at once when wheel 0's file exists (unless
    ``overwrite``), and from :meth:`open_wheel` for a later wheel's.
    """

    def __init__(self, template: str, *, n_legs: int, source: str = "live", overwrite: bool = False,
                 interval: float = 0.1):
        self.template = template
        self.n_legs = n_legs
        self.source = source
        self.overwrite = overwrite
        self.interval = interval
        self._writers: dict[int, LogWriter] = {}
        self._pending: dict[int, list[WheelSamples]] = {}
        self._last_flush = 0.0
        first = record_path(template, 0)
        if not overwrite and os.path.exists(first):
            raise FileExistsError(f"{first} exists (a recording is never overwritten by mistake)")

    def open_wheel(self, wheel: int) -> None:
        """Create the wheel's file (its header and metadata); FileExistsError when it exists."""
        meta = {"nL": self.n_legs, "wheel": wheel, "source": self.source,
                "recorded": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        try:
            self._writers[wheel] = LogWriter(record_path(self.template, wheel), ("t", "az", "theta", "slip"),
                                             metadata=meta, overwrite=self.overwrite,
                                             comments=["recorded live by slipest; az=nan rows stand for lost frames"])
        except FileExistsError:
            raise
        except OSError as exc:
            raise self._failed(wheel, exc) from None
        self._pending[wheel] = []

    def add(self, wheel: int, samples: WheelSamples) -> None:
        """Samples of an opened wheel, in order (written by the next :meth:`flush`)."""
        if len(samples):
            self._pending[wheel].append(samples)

    def flush(self, force: bool = False) -> None:
        """Write the buffered samples and flush the files to the OS (every ``interval`` s at most unless
        ``force``: formatting a few rows at a time would cost more than estimating them)."""
        now = time.monotonic()
        if not force and now - self._last_flush < self.interval:
            return
        self._last_flush = now
        for wheel, pending in self._pending.items():
            if pending:
                s = WheelSamples.concatenate(pending)
                pending.clear()  # taken before writing: whatever happens, no row is ever written twice
                writer = self._writers[wheel]
                try:
                    writer.write(s.t, s.az, s.theta, s.slip)
                    writer.flush()
                except OSError as exc:
                    raise self._failed(wheel, exc, len(s)) from None

    def _failed(self, wheel: int, exc: OSError, lost: int = 0) -> OSError:
        """``exc`` naming the wheel's file and what it holds (the recording stops there)."""
        writer = self._writers.get(wheel)
        done = writer.rows_written if writer is not None else 0
        return OSError(exc.errno, f"{record_path(self.template, wheel)}: recording the samples failed "
                                  f"({exc.strerror or exc}) after {done} rows"
                                  + (f"; {lost} samples not recorded, and none after them" if lost else ""))

    def rows(self, wheel: int) -> int | None:
        """Rows written for the wheel so far (None: not recorded)."""
        writer = self._writers.get(wheel)
        return None if writer is None else writer.rows_written

    def close(self) -> None:
        """Write what is buffered, flush and close every file."""
        try:
            self.flush(force=True)
        finally:
            first = None
            for wheel, writer in self._writers.items():  # every file closed, the first failure raised
                try:
                    writer.close()
                except OSError as exc:
                    first = first or self._failed(wheel, exc)
            if first is not None:
                raise first


class FrameRecorder:
    """Every CAN frame of a live run in a python-can log (see the module docstring).

    ``path``: the log; python-can's writer for its suffix writes it
    (``can.Logger``; ``.csv`` is python-can's CSV here).  ``ValueError``
    naming the path for a suffix python-can cannot write or ``slipest
    replay`` cannot read back, or a writer that is missing its package
    (``.mf4`` without asammdf: ``pip install 'slipest[mf4]'``); ``FileExistsError`` when it exists (unless
    ``overwrite``).

    A python-can listener: :meth:`on_message_received` (also ``self(msg)``)
    takes each frame, from any thread (a source's reader thread); the frame
    is written with its bus timestamp, channel and direction as python-can
    gave them.  :meth:`flush` (from the thread that runs the loop) flushes
    the file every ``interval`` s at most and raises, naming the file, the
    error that stopped the writing (a full disk...): the frames that came
    after it are counted (``frames_not_recorded``), never written halfway.
    :meth:`close` (once the source has stopped) completes the file.
    """

    def __init__(self, path: str, *, overwrite: bool = False, interval: float = 0.1):
        import can
        from can.io.logger import MESSAGE_WRITERS
        from can.io.player import MESSAGE_READERS

        self.path = os.fspath(path)
        self.interval = interval
        name = self.path.lower()
        base = name[:-3] if name.endswith(".gz") else name
        suffix = os.path.splitext(base)[1]
        if suffix not in MESSAGE_WRITERS or suffix not in MESSAGE_READERS:
            known = sorted(set(MESSAGE_WRITERS) & set(MESSAGE_READERS))
            raise ValueError(f"{self.path}: not a python-can log that slipest replay reads back "
                             f"(suffixes: {', '.join(known)}, the text ones also gzipped)")
        if not overwrite and os.path.exists(self.path):
            raise FileExistsError(f"{self.path} exists (a recording is never overwritten by mistake)")
        if suffix == ".mf4":  # python-can's own message names its extra, not ours
            try:
                import_extra("asammdf", "mf4", "recording a .mf4 CAN log")
            except MissingExtra as exc:
                raise ValueError(f"{self.path}: {exc}") from None
        kwargs = {"max_container_size": BLF_CONTAINER_BYTES} if base.endswith(".blf") else {}
        try:
            self.writer = can.Logger(self.path, **kwargs)
        except (ValueError, NotImplementedError, ImportError) as exc:  # e.g. .blf.gz; .mf4 without asammdf
            raise ValueError(f"{self.path}: python-can cannot write it: {exc}") from None
        self.frames = 0
        self.frames_not_recorded = 0
        self.error: str | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._last_flush = 0.0

    def on_message_received(self, msg) -> None:
        """Write one frame (any thread)."""
        with self._lock:
            if self._closed or self.error is not None:
                self.frames_not_recorded += 1
                return
            try:
                self.writer.on_message_received(msg)
            except Exception as exc:  # kept and raised by flush()/close() in the loop's thread: not swallowed
                self.error = f"{type(exc).__name__}: {exc}"
                self.frames_not_recorded += 1
                return
            self.frames += 1

    __call__ = on_message_received

    def _raise(self) -> None:
        if self.error is not None:
            raise OSError(f"{self.path}: recording the CAN frames failed ({self.error}); "
                          f"{self.frames} frames recorded, {self.frames_not_recorded} not")

    def flush(self, force: bool = False) -> None:
        """Flush the written frames to the OS (every ``interval`` s at most unless ``force``); raise the
        error that stopped the writing, if any."""
        self._raise()
        now = time.monotonic()
        if not force and now - self._last_flush < self.interval:
            return
        self._last_flush = now
        with self._lock:
            file = getattr(self.writer, "file", None)  # (python-can's SqliteWriter commits on its own)
            if not self._closed and file is not None and not file.closed:
                file.flush()

    def counters(self) -> dict:
        """``frames_recorded`` and ``frames_not_recorded``."""
        return {"frames_recorded": self.frames, "frames_not_recorded": self.frames_not_recorded}

    def close(self) -> None:
        """Complete and close the log (idempotent); raise the error that stopped the writing, if any."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self.writer.stop()
        self._raise()

    def stop(self) -> None:
        """python-can's name for :meth:`close`."""
        self.close()


class Recording:
    """What a live run records: the samples in one log CSV and the raw CAN frames in python-can logs.

    ``paths``: file names, each recorded as :func:`record_kind` says (at
    most one samples recording); ``frames``: names recorded as CAN frames
    whatever their suffix (python-can's ``.csv``).  ``source``: the
    :class:`~slipest.io.source.Source`; frame logs are given its frames
    (``source.add_listener``), so it must deliver CAN frames.  ``n_legs``:
    the samples' metadata.  Raises, before any file is created:
    ``ValueError`` (a frame log of a source without CAN frames, two samples
    recordings, a suffix python-can cannot write), ``FileExistsError``
    (unless ``overwrite``).  The interface of :class:`Recorder`
    (:meth:`open_wheel`, :meth:`add`, :meth:`flush`, :meth:`rows`,
    :meth:`close`) plus :meth:`counters`.
    """

    def __init__(self, paths=(), *, source, n_legs: int, frames=(), overwrite: bool = False, interval: float = 0.1):
        paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
        samples = [os.fspath(p) for p in paths if record_kind(p) == "samples"]
        frame_paths = [os.fspath(p) for p in paths if record_kind(p) == "frames"] + [os.fspath(p) for p in frames]
        if len(samples) > 1:
            raise ValueError(f"one samples recording at most, got {', '.join(samples)}")
        add_listener = getattr(source, "add_listener", None)
        if frame_paths and add_listener is None:
            raise ValueError(f"{frame_paths[0]}: a python-can log records CAN frames, and {source.describe()} "
                             "delivers none (record its samples to a .csv instead)")
        for path in frame_paths:
            if "{wheel}" in path:
                raise ValueError(f"{path}: one CAN log holds every wheel's frames ({{wheel}} is for samples)")
            if not overwrite and os.path.exists(path):
                raise FileExistsError(f"{path} exists (a recording is never overwritten by mistake)")
        self.samples = (Recorder(samples[0], n_legs=n_legs, source=source.describe(), overwrite=overwrite,
                                 interval=interval) if samples else None)
        self.frame_logs: list[FrameRecorder] = []
        try:
            for path in frame_paths:
                self.frame_logs.append(FrameRecorder(path, overwrite=overwrite, interval=interval))
        except BaseException:
            self.close()
            raise
        for log in self.frame_logs:
            add_listener(log)

    def open_wheel(self, wheel: int) -> None:
        """Create the wheel's samples file (FileExistsError when it exists); nothing for frame logs."""
        if self.samples is not None:
            self.samples.open_wheel(wheel)

    def add(self, wheel: int, samples: WheelSamples) -> None:
        """Samples of an opened wheel, in order."""
        if self.samples is not None:
            self.samples.add(wheel, samples)

    def flush(self, force: bool = False) -> None:
        """Write and flush what is buffered (every ``interval`` s at most unless ``force``)."""
        if self.samples is not None:
            self.samples.flush(force)
        for log in self.frame_logs:
            log.flush(force)

    def rows(self, wheel: int) -> int | None:
        """Sample rows written for the wheel so far (None: samples not recorded)."""
        return None if self.samples is None else self.samples.rows(wheel)

    def counters(self) -> dict:
        """Per frame log (its path): frames recorded and not recorded."""
        return {log.path: log.counters() for log in self.frame_logs}

    def close(self) -> None:
        """Complete and close every file (the source must have stopped); the first error is raised."""
        errors = []
        for closer in ([self.samples.close] if self.samples is not None else []) + [g.close for g in self.frame_logs]:
            try:
                closer()
            except Exception as exc:  # every file is closed; then the first error is raised
                errors.append(exc)
        if errors:
            raise errors[0]
