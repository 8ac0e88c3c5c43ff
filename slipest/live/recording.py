"""Recording a live run's input: one log CSV per wheel, flushed as it goes.

:class:`Recorder` writes what each wheel's estimator was given (the samples
of :class:`~slipest.io.device_stream.WheelStream`) in the log format
``slipest replay`` reads: ``t`` (device time [s]), ``az`` [m/s^2],
``theta`` [rad, unwrapped], ``slip`` (reference [-], NaN when none).  A lost
frame is a row with ``az = nan`` (a dropout, as the estimator saw it); every
received sample is written as received.  Wheel 0 goes to the path given,
wheel k to ``STEM.wheelK.EXT`` (or to the path with ``{wheel}`` replaced,
when it contains it: :func:`record_path`).

Samples are buffered and written at most every ``interval`` seconds (unless
forced), then flushed to the operating system, so a process killed between
two flushes loses at most that much; :meth:`Recorder.close` writes the rest.
A file that exists is never overwritten unless told (``FileExistsError``).
"""

from __future__ import annotations

import os
import time

from slipest.io.device_stream import WheelSamples
from slipest.io.log_csv import LogWriter

__all__ = ["Recorder", "record_path"]


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
        self._writers[wheel] = LogWriter(record_path(self.template, wheel), ("t", "az", "theta", "slip"),
                                         metadata=meta, overwrite=self.overwrite,
                                         comments=["recorded live by slipest; az=nan rows stand for lost frames"])
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
                writer.write(s.t, s.az, s.theta, s.slip)
                writer.flush()

    def rows(self, wheel: int) -> int | None:
        """Rows written for the wheel so far (None: not recorded)."""
        writer = self._writers.get(wheel)
        return None if writer is None else writer.rows_written

    def close(self) -> None:
        """Write what is buffered, flush and close every file."""
        try:
            self.flush(force=True)
        finally:
            for writer in self._writers.values():
                writer.close()
