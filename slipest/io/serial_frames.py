"""Binary serial wire format of slipest: fixed little-endian frames, CRC-16, COBS.

Every frame on the serial link is::

    COBS( payload || CRC16_LE(payload) ) || 0x00

* ``payload`` is a fixed little-endian ``struct`` layout whose first byte is
  the frame type, so new frame types can be added later.
* ``CRC16_LE`` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no
  reflection, no final xor; check value ``0x29B1`` for ``b"123456789"``)
  computed with ``binascii.crc_hqx(payload, 0xFFFF)`` over the whole payload
  (type byte included) and appended little-endian (low byte first).
* ``COBS`` is Consistent Overhead Byte Stuffing (package ``cobs``); the encoded
  frame contains no zero byte, and a single ``0x00`` terminates it.  Payloads
  are shorter than 254 bytes, so COBS adds exactly one byte.  A sender may
  also emit a lone ``0x00`` at start-up to flush whatever garbage the receiver
  has buffered; empty frames are ignored by the receiver.

Frame types (all multi-byte fields little-endian)::

    IMU_SAMPLE (type 0x01) payload 20 B, +CRC 22 B, COBS 23 B, on wire 24 B
    off size type     field   unit / meaning
      0   1  u8       type    0x01
      1   1  u8       wheel   wheel-leg index 0..5
      2   2  u16      seq     per-(type, wheel) sequence counter, +1 per frame,
                              wraps 65535 -> 0
      4   8  u64      t_us    device timestamp [us]
     12   4  float32  az      vertical specific force [m/s^2], +9.81 at rest
     16   4  float32  theta   wheel-leg angle [rad], wrapped by the device
                              (normally to [-pi, pi)); the receiver unwraps
     20   2  u16      crc     CRC-16/CCITT-FALSE of bytes 0..19

    SLIP_REFERENCE (type 0x02) payload 16 B, +CRC 18 B, COBS 19 B, on wire 20 B
    off size type     field   unit / meaning
      0   1  u8       type    0x02
      1   1  u8       wheel   wheel-leg index 0..5
      2   2  u16      seq     as above (own counter per type and wheel)
      4   8  u64      t_us    device timestamp [us]
     12   4  float32  slip    reference slip from the testbed [-]
     16   2  u16      crc     CRC-16/CCITT-FALSE of bytes 0..15

Sequence counters are 16 bit: the receiver computes the number of missed
frames of a stream as ``(seq - last_seq - 1) mod 65536``.  A forward distance
of 32768 or more is read as a duplicate, a reordering or a device restart
(counter ``seq_backwards``) rather than a gap, as in serial-number arithmetic
(RFC 1982); an outage longer than 32767 frames (32 s at 1 kHz) is therefore
miscounted, and the timestamps ``t_us`` tell the whole story.

Receiving: :class:`FrameDecoder` is a protocol object in the style of
``serial.threaded.Packetizer``: feed it bytes in chunks of any size, it returns
the frames completed by that chunk.  It never delivers a frame that failed
any check, resynchronises on the next ``0x00`` and keeps counters (see
:meth:`FrameDecoder.counters`).  Every non-empty segment between two zeros is
classified, in this order:

1. its length is not the COBS length of a known frame type -> ``malformed``
   (this also bounds the receive buffer: a segment longer than
   :data:`MAX_SEGMENT_LEN` bytes is dropped as soon as it is that long);
2. COBS decoding fails -> ``malformed``;
3. CRC mismatch -> ``crc_errors``;
4. the type byte does not belong to that length, or ``wheel`` >= 6 ->
   ``malformed``;
5. a float field is NaN or infinite -> ``nonfinite`` (the frame was received
   intact, so it still advances the sequence counter, but it is not delivered);
6. otherwise the frame is delivered (``frames_ok``).

(CRC-16 detects every burst of up to 16 bits and every odd number of bit
errors; other corruptions of a correctly framed frame pass it with a
probability of about 2**-16.)

:func:`decode_capture` does the same on a whole captured byte stream with
numpy (vectorised COBS unstuffing and a 16-bit-table CRC; all classification
is vectorised because each frame type has a fixed encoded length) and returns
exactly what a fresh :class:`FrameDecoder` would deliver, as a structured
array of dtype :data:`CAPTURE_DTYPE`, together with the same counters.

:class:`FrameProtocol` plugs the decoder into ``serial.threaded.ReaderThread``.
"""

from __future__ import annotations

import binascii
import math
import struct
from typing import Callable, NamedTuple, Union

import numpy as np
import serial.threaded
from cobs import cobs

__all__ = [
    "FRAME_IMU_SAMPLE",
    "FRAME_SLIP_REFERENCE",
    "N_WHEELS",
    "SEQ_MODULUS",
    "MAX_SEGMENT_LEN",
    "CAPTURE_DTYPE",
    "ImuSample",
    "SlipReference",
    "Frame",
    "crc16",
    "encode_frame",
    "encode_imu_sample",
    "encode_slip_reference",
    "encode_imu_samples",
    "encode_slip_references",
    "FrameDecoder",
    "FrameProtocol",
    "decode_capture",
    "frames_to_array",
]

#: Frame type byte of an IMU sample.
FRAME_IMU_SAMPLE = 0x01
#: Frame type byte of a testbed reference slip.
FRAME_SLIP_REFERENCE = 0x02
#: Number of wheel-legs; valid wheel indices are 0..N_WHEELS-1.
N_WHEELS = 6
#: Sequence counters wrap modulo this value (16-bit counters).
SEQ_MODULUS = 1 << 16
_SEQ_HALF = SEQ_MODULUS // 2
#: Longest segment (bytes between two zero delimiters) the decoder buffers;
#: longer segments are dropped and counted as malformed.
MAX_SEGMENT_LEN = 255


class ImuSample(NamedTuple):
    """One hub IMU sample of one wheel-leg, as sent by the device."""

    wheel: int  #: wheel-leg index 0..5
    seq: int  #: 16-bit sequence counter
    t_us: int  #: device timestamp [us]
    az: float  #: vertical specific force [m/s^2] (float32 precision)
    theta: float  #: wheel-leg angle [rad], wrapped by the device

    @property
    def t(self) -> float:
        """Device timestamp [s]."""
        return self.t_us * 1e-6

    @property
    def kind(self) -> int:
        """Frame type byte (:data:`FRAME_IMU_SAMPLE`)."""
        return FRAME_IMU_SAMPLE


class SlipReference(NamedTuple):
    """One reference slip value of one wheel-leg, as sent by a testbed."""

    wheel: int  #: wheel-leg index 0..5
    seq: int  #: 16-bit sequence counter
    t_us: int  #: device timestamp [us]
    slip: float  #: reference slip [-] (float32 precision)

    @property
    def t(self) -> float:
        """Device timestamp [s]."""
        return self.t_us * 1e-6

    @property
    def kind(self) -> int:
        """Frame type byte (:data:`FRAME_SLIP_REFERENCE`)."""
        return FRAME_SLIP_REFERENCE


Frame = Union[ImuSample, SlipReference]

#: One decoded frame per row, in stream order.  ``kind`` is the frame type
#: byte; ``t_us`` the device timestamp [us]; ``az`` [m/s^2] and ``theta``
#: [rad] are NaN in SLIP_REFERENCE rows, ``slip`` [-] is NaN in IMU_SAMPLE rows.
CAPTURE_DTYPE = np.dtype(
    [
        ("kind", "u1"),
        ("wheel", "u1"),
        ("seq", "<u2"),
        ("t_us", "<u8"),
        ("az", "<f4"),
        ("theta", "<f4"),
        ("slip", "<f4"),
    ]
)


class _Spec(NamedTuple):
    kind: int
    payload: struct.Struct  # full payload layout, type byte first
    wire_dtype: np.dtype  # packed payload + crc, for the vectorised paths
    record: type
    values: tuple[str, ...]  # float fields, in payload order

    @property
    def payload_len(self) -> int:
        return self.payload.size

    @property
    def encoded_len(self) -> int:
        """COBS-encoded length without the delimiter (payload + 2 CRC + 1)."""
        return self.payload.size + 3


def _wire_dtype(values: tuple[str, ...]) -> np.dtype:
    fields = [("kind", "u1"), ("wheel", "u1"), ("seq", "<u2"), ("t_us", "<u8")]
    fields += [(name, "<f4") for name in values]
    fields += [("crc", "<u2")]
    return np.dtype(fields)  # packed (align=False), itemsize = payload + 2


_SPECS: dict[int, _Spec] = {
    FRAME_IMU_SAMPLE: _Spec(
        FRAME_IMU_SAMPLE, struct.Struct("<BBHQff"), _wire_dtype(("az", "theta")),
        ImuSample, ("az", "theta"),
    ),
    FRAME_SLIP_REFERENCE: _Spec(
        FRAME_SLIP_REFERENCE, struct.Struct("<BBHQf"), _wire_dtype(("slip",)),
        SlipReference, ("slip",),
    ),
}
#: encoded length -> spec; the decoder relies on each type having its own length.
_SPEC_BY_ENCODED_LEN: dict[int, _Spec] = {s.encoded_len: s for s in _SPECS.values()}
if len(_SPEC_BY_ENCODED_LEN) != len(_SPECS):  # pragma: no cover - guards future edits
    raise RuntimeError("two serial frame types have the same encoded length")
for _s in _SPECS.values():  # pragma: no cover - guards future edits
    if (_s.wire_dtype.itemsize != _s.payload_len + 2
            or _s.payload_len % 2  # the vectorised CRC works on 16-bit words
            or _s.encoded_len > MAX_SEGMENT_LEN):
        raise RuntimeError(f"serial frame type {_s.kind:#04x}: inconsistent layout")

_CRC = struct.Struct("<H")

# ---------------------------------------------------------------------------
# CRC-16/CCITT-FALSE
# ---------------------------------------------------------------------------


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``binascii.crc_hqx(data, 0xFFFF)``)."""
    return binascii.crc_hqx(data, 0xFFFF)


def _crc_word_table() -> np.ndarray:
    """Table T with crc' = T[crc ^ word] for one big-endian 16-bit word.

    Feeding bytes b0, b1 to a non-reflected 16-bit CRC register equals xoring
    ``b0 << 8 | b1`` into the register and shifting 16 zero bits through it,
    and shifting 16 zero bits is ``crc_hqx(b"\\0\\0", x)``.
    """
    byte_table = np.array([binascii.crc_hqx(bytes([i]), 0) for i in range(256)], np.uint32)
    x = np.arange(1 << 16, dtype=np.uint32)
    c1 = ((x << 8) & 0xFFFF) ^ byte_table[x >> 8]
    c2 = ((c1 << 8) & 0xFFFF) ^ byte_table[c1 >> 8]
    return c2.astype(np.uint16)


_CRC_WORD_TABLE = _crc_word_table()


def _crc16_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of every row of a (n, even) uint8 array -> uint16[n]."""
    if rows.strides[-1] != 1:
        rows = np.ascontiguousarray(rows)
    words = rows.view(">u2")  # big-endian 16-bit words, one row per frame
    crc = np.full(rows.shape[0], 0xFFFF, np.uint16)
    for j in range(words.shape[1]):
        np.bitwise_xor(crc, words[:, j], out=crc, casting="unsafe")
        crc = _CRC_WORD_TABLE.take(crc)
    return crc


# ---------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------


def encode_frame(payload: bytes) -> bytes:
    """Wrap a raw payload (type byte first): append CRC, COBS-encode, add 0x00.

    Low-level; use :func:`encode_imu_sample` and friends for known frame types.
    """
    payload = bytes(payload)
    return cobs.encode(payload + _CRC.pack(crc16(payload))) + b"\x00"


def _check_header(wheel: int, seq: int, t_us: int) -> int:
    if not 0 <= wheel < N_WHEELS:
        raise ValueError(f"wheel index must be 0..{N_WHEELS - 1}, got {wheel!r}")
    if not 0 <= t_us < 1 << 64:
        raise ValueError(f"t_us must be 0 <= t_us < 2**64 microseconds, got {t_us!r}")
    return seq % SEQ_MODULUS


def _check_float32(name: str, value: float) -> float:
    value = float(value)
    with np.errstate(over="ignore", invalid="ignore"):
        finite = np.isfinite(np.float32(value))
    if not finite:
        raise ValueError(f"{name} must be a finite float32 value, got {value!r}")
    return value


def encode_imu_sample(wheel: int, seq: int, t_us: int, az: float, theta: float) -> bytes:
    """Encode one IMU_SAMPLE frame (delimiter included).

    :param wheel: wheel-leg index 0..5.
    :param seq: sequence counter; reduced modulo 2**16.
    :param t_us: device timestamp [us], 0 <= t_us < 2**64.
    :param az: vertical specific force [m/s^2] (sent as float32).
    :param theta: wheel-leg angle [rad] (sent as float32, as the device wraps it).
    :raises ValueError: wheel out of range, negative timestamp, non-finite value.
    """
    seq = _check_header(wheel, seq, t_us)
    payload = _SPECS[FRAME_IMU_SAMPLE].payload.pack(
        FRAME_IMU_SAMPLE, wheel, seq, t_us,
        _check_float32("az", az), _check_float32("theta", theta),
    )
    return encode_frame(payload)


def encode_slip_reference(wheel: int, seq: int, t_us: int, slip: float) -> bytes:
    """Encode one SLIP_REFERENCE frame (delimiter included).

    :param wheel: wheel-leg index 0..5.
    :param seq: sequence counter; reduced modulo 2**16.
    :param t_us: device timestamp [us].
    :param slip: reference slip [-] (sent as float32).
    :raises ValueError: wheel out of range, negative timestamp, non-finite value.
    """
    seq = _check_header(wheel, seq, t_us)
    payload = _SPECS[FRAME_SLIP_REFERENCE].payload.pack(
        FRAME_SLIP_REFERENCE, wheel, seq, t_us, _check_float32("slip", slip)
    )
    return encode_frame(payload)


def _cobs_encode_rows(rows: np.ndarray) -> np.ndarray:
    """COBS-encode every row of a (n, L) uint8 array, L < 254, and append 0x00.

    Returns a (n, L + 2) uint8 array: code byte, stuffed data, delimiter.
    """
    n, width = rows.shape
    out = np.empty((n, width + 2), np.uint8)
    next_zero = np.full(n, width, np.int64)  # index of the next zero (virtual one at the end)
    for i in range(width - 1, -1, -1):
        col = rows[:, i]
        is_zero = col == 0
        out[:, i + 1] = np.where(is_zero, next_zero - i, col)
        next_zero = np.where(is_zero, i, next_zero)
    out[:, 0] = next_zero + 1
    out[:, -1] = 0
    return out


def _encode_many(spec: _Spec, wheel, seq, t_us, values: dict) -> bytes:
    ints = {"wheel": np.asarray(wheel), "seq": np.asarray(seq), "t_us": np.asarray(t_us)}
    for name, arr in ints.items():
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{name} must be integers, got dtype {arr.dtype}")
    floats = {name: np.asarray(v, dtype=np.float64) for name, v in values.items()}
    try:
        arrays = np.broadcast_arrays(*ints.values(), *floats.values())
    except ValueError as exc:
        raise ValueError(f"arguments do not broadcast together: {exc}") from None
    if arrays[0].ndim > 1:
        raise ValueError(f"arguments must be scalars or 1-D arrays, got shape {arrays[0].shape}")
    wheel_a, seq_a, t_a, *float_arrs = (np.ravel(a) for a in arrays)
    n = wheel_a.size
    if n == 0:
        return b""
    if wheel_a.min() < 0 or wheel_a.max() >= N_WHEELS:
        raise ValueError(f"wheel indices must be 0..{N_WHEELS - 1}")
    if t_a.min() < 0:
        raise ValueError("t_us must be >= 0 microseconds")
    rec = np.zeros(n, spec.wire_dtype)
    rec["kind"] = spec.kind
    rec["wheel"] = wheel_a
    rec["seq"] = seq_a & 0xFFFF  # modulo 2**16, also for negative integers
    rec["t_us"] = t_a
    for name, arr in zip(floats, float_arrs):
        with np.errstate(over="ignore", invalid="ignore"):
            as32 = arr.astype(np.float32)
        if not np.isfinite(as32).all():
            raise ValueError(f"{name} must be finite float32 values")
        rec[name] = as32
    raw = rec.view(np.uint8).reshape(n, spec.wire_dtype.itemsize)
    rec["crc"] = _crc16_rows(raw[:, : spec.payload_len])
    return _cobs_encode_rows(raw).tobytes()


def encode_imu_samples(wheel, seq, t_us, az, theta) -> bytes:
    """Encode many IMU_SAMPLE frames at once (vectorised; same bytes as a loop
    over :func:`encode_imu_sample`).

    Arguments are scalars or 1-D arrays broadcast together: ``wheel`` (0..5),
    ``seq`` (integers, reduced modulo 2**16), ``t_us`` [us, integers >= 0],
    ``az`` [m/s^2], ``theta`` [rad].
    :raises ValueError: as :func:`encode_imu_sample`.
    """
    return _encode_many(_SPECS[FRAME_IMU_SAMPLE], wheel, seq, t_us, {"az": az, "theta": theta})


def encode_slip_references(wheel, seq, t_us, slip) -> bytes:
    """Encode many SLIP_REFERENCE frames at once (vectorised).

    Arguments as :func:`encode_imu_samples`; ``slip`` [-].
    """
    return _encode_many(_SPECS[FRAME_SLIP_REFERENCE], wheel, seq, t_us, {"slip": slip})


# ---------------------------------------------------------------------------
# Per-frame decoding (protocol object)
# ---------------------------------------------------------------------------

# encoded length -> (type byte, unpack of the record fields, payload length,
# record class, number of leading non-float record fields)
_DECODE_TABLE = {
    spec.encoded_len: (
        spec.kind,
        struct.Struct("<x" + spec.payload.format[2:]).unpack_from,  # skip the type byte
        spec.payload_len,
        spec.record,
        3,  # wheel, seq, t_us; the rest are float32 values
    )
    for spec in _SPECS.values()
}
_cobs_decode = cobs.decode
_CobsDecodeError = cobs.DecodeError
_crc_hqx = binascii.crc_hqx
_isfinite = math.isfinite
_tuple_new = tuple.__new__


def _empty_counters() -> dict:
    return {
        "frames_ok": 0,
        "crc_errors": 0,
        "malformed": 0,
        "nonfinite": 0,
        "seq_gaps": 0,
        "seq_backwards": 0,
        "bytes_in": 0,
        "bytes_discarded": 0,
        "pending_bytes": 0,
        "seq_gaps_by_wheel": {w: 0 for w in range(N_WHEELS)},
    }


class FrameDecoder:
    """Incremental decoder of the serial byte stream (a protocol object).

    Feed it bytes as they arrive, in chunks of any size; :meth:`feed` returns
    the frames completed by that chunk, in stream order.  A frame that fails
    any check is never returned; the decoder resynchronises on the next zero
    byte.  Memory is bounded: at most :data:`MAX_SEGMENT_LEN` bytes are kept.
    Not thread-safe: feed it from one thread (the port reader).

    Counters (see :meth:`counters`): ``frames_ok`` delivered frames;
    ``crc_errors``; ``malformed`` (wrong length, bad COBS, unknown type, wheel
    out of range, over-long segment); ``nonfinite`` intact frames carrying a
    NaN/inf, not delivered; ``seq_gaps`` frames missed according to the
    sequence counters (also ``seq_gaps_by_wheel``); ``seq_backwards``
    duplicates, reorderings or device restarts; ``bytes_in`` bytes fed;
    ``bytes_discarded`` bytes of rejected (CRC/malformed) segments;
    ``pending_bytes`` bytes of an incomplete frame held in the buffer.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False
        self._last_seq: dict[int, int] = {}
        self._c = _empty_counters()

    def feed(self, data: bytes) -> list[Frame]:
        """Consume a chunk of the stream; return the frames it completes."""
        out: list[Frame] = []
        if not data:
            return out
        self._c["bytes_in"] += len(data)
        parts = bytes(data).split(b"\x00")
        tail = parts.pop()  # after the last delimiter: incomplete
        if parts:  # parts[0] completes the buffered segment
            if self._discarding:
                self._c["bytes_discarded"] += len(parts[0])
                self._discarding = False
                parts[0] = b""
            elif self._buf:
                parts[0] = bytes(self._buf) + parts[0]
                self._buf.clear()
            self._segments(parts, out)
        self._accumulate(tail)
        return out

    def _accumulate(self, piece: bytes) -> None:
        if not piece:
            return
        if self._discarding:
            self._c["bytes_discarded"] += len(piece)
        elif len(self._buf) + len(piece) > MAX_SEGMENT_LEN:
            self._c["malformed"] += 1
            self._c["bytes_discarded"] += len(self._buf) + len(piece)
            self._buf.clear()
            self._discarding = True
        else:
            self._buf += piece

    def _segments(self, segments: list, out: list) -> None:
        """Classify complete segments (the checks of the module docstring, in
        that order, as in :func:`decode_capture`) and deliver the good frames."""
        table = _DECODE_TABLE
        last_seq = self._last_seq
        by_wheel = self._c["seq_gaps_by_wheel"]
        append = out.append
        crc_errors = malformed = nonfinite = ok = gaps = backwards = discarded = 0
        for segment in segments:
            n_seg = len(segment)
            if not n_seg:
                continue  # empty frames are idle fill
            entry = table.get(n_seg)
            if entry is None:
                malformed += 1
                discarded += n_seg
                continue
            kind, unpack_from, n, record_cls, n_int = entry
            try:
                decoded = _cobs_decode(segment)
            except _CobsDecodeError:
                malformed += 1
                discarded += n_seg
                continue
            if _crc_hqx(decoded[:n], 0xFFFF) != decoded[n] | (decoded[n + 1] << 8):
                crc_errors += 1
                discarded += n_seg
                continue
            wheel = decoded[1]
            if decoded[0] != kind or wheel >= N_WHEELS:
                malformed += 1
                discarded += n_seg
                continue
            fields = unpack_from(decoded)
            seq = fields[1]
            key = (kind, wheel)
            last = last_seq.get(key)
            last_seq[key] = seq
            if last is not None and seq != last + 1:
                gap = (seq - last - 1) % SEQ_MODULUS
                if gap >= _SEQ_HALF:
                    backwards += 1
                elif gap:
                    gaps += gap
                    by_wheel[wheel] += gap
            for value in fields[n_int:]:
                if not _isfinite(value):
                    nonfinite += 1
                    break
            else:
                ok += 1
                append(_tuple_new(record_cls, fields))
        c = self._c
        c["frames_ok"] += ok
        c["crc_errors"] += crc_errors
        c["malformed"] += malformed
        c["nonfinite"] += nonfinite
        c["seq_gaps"] += gaps
        c["seq_backwards"] += backwards
        c["bytes_discarded"] += discarded

    def counters(self) -> dict:
        """Snapshot of the counters (a new dict, safe to print or keep)."""
        snap = dict(self._c)
        snap["seq_gaps_by_wheel"] = dict(self._c["seq_gaps_by_wheel"])
        snap["pending_bytes"] = 0 if self._discarding else len(self._buf)
        return snap

    def reset(self) -> None:
        """Forget buffered bytes and sequence history (e.g. after reopening a
        port); counters are kept."""
        self._buf.clear()
        self._discarding = False
        self._last_seq.clear()


class FrameProtocol(serial.threaded.Protocol):
    """``serial.threaded`` protocol: port bytes -> :class:`FrameDecoder` -> frames.

    Use with ``serial.threaded.ReaderThread(port, lambda: FrameProtocol(cb))``;
    ``cb(frame)`` is called in the reader thread for every delivered frame
    (or override :meth:`handle_frame`).  ``decoder.counters()`` gives the counters.
    """

    def __init__(self, on_frame: Callable[[Frame], None] | None = None) -> None:
        self.decoder = FrameDecoder()
        self.on_frame = on_frame
        self.transport = None

    def connection_made(self, transport) -> None:
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        for frame in self.decoder.feed(data):
            self.handle_frame(frame)

    def connection_lost(self, exc) -> None:
        self.transport = None
        super().connection_lost(exc)

    def handle_frame(self, frame: Frame) -> None:
        """Called for each delivered frame; calls ``on_frame`` by default."""
        if self.on_frame is not None:
            self.on_frame(frame)


def frames_to_array(frames) -> np.ndarray:
    """Frames (as returned by :meth:`FrameDecoder.feed`) -> ``CAPTURE_DTYPE`` array."""
    out = np.zeros(len(frames), CAPTURE_DTYPE)
    out["az"] = out["theta"] = out["slip"] = np.nan
    for i, f in enumerate(frames):
        row = out[i]
        row["kind"], row["wheel"], row["seq"], row["t_us"] = f.kind, f.wheel, f.seq, f.t_us
        if f.kind == FRAME_IMU_SAMPLE:
            row["az"], row["theta"] = f.az, f.theta
        else:
            row["slip"] = f.slip
    return out


# ---------------------------------------------------------------------------
# Vectorised decoding of a whole capture
# ---------------------------------------------------------------------------


def _cobs_decode_rows(enc: np.ndarray):
    """Vectorised COBS decoding of (m, L) uint8 rows without zeros, L < 255.

    Returns (decoded (m, L-1) uint8, valid bool[m]).  A row is valid exactly
    when the chain of code bytes lands on L, which is when ``cobs.decode``
    accepts it.
    """
    m, width = enc.shape
    enc = np.ascontiguousarray(enc)
    dec = enc[:, 1:].copy()  # a copy even when enc[:, 1:] is contiguous
    flat_enc = enc.reshape(-1)
    flat_dec = dec.reshape(-1)
    pos = enc[:, 0].astype(np.int64)  # position of the next code byte
    rows = np.flatnonzero(pos < width)
    base = rows * width
    for _ in range(width):  # every step advances by >= 1 (codes are non-zero)
        if not rows.size:
            break
        p = pos[rows]
        flat_dec[rows * (width - 1) + p - 1] = 0
        p = p + flat_enc[base + p]
        pos[rows] = p
        keep = p < width
        rows = rows[keep]
        base = base[keep]
    return dec, pos == width


def decode_capture(data: bytes) -> tuple[np.ndarray, dict]:
    """Decode a whole captured byte stream at once (vectorised).

    :param data: the raw bytes (any bytes-like object), as read from the port;
        the capture may start and end anywhere in a frame.
    :returns: ``(frames, counters)``: a ``CAPTURE_DTYPE`` array of the delivered
        frames in stream order and a counters dict, both equal to what a fresh
        :class:`FrameDecoder` fed the same bytes (in any chunking) delivers and
        reports.  Bytes after the last zero are an incomplete frame
        (``pending_bytes``), as for the decoder.
    """
    buf = np.frombuffer(data, np.uint8)
    counters = _empty_counters()
    counters["bytes_in"] = int(buf.size)
    zeros = np.flatnonzero(buf == 0)
    after_last_zero = int(zeros[-1]) + 1 if zeros.size else 0
    tail = buf.size - after_last_zero
    if tail > MAX_SEGMENT_LEN:
        counters["malformed"] += 1
        counters["bytes_discarded"] += tail
    else:
        counters["pending_bytes"] = tail
    starts = np.empty(zeros.size, np.intp)
    if zeros.size:
        starts[0] = 0
        starts[1:] = zeros[:-1] + 1
    lengths = zeros - starts
    n_segments = int(np.count_nonzero(lengths))  # empty segments are ignored
    segment_bytes = after_last_zero - zeros.size

    # Per frame type: the intact frames (delivered or non-finite).
    parts = []  # (spec, segment index, wire fields, finite mask)
    for enc_len, spec in _SPEC_BY_ENCODED_LEN.items():
        idx = np.flatnonzero(lengths == enc_len)
        if not idx.size:
            continue
        windows = np.lib.stride_tricks.sliding_window_view(buf, enc_len)
        dec, valid = _cobs_decode_rows(windows[starts[idx]])
        if not valid.all():
            idx, dec = idx[valid], dec[valid]
        n = spec.payload_len
        crc_rx = dec[:, n].astype(np.uint16) | (dec[:, n + 1].astype(np.uint16) << 8)
        crc_ok = _crc16_rows(dec[:, :n]) == crc_rx
        counters["crc_errors"] += int(crc_ok.size - np.count_nonzero(crc_ok))
        fields = dec.view(spec.wire_dtype).reshape(-1)
        good = crc_ok & (fields["kind"] == spec.kind) & (fields["wheel"] < N_WHEELS)
        if not good.all():
            idx, fields = idx[good], fields[good]
        finite = np.ones(idx.size, bool)
        for name in spec.values:
            finite &= np.isfinite(fields[name])
        parts.append((spec, idx, fields, finite))

    n_intact = sum(p[1].size for p in parts)
    n_ok = sum(int(np.count_nonzero(p[3])) for p in parts)
    counters["frames_ok"] = n_ok
    counters["nonfinite"] = n_intact - n_ok
    counters["malformed"] += n_segments - n_intact - counters["crc_errors"]
    counters["bytes_discarded"] += segment_bytes - sum(
        p[0].encoded_len * p[1].size for p in parts)

    # Sequence counters of the intact frames, per stream, in stream order.
    if parts:
        idx_all = np.concatenate([p[1] for p in parts])
        keys = np.concatenate([(p[2]["kind"].astype(np.uint16) << 8) | p[2]["wheel"]
                               for p in parts])
        seqs = np.concatenate([p[2]["seq"] for p in parts])
        if len(parts) > 1:
            order = np.argsort(idx_all)
            keys, seqs = keys[order], seqs[order]
        order = np.argsort(keys, kind="stable")  # radix sort on uint16
        keys, seqs = keys[order], seqs[order].astype(np.int64)
        same = keys[1:] == keys[:-1]
        gap = (seqs[1:] - seqs[:-1] - 1) % SEQ_MODULUS
        forward = same & (gap < _SEQ_HALF)
        counters["seq_backwards"] = int(np.count_nonzero(same & (gap >= _SEQ_HALF)))
        counters["seq_gaps"] = int(gap[forward].sum())
        wheels = keys[1:][forward] & 0xFF
        per_wheel = np.bincount(wheels, weights=gap[forward], minlength=N_WHEELS)
        counters["seq_gaps_by_wheel"] = {w: int(per_wheel[w]) for w in range(N_WHEELS)}

    # Delivered frames, merged back into stream order.
    out = np.empty(n_ok, CAPTURE_DTYPE)
    for name in ("az", "theta", "slip"):
        out[name] = np.nan
    oks = [(p[0], p[1][p[3]], p[2][p[3]]) for p in parts]
    if len(oks) == 1:
        positions = [slice(None)]
    else:
        all_idx = np.concatenate([o[1] for o in oks]) if oks else np.empty(0, np.intp)
        rank = np.empty(all_idx.size, np.intp)
        rank[np.argsort(all_idx)] = np.arange(all_idx.size)
        bounds = np.cumsum([0] + [o[1].size for o in oks])
        positions = [rank[bounds[i]:bounds[i + 1]] for i in range(len(oks))]
    for (spec, _, fields), pos in zip(oks, positions):
        for name in ("kind", "wheel", "seq", "t_us") + spec.values:
            out[name][pos] = fields[name]
    return out, counters
