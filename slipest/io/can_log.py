"""Recorded CAN traffic (python-can's log files) handed on as the live CAN source hands it on.

A rover team records its bus with ``python -m can.logger`` or ``candump -l``.
:class:`CanLogFile` reads such a file with :func:`can.LogReader` (by its
suffix: ``.asc``, ``.blf``, ``.csv``, ``.db``, ``.log`` (candump -l),
``.mf4`` (with asammdf), ``.trc``, and each of them gzipped, ``.asc.gz``...),
decodes its frames with the DBC, a chunk at a time
(:meth:`~slipest.io.can_messages.CanDecoder.decode_many`: unknown IDs, error
frames and bad frames are counted and skipped, and so are SlipReference
frames flagged invalid or outside [0, 1), as live) and yields
:class:`~slipest.io.source.SourceBatch` es as
:class:`~slipest.io.can_source.CanSource` does live, the frame's recorded
timestamp standing for its arrival time (``intake``).  It declares the same
wire facts (``seq_modulus``, ``time_unit``, ``time_modulus``), so
:class:`slipest.live.LiveEstimation` turns a recording into samples and
estimates with the very code that serves the bus: a replay gives the
estimates the live run gave on the same frames.

A file python-can cannot read, or a frame it cannot parse, raises
:class:`~slipest.io.log_csv.LogFormatError` naming the file and the frame's
1-based index (a bad frame after the frames before it are handed on).
``check_references`` sees each chunk's references before any is handed on:
a replay that learns from them refuses one outside [0, 1) there.  A ``.mf4``
needs asammdf (:class:`~slipest.extras.MissingExtra` naming
``pip install 'slipest[mf4]'``).
Memory: one batch at a time (``batch_frames`` frames).
"""

from __future__ import annotations

import os
from typing import Callable, Iterator

import can
import numpy as np
from can.io.player import MESSAGE_READERS

from slipest.extras import import_extra
from slipest.io.can_messages import COUNTER_MODULUS, REORDER_FRAMES, TIME_MOD_PERIOD, CanDecoder, SlipReferenceMessage
from slipest.io.can_source import add_record
from slipest.io.log_csv import LogFormatError
from slipest.io.source import SourceBatch

__all__ = ["CAN_LOG_SUFFIXES", "CanLogFile", "is_can_log_name"]

#: Suffixes python-can reads (a ``.gz`` after one of them too); ``.csv`` is also the slipest log's.
CAN_LOG_SUFFIXES = tuple(sorted(MESSAGE_READERS))


def is_can_log_name(path) -> bool:
    """Whether python-can would pick a reader for this file name (``.blf``, ``.asc.gz``...)."""
    name = os.fspath(path).lower()
    if name.endswith(".gz"):
        name = name[:-3]
    return os.path.splitext(name)[1] in MESSAGE_READERS


class CanLogFile:
    """A python-can log file's frames as :class:`~slipest.io.source.SourceBatch` es.

    ``path``: the file (python-can picks the reader by suffix).  Iterate
    :meth:`batches` once.  Wire facts as :class:`~slipest.io.can_source.CanSource`.
    Counters (:meth:`counters`): ``frames`` read, the decoder's (``ok``,
    ``unknown_id``, ``bad_frame``, ``not_data``, ``counter_gaps``...),
    ``references_invalid`` (SlipReference frames flagged invalid) and
    ``references_out_of_range`` (SlipReference frames with a slip outside [0, 1)), both skipped.
    ``check_references(slip, t)``: called with the slips [-] and recorded timestamps [s] of each chunk's
    SlipReference frames not flagged invalid, before any of the chunk is handed on; what it raises stops
    the reading (a replay that learns from the references refuses one outside [0, 1) this way).
    """

    seq_modulus = COUNTER_MODULUS
    reorder_window = REORDER_FRAMES
    time_unit = 1.0
    time_modulus = TIME_MOD_PERIOD

    def __init__(self, path, *, batch_frames: int = 4096, check_references: Callable | None = None):
        self.path = os.fspath(path)
        if not is_can_log_name(self.path):
            raise LogFormatError(f"python-can reads no log with this suffix (it reads {', '.join(CAN_LOG_SUFFIXES)}, "
                                 "also gzipped)", self.path)
        if not os.path.isfile(self.path):
            raise FileNotFoundError(2, "no such file", self.path)
        if self.path.lower().removesuffix(".gz").endswith(".mf4"):
            import_extra("asammdf", "mf4", f"reading the .mf4 CAN log {self.path}")
        self.batch_frames = max(1, int(batch_frames))
        self.check_references = check_references
        self.decoder = CanDecoder()
        self.c = {"frames": 0, "references_invalid": 0, "references_out_of_range": 0, "bytes_missing": 0}
        self.first_timestamp: float | None = None

    def describe(self) -> str:
        return f"canlog:{self.path}"

    def counters(self) -> dict:
        c = self.decoder.counters()
        c.pop("counter_gaps_by_wheel", None)
        c.update(self.c)
        return c

    def _messages(self) -> Iterator[can.Message]:
        try:
            reader = can.LogReader(self.path)
        except Exception as exc:  # python-can's readers raise what they raise (BLFParseError, struct.error, ...)
            raise LogFormatError(f"python-can cannot open it ({type(exc).__name__}: {exc})", self.path) from None
        stated = getattr(reader, "file_size", 0)  # a BLF header's size of the whole file
        if not self.path.endswith(".gz") and stated and stated > os.path.getsize(self.path):
            self.c["bytes_missing"] = stated - os.path.getsize(self.path)
        with reader:
            it = iter(reader)
            while True:
                try:
                    msg = next(it)
                except StopIteration:
                    return
                except Exception as exc:  # python-can's parsers raise what they raise: name the frame
                    raise LogFormatError(f"frame {self.c['frames'] + 1}: python-can cannot parse it "
                                         f"({type(exc).__name__}: {exc})", self.path) from None
                yield msg

    def batches(self) -> Iterator[list[SourceBatch]]:
        """Lists of up to ``batch_frames`` batches, one per frame of ours (in file order), each with
        its recorded timestamp as ``intake``.  A frame python-can cannot parse raises
        :class:`LogFormatError` naming it, after the batches of every frame before it."""
        c = self.c
        out: list[SourceBatch] = []
        chunk: list[can.Message] = []
        messages = self._messages()
        error = None
        while error is None:
            try:
                for msg in messages:  # the frames are decoded together (decode_many), a chunk at a time
                    c["frames"] += 1
                    chunk.append(msg)
                    if len(chunk) >= self.batch_frames:
                        break
            except LogFormatError as exc:  # the frames before the one python-can could not parse go on first
                error = exc
            if not chunk:
                break
            recs = self.decoder.decode_many(chunk)
            if self.check_references is not None:
                self._check_references(chunk, recs)
            for msg, rec in zip(chunk, recs):
                imu: list = []
                refs: list = []
                unusable = add_record(rec, imu, refs)
                if unusable:
                    c[unusable] += 1
                if not (imu or refs):
                    continue
                ts = float(msg.timestamp)
                if self.first_timestamp is None:
                    self.first_timestamp = ts
                out.append(SourceBatch(ts, imu, refs))
                if len(out) >= self.batch_frames:
                    yield out
                    out = []
            chunk = []
        if out:
            yield out
        if error is not None:
            raise error

    def _check_references(self, chunk, recs) -> None:
        got = [(rec.slip, msg.timestamp) for msg, rec in zip(chunk, recs)
               if isinstance(rec, SlipReferenceMessage) and rec.slip == rec.slip]
        if got:
            slip, t = np.array(got, dtype=float).T
            self.check_references(slip, t)
