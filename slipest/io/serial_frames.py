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
5. a float field is NaN, infinite or beyond +-:data:`FIELD_LIMIT` (1e7: no
   acceleration, angle or slip reaches it, and a float32 there holds no
   angle to within a radian; a device's corrupted value) -> ``nonfinite``
   (the frame was received intact, so it still advances the sequence
   counter, but it is not delivered: the receiver counts it lost);
6. otherwise the frame is delivered (``frames_ok``).

(CRC-16 detects every burst of up to 16 bits and every odd number of bit
errors; other corruptions of a correctly framed frame pass it with a
probability of about 2**-16.)

:class:`FrameProtocol` plugs the decoder into ``serial.threaded.ReaderThread``.
"""

from __future__ import annotations

import binascii
import math
import operator
import struct
from typing import Callable, NamedTuple, Union

import serial.threaded
from cobs import cobs

__all__ = [
    "FRAME_IMU_SAMPLE",
    "FRAME_SLIP_REFERENCE",
    "N_WHEELS",
    "SEQ_MODULUS",
    "MAX_SEGMENT_LEN",
    "FIELD_LIMIT",
    "ImuSample",
    "SlipReference",
    "Frame",
    "crc16",
    "encode_frame",
    "encode_imu_sample",
    "encode_slip_reference",
    "FrameDecoder",
    "FrameProtocol",
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
    """One hub IMU sample of one wheel-leg, as sent by the device.

    ``kind`` (class attribute) is the frame type byte :data:`FRAME_IMU_SAMPLE`."""

    wheel: int  #: wheel-leg index 0..5
    seq: int  #: 16-bit sequence counter
    t_us: int  #: device timestamp [us]
    az: float  #: vertical specific force [m/s^2] (float32 precision)
    theta: float  #: wheel-leg angle [rad], wrapped by the device
    kind = FRAME_IMU_SAMPLE

    @property
    def t(self) -> float:
        """Device timestamp [s]."""
        return self.t_us * 1e-6


class SlipReference(NamedTuple):
    """One reference slip value of one wheel-leg, as sent by a testbed.

    ``kind`` (class attribute) is the frame type byte :data:`FRAME_SLIP_REFERENCE`."""

    wheel: int  #: wheel-leg index 0..5
    seq: int  #: 16-bit sequence counter
    t_us: int  #: device timestamp [us]
    slip: float  #: reference slip [-] (float32 precision)
    kind = FRAME_SLIP_REFERENCE

    @property
    def t(self) -> float:
        """Device timestamp [s]."""
        return self.t_us * 1e-6


Frame = Union[ImuSample, SlipReference]


#: Largest magnitude of a frame's float field delivered (m/s^2, rad, -): beyond it the value is corrupted.
FIELD_LIMIT = 1e7


class _Spec(NamedTuple):
    kind: int
    payload: struct.Struct  # full payload layout, type byte first
    record: type
    values: tuple[str, ...]  # float32 fields, in payload order

    @property
    def payload_len(self) -> int:
        return self.payload.size

    @property
    def encoded_len(self) -> int:
        """COBS-encoded length without the delimiter (payload + 2 CRC + 1)."""
        return self.payload.size + 3


_IMU = _Spec(FRAME_IMU_SAMPLE, struct.Struct("<BBHQff"), ImuSample, ("az", "theta"))
_REF = _Spec(FRAME_SLIP_REFERENCE, struct.Struct("<BBHQf"), SlipReference, ("slip",))
_SPECS = (_IMU, _REF)
for _s in _SPECS:  # pragma: no cover - guards future edits
    if _s.encoded_len > MAX_SEGMENT_LEN or _s.record._fields != ("wheel", "seq", "t_us") + _s.values:
        raise RuntimeError(f"serial frame type {_s.kind:#04x}: inconsistent layout")
if len({s.encoded_len for s in _SPECS}) != len(_SPECS):  # pragma: no cover
    raise RuntimeError("two serial frame types have the same encoded length")

_CRC = struct.Struct("<H")
_F32 = struct.Struct("<f")
_crc_hqx = binascii.crc_hqx
_isfinite = math.isfinite

# ---------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``binascii.crc_hqx(data, 0xFFFF)``)."""
    return _crc_hqx(data, 0xFFFF)


def encode_frame(payload: bytes) -> bytes:
    """Wrap a raw payload (type byte first): append CRC, COBS-encode, add 0x00.

    Low-level; use :func:`encode_imu_sample` and friends for known frame types.
    """
    payload = bytes(payload)
    return cobs.encode(payload + _CRC.pack(_crc_hqx(payload, 0xFFFF))) + b"\x00"


def _why_invalid(spec: _Spec, wheel, seq, t_us, values) -> str:
    """What is wrong with the fields of a frame that failed to pack."""
    for name, value in (("wheel", wheel), ("seq", seq), ("t_us", t_us)):
        try:
            operator.index(value)
        except TypeError:
            return f"{name} must be an integer, got {value!r}"
    if not 0 <= wheel < N_WHEELS:
        return f"wheel index must be 0..{N_WHEELS - 1}, got {wheel!r}"
    if not 0 <= t_us < 1 << 64:
        return f"t_us must be 0 <= t_us < 2**64 microseconds, got {t_us!r}"
    for name, value in zip(spec.values, values):
        try:
            _F32.pack(value)
            finite = _isfinite(value) and -FIELD_LIMIT <= value <= FIELD_LIMIT
        except (struct.error, OverflowError, TypeError):
            finite = False
        if not finite:
            return f"{name} must be a finite float32 value within +-{FIELD_LIMIT:g}, got {value!r}"
    return f"cannot pack the fields {(wheel, seq, t_us, *values)!r}"  # pragma: no cover


def _encode(spec: _Spec, wheel, seq, t_us, *values) -> bytes:
    """One frame of type ``spec`` (delimiter included), or ValueError naming the bad field."""
    try:
        if 0 <= wheel < N_WHEELS:
            payload = spec.payload.pack(spec.kind, wheel, seq % SEQ_MODULUS, t_us, *values)
            for value in values:
                if not (_isfinite(value) and -FIELD_LIMIT <= value <= FIELD_LIMIT):
                    break
            else:
                return encode_frame(payload)
    except (struct.error, OverflowError, TypeError):
        pass
    raise ValueError(_why_invalid(spec, wheel, seq, t_us, values))


def encode_imu_sample(wheel: int, seq: int, t_us: int, az: float, theta: float) -> bytes:
    """Encode one IMU_SAMPLE frame (delimiter included): 24 bytes.

    :param wheel: wheel-leg index 0..5.
    :param seq: sequence counter (an integer); reduced modulo 2**16.
    :param t_us: device timestamp [us], 0 <= t_us < 2**64.
    :param az: vertical specific force [m/s^2] (sent as float32).
    :param theta: wheel-leg angle [rad] (sent as float32, as the device wraps it).
    :raises ValueError: naming the field: a non-integer index, wheel out of
        range, timestamp out of range, a value that is not a finite float32.
    """
    return _encode(_IMU, wheel, seq, t_us, az, theta)


def encode_slip_reference(wheel: int, seq: int, t_us: int, slip: float) -> bytes:
    """Encode one SLIP_REFERENCE frame (delimiter included): 20 bytes.

    :param wheel: wheel-leg index 0..5.
    :param seq: sequence counter (an integer); reduced modulo 2**16.
    :param t_us: device timestamp [us], 0 <= t_us < 2**64.
    :param slip: reference slip [-] (sent as float32).
    :raises ValueError: as :func:`encode_imu_sample`.
    """
    return _encode(_REF, wheel, seq, t_us, slip)


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
    for spec in _SPECS
}
_cobs_decode = cobs.decode
_CobsDecodeError = cobs.DecodeError
_tuple_new = tuple.__new__


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
    NaN/inf or a value beyond :data:`FIELD_LIMIT`, not delivered; ``seq_gaps`` frames missed according to the
    sequence counters (also ``seq_gaps_by_wheel``); ``seq_backwards``
    duplicates, reorderings or device restarts; ``bytes_in`` bytes fed;
    ``bytes_discarded`` bytes of rejected (CRC/malformed) segments;
    ``pending_bytes`` bytes of an incomplete frame held in the buffer.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._discarding = False
        self._last_seq: dict[int, int] = {}
        self._c = {
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
        that order) and deliver the good frames."""
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
                if not (_isfinite(value) and -FIELD_LIMIT <= value <= FIELD_LIMIT):
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
