"""The slipest CSV log format: write and read IMU + wheel-leg encoder logs.

This module is the I/O edge of the package: it knows about files and streams,
and nothing about estimation. Everything it returns is SI.

Format
------
A UTF-8 text file (a leading byte order mark is ignored) with ``\\n`` (or
``\\r\\n``) line endings::

    # nL=4
    # slip=0.25
    # kS=1000
    # any free-form comment
    t,az,theta,slip
    0.000000,9.810000,0.0000000,0.2500000
    0.001000,9.812345,0.0006300,0.2500000

* Lines starting with ``#`` are comments. A comment of the form
  ``# key=value`` (key: a letter or ``_`` followed by letters, digits, ``_``,
  ``.`` or ``-``) before the header is *metadata*; every comment, anywhere in
  the file, is kept (``comments``) with its line number.
* Blank lines are ignored.
* The first other line is the header: comma-separated column names.
  Required columns: ``t`` (s), ``az`` (m/s^2, vertical specific force as the
  IMU reports it, gravity included, +9.81 at rest), ``theta`` (rad, the
  wheel-leg angle). Optional: ``slip`` (dimensionless reference slip). Columns
  may appear in any order; any other column is an *extra* column: allowed,
  ignored by default, parsed as numbers on request (``extra_columns``).
* Each data row has exactly as many comma-separated fields as the header.
  A value is a number in plain decimal or exponent notation (``-1.5``,
  ``.5``, ``5.``, ``1e-3``, ``+2E+05``), or ``nan`` or ``inf`` (any case,
  optional sign), with optional spaces or tabs around it; anything else
  (``9_8``, ``0x1f``, ``infinity``, non-ASCII digits or spaces, ...) is
  malformed. ``nan`` is a valid value (a sensor dropout) and is passed
  through as NaN. An empty field is malformed in a required column and NaN
  in an optional or extra column.

Precision written by :class:`LogWriter` (fixed-point decimals, by column):
``t`` 6 (1 us), ``az`` 6 (1e-6 m/s^2), ``theta`` 7 (1e-7 rad), ``slip`` 7,
extra columns 7 unless told otherwise (``decimals=``). The round-trip error
is at most half a unit of the last decimal.

Malformed rows raise :class:`LogFormatError` naming the file, the 1-based
line number (every line counts: comments, blank lines and the header too) and
what was wrong; with ``skip_bad=True`` they are counted and skipped instead
(``LogReader.n_skipped``, ``LogReader.bad_rows``).

Speed: the reader parses a block of lines at once. A block of fixed-point
numbers (what :class:`LogWriter` writes) is read as integers and scaled; a
block whose bytes can only be numbers goes to ``numpy.loadtxt``; a block with
anything else (comments, blank lines, empty fields, bad rows, text in
ignored columns) is checked line by line, which names the bad lines. All
three give the values of ``float(text)``. The writer formats a chunk of rows
with one ``%``-format. Figures: tools/bench_segmentation.py.
"""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass, field
from typing import Iterator, Mapping, Sequence

import numba
import numpy as np

__all__ = [
    "REQUIRED_COLUMNS",
    "OPTIONAL_COLUMNS",
    "DEFAULT_DECIMALS",
    "EXTRA_DECIMALS",
    "LogFormatError",
    "BadRow",
    "LogMetadata",
    "LogChunk",
    "LogData",
    "LogReader",
    "LogWriter",
    "read_log",
    "slip_out_of_range",
]

#: Columns every log must have: time [s], vertical specific force [m/s^2],
#: wheel-leg angle [rad].
REQUIRED_COLUMNS = ("t", "az", "theta")
#: Columns that are understood when present: reference slip [-].
OPTIONAL_COLUMNS = ("slip",)
#: Decimals written for the known columns (fixed point).
DEFAULT_DECIMALS = {"t": 6, "az": 6, "theta": 7, "slip": 7}
#: Decimals written for any other column unless ``decimals=`` says otherwise.
EXTRA_DECIMALS = 7

_MAX_LINE_BYTES = 1 << 20  # longest line accepted, so memory stays bounded on garbage input
_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_NAME_BAD_CHARS = set(",#\r\n\t ")


def slip_out_of_range(slip):
    """Where a reference slip [-] (a number or an array) is outside ``[0, 1)``, the fraction the model's slip is:
    in percent, negative (a sign convention), 1 and above, ``inf`` and ``-inf``.  NaN (no reference) is not.
    The one statement of the range: a log refuses such a value
    (:func:`slipest.offline.reference_slip.check_reference_slip`), a live stream skips it
    (:func:`slipest.io.can_source.add_record`, :class:`slipest.io.serial_source.SerialSource`)."""
    return (slip < 0.0) | (slip >= 1.0)


class LogFormatError(ValueError):
    """A log file is malformed.

    ``source`` is the file name (or stream description), ``line`` the 1-based
    line number (``None`` when the problem is not on one line) and ``reason``
    what was wrong. ``str(err)`` is ``"<source>, line <n>: <reason>"``.
    """

    def __init__(self, reason: str, source: str | None = None, line: int | None = None):
        self.reason = reason
        self.source = source
        self.line = line
        where = source if source is not None else "<log>"
        if line is not None:
            where = f"{where}, line {line}"
        super().__init__(f"{where}: {reason}")


@dataclass(frozen=True)
class BadRow:
    """A skipped malformed row: its 1-based line number and the reason."""

    line: int
    reason: str


class LogMetadata(dict):
    """Metadata of a log: ``key -> value`` strings from ``# key=value`` lines.

    A plain ``dict`` of str -> str, plus typed accessors that raise
    :class:`LogFormatError` naming the file and line of a bad value.
    ``lines[key]`` is the line the (last) value came from.
    """

    def __init__(self, items=(), *, source: str | None = None, lines: Mapping[str, int] | None = None):
        super().__init__(items)
        self.source = source
        self.lines: dict[str, int] = dict(lines or {})

    def _typed(self, key, conv, kind, default):
        if key not in self:
            return default
        raw = self[key]
        try:
            return conv(raw)
        except (TypeError, ValueError):
            raise LogFormatError(
                f"metadata {key}={raw!r} is not {kind}", self.source, self.lines.get(key)
            ) from None

    def get_int(self, key: str, default: int | None = None) -> int | None:
        """Value of ``key`` as an int (``default`` when absent)."""
        return self._typed(key, int, "an integer", default)

    def get_float(self, key: str, default: float | None = None) -> float | None:
        """Value of ``key`` as a float (``default`` when absent)."""
        return self._typed(key, float, "a number", default)

    @property
    def n_legs(self) -> int | None:
        """Number of legs of the wheel-leg (``# nL=``), or None."""
        n = self.get_int("nL")
        if n is not None and n < 1:
            raise LogFormatError(f"metadata nL={n} must be >= 1", self.source, self.lines.get("nL"))
        return n

    @property
    def slip(self) -> float | None:
        """Commanded/reference slip of the whole log (``# slip=``) [-], or None."""
        return self.get_float("slip")


@dataclass(frozen=True)
class LogChunk:
    """A run of consecutive rows: ``t`` [s], ``az`` [m/s^2], ``theta`` [rad],
    ``slip`` [-] (None when the log has no slip column), ``extras`` (name ->
    array, only the extra columns that were asked for)."""

    t: np.ndarray
    az: np.ndarray
    theta: np.ndarray
    slip: np.ndarray | None
    extras: dict

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass
class LogData:
    """A whole log in memory (see :func:`read_log`)."""

    metadata: LogMetadata
    columns: tuple
    t: np.ndarray
    az: np.ndarray
    theta: np.ndarray
    slip: np.ndarray | None
    extras: dict
    comments: list = field(default_factory=list)
    n_skipped: int = 0
    bad_rows: list = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.t.shape[0])


# ---------------------------------------------------------------------------
# Numbers: the grammar, the block check, the conversion, the formatter
# ---------------------------------------------------------------------------

#: A number field (after removing spaces and tabs around it): plain decimal or
#: exponent notation, ``nan`` or ``inf`` (any case), with an optional sign.
_NUMBER_RE = re.compile(r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|nan|inf)", re.IGNORECASE | re.ASCII)
# Bytes a block of rows holding only numbers may contain, letters of nan/inf aside.
_NUMBER_BYTES = b"0123456789.,+-eE \t\n"


def _only_number_bytes(block: bytes) -> bool:
    """True if ``block`` holds no byte a number field cannot contain (letters
    only inside ``nan``/``inf``). Together with numpy.loadtxt accepting every
    field this proves each field matches :data:`_NUMBER_RE`: loadtxt alone
    also takes ``infinity`` and Unicode spaces, which this check excludes."""
    if not block.translate(None, _NUMBER_BYTES):
        return True
    return not block.lower().replace(b"nan", b"").replace(b"inf", b"").translate(None, _NUMBER_BYTES)


def _to_array(lines: Sequence[str], ncols: int) -> np.ndarray:
    """Lines of ``ncols`` comma-separated numbers -> (nlines, ncols) float64
    array, each value the correctly rounded double of its text (numpy.loadtxt;
    ValueError on a field it cannot read or a changing field count)."""
    if not lines:
        return np.empty((0, ncols), dtype=np.float64)
    return np.loadtxt(lines, delimiter=",", comments=None, dtype=np.float64, ndmin=2)


_POW10 = np.array([float(10**k) for k in range(23)])  # exact: 10**22 is the largest exact power
_MAX_FIXED_DIGITS = 15  # digits of a field the fast path reads: below 10**15 < 2**53, every integer is exact


@numba.njit(cache=True)
def _fixed_point_rows(a, ncols, out, pow10):
    """The compiled pass of :func:`_fixed_point`: parses the bytes ``a`` (uint8) into ``out`` ``(nrows,
    ncols)`` float64; returns False (``out`` partly written) at the first byte that breaks the form."""
    n = a.size
    dec = np.empty(ncols, dtype=np.int64)
    pos = 0
    for r in range(out.shape[0]):
        for c in range(ncols):
            negative = pos < n and a[pos] == 45  # '-'
            if negative:
                pos += 1
            v = 0
            digits = 0
            frac = -1  # digits after the point; -1: no point yet
            while pos < n:
                b = a[pos]
                if 48 <= b <= 57:
                    if digits == _MAX_FIXED_DIGITS:
                        return False
                    v = v * 10 + (b - 48)
                    digits += 1
                    if frac >= 0:
                        frac += 1
                elif b == 46 and frac < 0:  # '.', the first of the field
                    frac = 0
                else:
                    break
                pos += 1
            if digits == 0 or frac < 0:
                return False
            if r == 0:
                dec[c] = frac
            elif frac != dec[c]:
                return False
            if pos >= n or a[pos] != (44 if c < ncols - 1 else 10):  # ',' between fields, '\n' after the last
                return False
            pos += 1
            x = float(v) / pow10[frac]
            out[r, c] = -x if negative else x
    return pos == n


@numba.njit(cache=True)
def _count_newlines(a):
    """How many bytes of the uint8 array ``a`` are ``\\n``."""
    n = 0
    for b in a:
        n += b == 10
    return n


def _newlines(block: bytes) -> int:
    """``block.count(b"\\n")``, a few times faster (compiled)."""
    return int(_count_newlines(np.frombuffer(block, dtype=np.uint8))) if block else 0


def _fixed_point(block: bytes, ncols: int) -> np.ndarray | None:
    """:func:`_to_array` of a block of fixed-point rows, faster: every line
    ``ncols`` fields ``-?digits.digits``, each column with one number of
    decimals (as :class:`LogWriter` writes them), no other byte, at most 15
    digits a field. The digits are read as an integer (exact below 2**53)
    and divided by 10**decimals; an integer below 2**53 divided by an exact
    power of ten is the correctly rounded double of the decimal, so the
    values are bit for bit those of :func:`_to_array` (``-0.0`` included).
    One compiled pass over the bytes (:func:`_fixed_point_rows`). None for
    any other block."""
    nrows = _newlines(block)
    if nrows == 0 or not block.endswith(b"\n"):
        return None
    out = np.empty((nrows, ncols))
    if not _fixed_point_rows(np.frombuffer(block, dtype=np.uint8), ncols, out, _POW10):
        return None
    return out


def _format_rows(cols: Sequence[np.ndarray], decimals: Sequence[int]) -> bytes:
    """Equal-length float64 columns -> CSV rows, ``%.<d>f`` per column
    (correctly rounded; ``nan``, ``inf``, ``-inf``; a value that rounds to
    zero is written without a minus sign)."""
    n = cols[0].shape[0]
    if n == 0:
        return b""
    fmt = ",".join(f"%.{d}f" for d in decimals) + "\n"
    out = ((fmt * n) % tuple(np.column_stack(cols).ravel().tolist())).encode("ascii")
    if b"-0" in out:
        for d in set(decimals):
            zero = b"0." + b"0" * d if d else b"0"
            for end in (b",", b"\n"):
                out = out.replace(b"-" + zero + end, zero + end)
    return out


# ---------------------------------------------------------------------------
# Writer
# ---------------------------------------------------------------------------


def _is_text_stream(stream) -> bool:
    if isinstance(stream, io.TextIOBase):
        return True
    if isinstance(stream, (io.RawIOBase, io.BufferedIOBase)):
        return False
    return hasattr(stream, "encoding")


def _check_column_names(columns: Sequence[str]) -> tuple:
    cols = tuple(columns)
    for name in cols:
        if not isinstance(name, str) or not name or (set(name) & _NAME_BAD_CHARS):
            raise ValueError(f"invalid column name {name!r}: must be non-empty, without ',', '#', spaces or newlines")
    dup = sorted({c for c in cols if cols.count(c) > 1})
    if dup:
        raise ValueError(f"duplicate column name(s): {', '.join(dup)}")
    missing = [c for c in REQUIRED_COLUMNS if c not in cols]
    if missing:
        raise ValueError(f"columns must include {', '.join(REQUIRED_COLUMNS)}; missing: {', '.join(missing)}")
    return cols


class LogWriter:
    """Write a log: metadata comments, header, then rows in chunks.

    ``target`` is a path (the file is created; an existing file is refused
    unless ``overwrite=True``, so a log is never overwritten by mistake) or an
    already open text or binary stream (e.g. ``sys.stdout``), which is left
    open by :meth:`close`.

    ``columns`` is the header, in order; it must contain ``t``, ``az``,
    ``theta``. ``metadata`` is written as ``# key=value`` lines and
    ``comments`` as ``# text`` lines before the header. ``decimals`` overrides
    the fixed-point decimals per column (see :data:`DEFAULT_DECIMALS`).
    The header is written at construction, so a log with no rows is valid.

    Rows are formatted a chunk at a time: 3.6 M rows take a few seconds. Call
    :meth:`flush` after each chunk (or pass ``flush_each_write=True``) so a
    live recording loses nothing when the process is interrupted.
    """

    def __init__(
        self,
        target,
        columns: Sequence[str] = ("t", "az", "theta"),
        *,
        metadata: Mapping[str, object] | None = None,
        comments: Sequence[str] = (),
        decimals: Mapping[str, int] | None = None,
        overwrite: bool = False,
        flush_each_write: bool = False,
    ):
        self.columns = _check_column_names(columns)
        dec = dict(DEFAULT_DECIMALS)
        if decimals:
            for k, v in decimals.items():
                if k not in self.columns:
                    raise ValueError(f"decimals given for unknown column {k!r}")
                if not isinstance(v, (int, np.integer)) or not 0 <= v <= 17:
                    raise ValueError(f"decimals for column {k!r} must be an int in [0, 17], got {v!r}")
                dec[k] = int(v)
        self.decimals = tuple(dec.get(c, EXTRA_DECIMALS) for c in self.columns)
        self.flush_each_write = flush_each_write
        self.rows_written = 0
        self._closed = False
        lines = []
        for key, value in (metadata or {}).items():
            key = str(key)
            sval = str(value)
            if not _KEY_RE.match(key):
                raise ValueError(f"invalid metadata key {key!r}: use letters, digits, '_', '.', '-'")
            if "\n" in sval or "\r" in sval:
                raise ValueError(f"metadata value for {key!r} must be one line")
            lines.append(f"# {key}={sval}\n")
        for text in comments:
            lines.append(self._comment_line(text))
        lines.append(",".join(self.columns) + "\n")
        # everything is checked: only now create the file
        if isinstance(target, (str, bytes, os.PathLike)):
            self.name = os.fsdecode(target)
            self._stream = open(target, "wb" if overwrite else "xb")
            self._owns = True
            self._text = False
        else:
            self.name = getattr(target, "name", "<stream>")
            self._stream = target
            self._owns = False
            self._text = _is_text_stream(target)
        try:
            self._write("".join(lines).encode("utf-8"))
        except BaseException:
            self.close()
            raise

    @staticmethod
    def _comment_line(text: str) -> str:
        text = str(text)
        if "\n" in text or "\r" in text:
            raise ValueError("a comment must be one line")
        return f"# {text}\n"

    def _write(self, data: bytes) -> None:
        if self._closed:
            raise ValueError(f"{self.name}: write to a closed LogWriter")
        if self._text:
            self._stream.write(data.decode("utf-8"))
        else:
            self._stream.write(data)

    def comment(self, text: str) -> None:
        """Write a ``# text`` comment line (between rows is fine)."""
        self._write(self._comment_line(text).encode("utf-8"))

    def write(self, t, az, theta, slip=None, **extras) -> int:
        """Append rows: ``t`` [s], ``az`` [m/s^2], ``theta`` [rad], ``slip``
        [-] and extra columns by name, as equal-length 1-D arrays (or
        scalars). Every header column must be given, no other. Returns the
        number of rows written."""
        given = {"t": t, "az": az, "theta": theta, **extras}
        if slip is not None:
            given["slip"] = slip
        unknown = [k for k in given if k not in self.columns]
        missing = [k for k in self.columns if k not in given]
        if unknown or missing:
            parts = []
            if missing:
                parts.append(f"missing column(s) {', '.join(missing)}")
            if unknown:
                parts.append(f"column(s) not in the header {', '.join(unknown)}")
            raise ValueError(f"{self.name}: write(): {'; '.join(parts)} (header: {','.join(self.columns)})")
        cols = [np.atleast_1d(np.asarray(given[c], dtype=np.float64)) for c in self.columns]
        return self._write_cols(cols)

    def write_array(self, rows) -> int:
        """Append rows given as an (n, ncolumns) array in header order."""
        arr = np.asarray(rows, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != len(self.columns):
            raise ValueError(
                f"{self.name}: write_array() needs shape (n, {len(self.columns)}) "
                f"for columns {','.join(self.columns)}, got {arr.shape}"
            )
        return self._write_cols([arr[:, i] for i in range(arr.shape[1])])

    def _write_cols(self, cols) -> int:
        n = cols[0].shape[0]
        for name, c in zip(self.columns, cols):
            if c.ndim != 1 or c.shape[0] != n:
                raise ValueError(
                    f"{self.name}: column {name!r} has shape {c.shape}, expected ({n},) like {self.columns[0]!r}"
                )
        step = 65536
        for i in range(0, n, step):
            self._write(_format_rows([c[i : i + step] for c in cols], self.decimals))
        self.rows_written += n
        if self.flush_each_write:
            self.flush()
        return n

    def flush(self, fsync: bool = False) -> None:
        """Push written rows to the OS (and to disk with ``fsync=True``)."""
        if self._closed:
            return
        self._stream.flush()
        if fsync:
            try:
                os.fsync(self._stream.fileno())
            except (AttributeError, OSError, io.UnsupportedOperation):
                pass

    def close(self) -> None:
        """Flush, and close the file if this writer opened it."""
        if self._closed:
            return
        try:
            self._stream.flush()
        finally:
            self._closed = True
            if self._owns:
                self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---------------------------------------------------------------------------
# Reader
# ---------------------------------------------------------------------------


class LogReader:
    """Read a log, whole (:meth:`read_all`) or in bounded-memory chunks
    (:meth:`iter_chunks`).

    ``source``: a path, or an open text or binary stream (left open).
    The comment lines and header are read at construction: ``metadata``,
    ``columns``, ``has_slip`` and ``extra_names`` are available at once.

    ``extra_columns``: False (default) ignores extra columns (any content,
    only the field count is checked); True parses them all as numbers; a
    list of names parses those. ``skip_bad``: count and skip malformed rows
    instead of raising :class:`LogFormatError`; ``n_skipped`` counts them and
    ``bad_rows`` keeps the first ``max_bad_reported`` (line, reason).
    ``block_bytes``: how much is read and parsed at a time (memory bound;
    at most 1 MiB).

    Errors in the rows are raised while iterating, when the block holding
    them is parsed (rows before it have already been yielded). A line longer
    than 1 MiB is an error, so garbage input cannot exhaust memory.
    """

    def __init__(
        self,
        source,
        *,
        skip_bad: bool = False,
        extra_columns: bool | Sequence[str] = False,
        max_bad_reported: int = 20,
        block_bytes: int = 1 << 20,
    ):
        self.skip_bad = skip_bad
        self.max_bad_reported = max_bad_reported
        self.n_skipped = 0
        self.bad_rows: list[BadRow] = []
        self.comments: list[tuple[int, str]] = []
        self.n_rows = 0
        self._block_bytes = min(max(int(block_bytes), 1024), _MAX_LINE_BYTES)
        if isinstance(source, (str, bytes, os.PathLike)):
            self.source = os.fsdecode(source)
            self._stream = open(source, "rb")
            self._owns = True
        else:
            self.source = str(getattr(source, "name", "<stream>"))
            self._stream = source
            self._owns = False
        self._text = _is_text_stream(self._stream)
        self._pending = b""  # the start of a line whose end is not read yet
        self._head = b""  # lines after the header, read with the preamble
        self._eof = False
        self._line = 0  # number of lines consumed so far
        self._started = False
        try:
            self._read_preamble()
            self._setup_columns(extra_columns)
        except BaseException:
            self.close()
            raise

    # -- raw input -------------------------------------------------------
    def _read_raw(self) -> bytes:
        """At most ``block_bytes`` bytes (a text stream: a quarter as many
        characters, which UTF-8 encodes in at most four bytes each)."""
        data = self._stream.read(self._block_bytes // 4 if self._text else self._block_bytes)
        if not data:
            return b""
        if self._text:
            data = data.encode("utf-8")
        return data

    def _next_block(self) -> bytes:
        """Complete lines (ending with \\n), at least one, or b'' at EOF."""
        while True:
            if not self._eof:
                data = self._read_raw()
                if data:
                    self._pending += data
                else:
                    self._eof = True
            cut = self._pending.rfind(b"\n") + 1
            if cut == 0 and self._eof and self._pending:
                self._pending += b"\n"
                cut = len(self._pending)
            if cut:
                block, self._pending = self._pending[:cut], self._pending[cut:]
                # a read is at most _MAX_LINE_BYTES: only the first line can span reads
                # (the pending start of a line), so only it can be longer
                if block.find(b"\n", 0, _MAX_LINE_BYTES + 1) < 0:
                    self._too_long()
                return block
            if self._eof:
                return b""
            if len(self._pending) > _MAX_LINE_BYTES:
                self._too_long()

    def _too_long(self):
        raise LogFormatError(
            f"line longer than {_MAX_LINE_BYTES} bytes (is this a text log?)", self.source, self._line + 1
        )

    def _read_preamble(self) -> None:
        meta: dict[str, str] = {}
        lines: dict[str, int] = {}
        header = None
        buf = b""
        while header is None:
            block = self._next_block()
            if not block:
                break
            buf = block
            start = 0
            while True:
                end = buf.find(b"\n", start)
                if end < 0:
                    break
                raw = buf[start:end]
                start = end + 1
                self._line += 1
                if self._line == 1 and raw.startswith(b"\xef\xbb\xbf"):
                    raw = raw[3:]  # UTF-8 byte order mark written by some editors
                text = self._decode(raw, self._line).strip()
                if not text:
                    continue
                if text.startswith("#"):
                    body = text[1:].strip()
                    self.comments.append((self._line, body))
                    key, eq, value = body.partition("=")
                    key = key.strip()
                    if eq and _KEY_RE.match(key):
                        meta[key] = value.strip()
                        lines[key] = self._line
                    continue
                header = text
                self.header_line = self._line
                break
            if header is not None:
                self._head = buf[start:]
        if header is None:
            raise LogFormatError(
                "no header line (expected column names, e.g. 't,az,theta')", self.source, self._line or None
            )
        self.metadata = LogMetadata(meta, source=self.source, lines=lines)
        names = [h.strip() for h in header.split(",")]
        self.columns = tuple(names)
        bad = [n for n in names if not n]
        if bad:
            raise LogFormatError(f"empty column name in header {header!r}", self.source, self.header_line)
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise LogFormatError(f"duplicate column(s) {', '.join(dup)} in header", self.source, self.header_line)
        missing = [c for c in REQUIRED_COLUMNS if c not in names]
        if missing:
            raise LogFormatError(
                f"missing required column(s) {', '.join(missing)} in header {header!r} "
                f"(required: {', '.join(REQUIRED_COLUMNS)})",
                self.source,
                self.header_line,
            )

    def _decode(self, raw: bytes, line: int) -> str:
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise LogFormatError(f"not valid UTF-8 text ({exc.reason})", self.source, line) from None

    def _setup_columns(self, extra_columns) -> None:
        names = self.columns
        known = set(REQUIRED_COLUMNS) | set(OPTIONAL_COLUMNS)
        self.extra_names = tuple(n for n in names if n not in known)
        self.has_slip = "slip" in names
        if extra_columns is True:
            extras = self.extra_names
        elif extra_columns is False or extra_columns is None:
            extras = ()
        else:
            extras = tuple(extra_columns)
            unknown = [e for e in extras if e not in self.extra_names]
            if unknown:
                raise LogFormatError(
                    f"extra column(s) {', '.join(unknown)} asked for but not in the header "
                    f"(extra columns: {', '.join(self.extra_names) or 'none'})",
                    self.source,
                    self.header_line,
                )
        self.loaded_extras = extras
        sel = list(REQUIRED_COLUMNS) + (["slip"] if self.has_slip else []) + list(extras)
        self._sel_names = tuple(sel)
        self._sel_idx = np.array([names.index(n) for n in sel], dtype=np.intp)
        self._required = np.array([n in REQUIRED_COLUMNS for n in sel])
        self._ncols = len(names)
        self._identity = np.array_equal(self._sel_idx, np.arange(len(names)))

    # -- parsing ---------------------------------------------------------
    def _bad(self, line: int, reason: str) -> None:
        if not self.skip_bad:
            raise LogFormatError(reason, self.source, line)
        self.n_skipped += 1
        if len(self.bad_rows) < self.max_bad_reported:
            self.bad_rows.append(BadRow(line, reason))

    def _parse_block(self, block: bytes, first_line: int) -> np.ndarray:
        """(nrows, nselected) array of one block of complete lines whose first
        line is ``first_line``.

        Common cases, checked for the whole block at once: fixed-point rows
        (:func:`_fixed_point`), or rows of numbers only (no comment, blank
        line, empty field, other byte), which numpy.loadtxt parses in one
        call. Any other block goes through :meth:`_check_lines`, which keeps
        the comments and names the bad lines; loadtxt then parses the rows it
        kept. All give the same values (tests/test_log_csv.py states it)."""
        if b"\r" in block:
            block = block.replace(b"\r\n", b"\n")
        arr = _fixed_point(block, self._ncols)
        if arr is not None:
            return arr if self._identity else arr[:, self._sel_idx]
        if _only_number_bytes(block) and b"\n\n" not in block and not block.startswith(b"\n"):
            lines = block.decode("ascii").split("\n")[:-1]
            try:
                arr = _to_array(lines, self._ncols)
            except ValueError:  # a field that is no number, or a wrong field count
                arr = None
            if arr is not None and arr.shape == (len(lines), self._ncols):
                return arr if self._identity else arr[:, self._sel_idx]
        return _to_array(self._check_lines(block, first_line), len(self._sel_names))

    def _check_lines(self, block: bytes, first_line: int) -> list[str]:
        """The rows of a block reduced to the selected fields, each checked
        against :data:`_NUMBER_RE` (an empty optional field becomes ``nan``).
        Comments are kept, blank lines dropped, malformed rows reported
        (:meth:`_bad`)."""
        ncols = self._ncols
        columns = list(zip(self._sel_idx.tolist(), self._required.tolist(), self._sel_names))
        rows = []
        for line, raw in enumerate(block.split(b"\n")[:-1], start=first_line):
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as exc:
                self._bad(line, f"not valid UTF-8 text ({exc.reason})")
                continue
            stripped = text.strip()
            if not stripped:
                continue
            if stripped.startswith("#"):
                self.comments.append((line, stripped[1:].strip()))
                continue
            fields = text.split(",")
            if len(fields) != ncols:
                self._bad(line, f"expected {ncols} fields ({','.join(self.columns)}), found {len(fields)}")
                continue
            values = []
            for j, required, name in columns:
                f = fields[j].strip(" \t")
                if not f:
                    if required:
                        self._bad(line, f"empty field in required column {name!r}")
                        break
                    f = "nan"
                elif not _NUMBER_RE.fullmatch(f):
                    self._bad(line, f"column {name!r}: {f[:40]!r} is not a number")
                    break
                values.append(f)
            else:
                rows.append(",".join(values))
        return rows

    def _blocks(self) -> Iterator[bytes]:
        """The blocks of complete lines after the header."""
        if self._head:
            yield self._head
            self._head = b""
        while block := self._next_block():
            yield block

    def _iter_blocks(self) -> Iterator[np.ndarray]:
        if self._started:
            raise RuntimeError(f"{self.source}: a LogReader can be iterated only once")
        self._started = True
        try:
            for block in self._blocks():
                arr = self._parse_block(block, self._line + 1)
                self._line += _newlines(block)
                if arr.shape[0]:
                    self.n_rows += arr.shape[0]
                    yield arr
        finally:
            self.close()  # at the end, on an error, or when the caller stops early

    def _chunk(self, arr: np.ndarray) -> LogChunk:
        return self._columns_chunk(np.ascontiguousarray(arr.T))

    def _columns_chunk(self, arr) -> LogChunk:
        k = len(REQUIRED_COLUMNS)
        slip = arr[k] if self.has_slip else None
        k += self.has_slip
        extras = {name: arr[k + i] for i, name in enumerate(self.loaded_extras)}
        return LogChunk(arr[0], arr[1], arr[2], slip, extras)

    def iter_chunks(self, chunk_rows: int = 65536) -> Iterator[LogChunk]:
        """Yield :class:`LogChunk` s of exactly ``chunk_rows`` rows (the last
        one may be shorter). Memory is bounded by one input block (at most 1 MiB)
        plus one chunk, whatever the size of the log."""
        if chunk_rows < 1:
            raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
        parts: list[np.ndarray] = []
        have = 0
        for arr in self._iter_blocks():
            parts.append(arr)
            have += arr.shape[0]
            if have < chunk_rows:
                continue
            joined = parts[0] if len(parts) == 1 else np.concatenate(parts)
            start = 0
            while have - start >= chunk_rows:
                yield self._chunk(joined[start : start + chunk_rows])
                start += chunk_rows
            parts = [joined[start:]] if start < have else []
            have -= start
        if have:
            yield self._chunk(parts[0] if len(parts) == 1 else np.concatenate(parts))

    def read_all(self) -> LogData:
        """Read every remaining row into a :class:`LogData`."""
        parts = list(self._iter_blocks())
        ncol = len(self._sel_names)
        if parts:
            # one copy per column, straight from the parsed blocks
            cols = [np.concatenate([blk[:, j] for blk in parts]) for j in range(ncol)]
        else:
            cols = [np.empty(0, dtype=np.float64) for _ in range(ncol)]
        del parts
        ch = self._columns_chunk(cols)
        return LogData(
            metadata=self.metadata,
            columns=self.columns,
            t=ch.t,
            az=ch.az,
            theta=ch.theta,
            slip=ch.slip,
            extras=ch.extras,
            comments=list(self.comments),
            n_skipped=self.n_skipped,
            bad_rows=list(self.bad_rows),
        )

    def close(self) -> None:
        """Close the file if this reader opened it (done automatically once
        the rows are read, or reading failed)."""
        if getattr(self, "_owns", False) and not self._stream.closed:
            self._stream.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_log(
    source,
    *,
    skip_bad: bool = False,
    extra_columns: bool | Sequence[str] = False,
    max_bad_reported: int = 20,
) -> LogData:
    """Read a whole log (path or open stream) into a :class:`LogData`.

    See :class:`LogReader` for the options and the errors raised.
    """
    with LogReader(
        source, skip_bad=skip_bad, extra_columns=extra_columns, max_bad_reported=max_bad_reported
    ) as reader:
        return reader.read_all()
