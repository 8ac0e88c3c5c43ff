"""Tests of the serial wire format (slipest.io.serial_frames)."""

from __future__ import annotations

import binascii
import math
import os
import struct
import threading
import tty

import numpy as np
import pytest
import serial
import serial.threaded
from cobs import cobs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slipest.io import serial_frames as sf

F32 = st.floats(-sf.FIELD_LIMIT, sf.FIELD_LIMIT, width=32)  # the values a frame may carry


def f32(x: float) -> float:
    return float(np.float32(x))


def feed_in_chunks(data: bytes, cuts) -> tuple[list, dict]:
    dec = sf.FrameDecoder()
    out = []
    prev = 0
    for cut in sorted(set(cuts)) + [len(data)]:
        out += dec.feed(data[prev:cut])
        prev = cut
    return out, dec.counters()


def imu_frames(wheel, seq, t_us, az, theta) -> bytes:
    """IMU_SAMPLE frames of the columns (scalars are repeated), concatenated."""
    cols = np.broadcast_arrays(wheel, seq, t_us, az, theta)
    return b"".join(sf.encode_imu_sample(*row) for row in zip(*(c.tolist() for c in cols)))


def assert_chunking_does_not_matter(data: bytes, frames: list, counters: dict) -> None:
    """One chunk, and one byte at a time, deliver the same frames and counters."""
    assert feed_in_chunks(data, []) == (frames, counters)
    assert feed_in_chunks(data, range(len(data))) == (frames, counters)


# --------------------------------------------------------------------------- CRC


def test_crc16_is_ccitt_false():
    assert sf.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check value


# --------------------------------------------------------------------------- layout


def test_imu_sample_byte_layout():
    frame = sf.encode_imu_sample(wheel=3, seq=0x1234, t_us=0x0102030405060708, az=9.81, theta=-1.5)
    assert len(frame) == 24
    assert frame[-1] == 0 and 0 not in frame[:-1]
    raw = cobs.decode(frame[:-1])
    assert len(raw) == 22
    payload, crc = raw[:20], raw[20:]
    assert struct.unpack("<BBHQff", payload) == (0x01, 3, 0x1234, 0x0102030405060708, f32(9.81), -1.5)
    assert crc == struct.pack("<H", binascii.crc_hqx(payload, 0xFFFF))


def test_slip_reference_byte_layout():
    frame = sf.encode_slip_reference(wheel=5, seq=65535, t_us=42, slip=0.25)
    assert len(frame) == 20
    assert frame[-1] == 0 and 0 not in frame[:-1]
    raw = cobs.decode(frame[:-1])
    assert struct.unpack("<BBHQf", raw[:16]) == (0x02, 5, 65535, 42, 0.25)
    assert raw[16:] == struct.pack("<H", binascii.crc_hqx(raw[:16], 0xFFFF))


def test_seq_is_reduced_modulo_2_16():
    a = sf.encode_imu_sample(0, 65536 + 7, 1, 0.0, 0.0)
    b = sf.encode_imu_sample(0, 7, 1, 0.0, 0.0)
    assert a == b
    assert sf.encode_imu_sample(0, -1, 1, 0.0, 0.0) == sf.encode_imu_sample(0, 65535, 1, 0.0, 0.0)
    assert sf.encode_slip_reference(0, 65536 * 3 + 2, 1, 0.5) == sf.encode_slip_reference(0, 2, 1, 0.5)


# --------------------------------------------------------------------------- round trips


def test_round_trip_imu_and_reference():
    data = (sf.encode_imu_sample(0, 1, 1_000_000, 9.81, 3.14159)
            + sf.encode_slip_reference(2, 9, 2_000_000, 0.125)
            + sf.encode_imu_sample(5, 2, 2**64 - 1, -157.0, -math.pi))
    frames = sf.FrameDecoder().feed(data)
    assert frames == [
        sf.ImuSample(0, 1, 1_000_000, f32(9.81), f32(3.14159)),
        sf.SlipReference(2, 9, 2_000_000, 0.125),
        sf.ImuSample(5, 2, 2**64 - 1, -157.0, f32(-math.pi)),
    ]
    assert frames[0].t == pytest.approx(1.0)
    assert frames[0].kind == sf.FRAME_IMU_SAMPLE and frames[1].kind == sf.FRAME_SLIP_REFERENCE


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 2**16 - 1),
                          st.integers(0, 2**64 - 1), F32, F32), min_size=0, max_size=40))
def test_imu_samples_round_trip(rows):
    data = b"".join(sf.encode_imu_sample(*r) for r in rows)
    assert len(data) == 24 * len(rows)
    frames = sf.FrameDecoder().feed(data)
    assert [tuple(f) for f in frames] == [r for r in rows]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 2**16 - 1),
                          st.integers(0, 2**64 - 1), F32), min_size=0, max_size=40))
def test_slip_references_round_trip(rows):
    data = b"".join(sf.encode_slip_reference(*r) for r in rows)
    assert len(data) == 20 * len(rows)
    assert sf.FrameDecoder().feed(data) == [sf.SlipReference(*r) for r in rows]


def test_encoders_take_numpy_scalars():
    assert (sf.encode_imu_sample(np.uint8(4), np.int64(70000), np.uint64(10), np.float32(0.5), np.float64(1.0))
            == sf.encode_imu_sample(4, 70000 - 65536, 10, 0.5, 1.0))
    assert sf.encode_slip_reference(np.int64(4), np.int64(2), np.int64(10), np.float64(0.5)) == \
        sf.encode_slip_reference(4, 2, 10, 0.5)


@pytest.mark.parametrize("kwargs, match", [
    (dict(wheel=6), "wheel"),
    (dict(wheel=-1), "wheel"),
    (dict(t_us=-1), "t_us"),
    (dict(t_us=2**64), "t_us"),
    (dict(az=float("nan")), "az"),
    (dict(theta=float("inf")), "theta"),
    (dict(az=1e39), "az"),  # overflows float32
])
def test_encoder_rejects_bad_input(kwargs, match):
    args = dict(wheel=0, seq=0, t_us=0, az=0.0, theta=0.0) | kwargs
    with pytest.raises(ValueError, match=match):
        sf.encode_imu_sample(**args)
    # the same checks on SLIP_REFERENCE, its float field being slip
    as_ref = {"az": "slip", "theta": "slip"}
    ref = dict(wheel=0, seq=0, t_us=0, slip=0.0) | {as_ref.get(k, k): v for k, v in kwargs.items()}
    with pytest.raises(ValueError, match=as_ref.get(match, match)):
        sf.encode_slip_reference(**ref)


@pytest.mark.parametrize("field", ["wheel", "seq", "t_us"])
@pytest.mark.parametrize("value", [0.5, "1", None])
def test_encoder_rejects_non_integer_header_fields(field, value):
    args = dict(wheel=0, seq=0, t_us=0, az=0.0, theta=0.0) | {field: value}
    with pytest.raises(ValueError, match=field):
        sf.encode_imu_sample(**args)


# --------------------------------------------------------------------------- decoder


def test_byte_by_byte_feeding_equals_one_chunk():
    data = imu_frames(np.arange(30) % 6, np.arange(30), np.arange(30) * 1000, 1.0, 2.0)
    whole = sf.FrameDecoder().feed(data)
    dec = sf.FrameDecoder()
    one_by_one = [f for i in range(len(data)) for f in dec.feed(data[i:i + 1])]
    assert len(whole) == 30
    assert one_by_one == whole


def test_resync_after_garbage():
    frames = b"".join(sf.encode_imu_sample(1, i, i, 1.0, 0.5) for i in range(5))
    garbage = bytes(range(1, 200))  # no zero byte
    dec = sf.FrameDecoder()
    out = dec.feed(garbage + frames)
    # The garbage and the first frame form one segment: frame 0 is lost, the
    # decoder resynchronises on its delimiter and frames 1..4 come through.
    assert [f.seq for f in out] == [1, 2, 3, 4]
    c = dec.counters()
    assert c["malformed"] == 1 and c["bytes_discarded"] == len(garbage) + 23
    # A sender that emits a lone 0x00 first loses nothing.
    dec = sf.FrameDecoder()
    assert [f.seq for f in dec.feed(garbage + b"\x00" + frames)] == [0, 1, 2, 3, 4]
    assert dec.counters()["malformed"] == 1
    assert dec.counters()["bytes_discarded"] == len(garbage)


def test_garbage_with_zeros_between_frames():
    a = sf.encode_imu_sample(0, 0, 0, 1.0, 1.0)
    b = sf.encode_imu_sample(0, 1, 1, 1.0, 1.0)
    junk = (b"\x05\x00\x00\xff\x13\x00" + bytes(23)
            + b"\x30" + b"\x01" * 22 + b"\x00"  # IMU length, COBS code overshoots
            + b"\x01" * 23 + b"\x00")  # valid COBS of 22 zero bytes: CRC fails
    out, c = feed_in_chunks(a + junk + b, [3, 30, 31])
    assert [f.seq for f in out] == [0, 1]
    assert c["malformed"] == 3  # b"\x05", b"\xff\x13", bad COBS
    assert c["crc_errors"] == 1
    assert c["frames_ok"] == 2 and c["seq_gaps"] == 0
    assert_chunking_does_not_matter(a + junk + b, out, c)


def test_buffer_is_bounded_on_endless_stream_without_delimiter():
    dec = sf.FrameDecoder()
    chunk = bytes([0x55]) * 4096
    for _ in range(2_000):  # 8 MB without a zero byte
        assert dec.feed(chunk) == []
        assert len(dec._buf) <= sf.MAX_SEGMENT_LEN
    c = dec.counters()
    assert c["malformed"] == 1
    assert c["bytes_discarded"] == 2_000 * 4096
    assert c["pending_bytes"] == 0
    # The next delimiter ends the junk; the following frame is decoded.
    out = dec.feed(b"\x55\x00" + sf.encode_slip_reference(0, 0, 0, 0.5))
    assert out == [sf.SlipReference(0, 0, 0, 0.5)]
    c = dec.counters()
    assert c["malformed"] == 1 and c["bytes_discarded"] == 2_000 * 4096 + 1


def test_sequence_gaps_with_wrap_and_duplicates():
    seqs = [65533, 65534, 0, 1, 4, 4, 5]  # 65535 missing, 2 and 3 missing, 4 duplicated
    data = b"".join(sf.encode_imu_sample(2, s, i, 0.0, 0.0) for i, s in enumerate(seqs))
    data += b"".join(sf.encode_imu_sample(4, s, 0, 0.0, 0.0) for s in (10, 20))
    # A second frame type of wheel 2 has its own counter: no gap here.
    data += b"".join(sf.encode_slip_reference(2, s, 0, 0.1) for s in (100, 101))
    out, c = feed_in_chunks(data, [])
    assert len(out) == 11
    assert c["seq_gaps"] == 3 + 9
    assert c["seq_gaps_by_wheel"] == {0: 0, 1: 0, 2: 3, 3: 0, 4: 9, 5: 0}
    assert c["seq_backwards"] == 1
    assert_chunking_does_not_matter(data, out, c)


def raw_frame(fmt: str, *fields) -> bytes:
    return sf.encode_frame(struct.pack(fmt, *fields))


def test_intact_but_invalid_frames_are_counted_not_delivered():
    good = sf.encode_imu_sample(1, 0, 0, 1.0, 1.0)
    cases = [
        raw_frame("<BBHQff", 0x7F, 1, 1, 0, 1.0, 1.0),        # unknown type, IMU length
        raw_frame("<BBHQff", 0x02, 1, 1, 0, 1.0, 1.0),        # SLIP_REFERENCE type, IMU length
        raw_frame("<BBHQff", 0x01, 6, 1, 0, 1.0, 1.0),        # wheel out of range
        raw_frame("<BBHQffB", 0x01, 1, 1, 0, 1.0, 1.0, 0),    # one byte too long
        raw_frame("<B", 0x01),                                # far too short
        sf.encode_frame(b""),                                 # CRC only
    ]
    data = good + b"".join(cases)
    out, c = feed_in_chunks(data, [])
    assert out == [sf.ImuSample(1, 0, 0, 1.0, 1.0)]
    assert c["malformed"] == len(cases) and c["crc_errors"] == 0
    assert_chunking_does_not_matter(data, out, c)


def test_non_finite_values_are_not_delivered_but_advance_the_counter():
    """NaN, inf and values beyond FIELD_LIMIT (a float32's largest, an angle of 1e30 rad: a device's corrupted
    value) are not delivered; the encoder refuses them."""
    data = (sf.encode_imu_sample(0, 0, 0, 1.0, 1.0)
            + raw_frame("<BBHQff", 0x01, 0, 1, 1, float("nan"), 1.0)
            + raw_frame("<BBHQf", 0x02, 0, 7, 1, float("-inf"))
            + raw_frame("<BBHQff", 0x01, 0, 2, 2, 9.81, 1e30)
            + raw_frame("<BBHQff", 0x01, 0, 3, 3, -3.4028234663852886e38, 1.0)
            + sf.encode_imu_sample(0, 4, 4, 1.0, sf.FIELD_LIMIT))
    out, c = feed_in_chunks(data, [5, 40])
    assert [f.seq for f in out] == [0, 4]
    assert c["nonfinite"] == 4 and c["seq_gaps"] == 0 and c["frames_ok"] == 2
    assert_chunking_does_not_matter(data, out, c)
    with pytest.raises(ValueError, match="theta must be a finite float32 value within"):
        sf.encode_imu_sample(0, 5, 5, 9.81, 2 * sf.FIELD_LIMIT)


def test_crc_error_is_counted():
    frame = bytearray(sf.encode_imu_sample(0, 0, 123, 1.0, 2.0))
    frame[15] ^= 0x01  # a data byte (not a COBS code byte) -> CRC mismatch
    out, c = feed_in_chunks(bytes(frame), [])
    assert out == [] and c["crc_errors"] == 1 and c["bytes_discarded"] == 23
    assert_chunking_does_not_matter(bytes(frame), out, c)


def test_counters_snapshot_is_a_copy_and_reset_keeps_counts():
    dec = sf.FrameDecoder()
    dec.feed(sf.encode_imu_sample(0, 0, 0, 1.0, 1.0) + b"\x01\x02")
    snap = dec.counters()
    snap["frames_ok"] = 99
    snap["seq_gaps_by_wheel"][0] = 99
    assert dec.counters()["frames_ok"] == 1
    assert dec.counters()["seq_gaps_by_wheel"][0] == 0
    assert dec.counters()["pending_bytes"] == 2
    dec.reset()
    assert dec.counters()["pending_bytes"] == 0 and dec.counters()["frames_ok"] == 1
    # after reset, no gap is reported against the old counter value
    dec.feed(sf.encode_imu_sample(0, 500, 0, 1.0, 1.0))
    assert dec.counters()["seq_gaps"] == 0


@pytest.mark.parametrize("data, pending", [(b"", 0), (b"\x00", 0), (b"\x00\x00\x00", 0), (b"\x01\x02\x03", 3),
                                           (bytes(1000), 0)])
def test_decoder_edge_cases(data, pending):
    out, c = feed_in_chunks(data, [])
    assert out == []
    assert c["bytes_in"] == len(data) and c["pending_bytes"] == pending
    assert c["malformed"] == c["crc_errors"] == c["bytes_discarded"] == 0
    assert_chunking_does_not_matter(data, out, c)


def test_over_long_tail_is_one_malformed_segment():
    out, c = feed_in_chunks(b"\x07" * 300, [])
    assert out == []
    assert c["malformed"] == 1 and c["bytes_discarded"] == 300 and c["pending_bytes"] == 0
    assert_chunking_does_not_matter(b"\x07" * 300, out, c)


# --------------------------------------------------------------------------- property test


@st.composite
def corrupted_streams(draw):
    n = draw(st.integers(0, 60))
    sent = []
    next_seq = {}
    chunks = []
    t_us = draw(st.integers(0, 2**40))
    for _ in range(n):
        kind = draw(st.sampled_from([sf.FRAME_IMU_SAMPLE, sf.FRAME_SLIP_REFERENCE]))
        wheel = draw(st.integers(0, 5))
        key = (kind, wheel)
        if key not in next_seq:
            next_seq[key] = draw(st.sampled_from([0, 1, 255, 256, 65530, 65535]))
        seq = next_seq[key]
        next_seq[key] = (seq + 1) % sf.SEQ_MODULUS
        t_us += draw(st.integers(1, 2**20))
        if kind == sf.FRAME_IMU_SAMPLE:
            rec = sf.ImuSample(wheel, seq, t_us, draw(F32), draw(F32))
            chunks.append(sf.encode_imu_sample(*rec))
        else:
            rec = sf.SlipReference(wheel, seq, t_us, draw(F32))
            chunks.append(sf.encode_slip_reference(*rec))
        sent.append(rec)
    data = bytearray(b"".join(chunks))
    ops = draw(st.lists(st.tuples(st.sampled_from(["flip", "drop", "insert"]),
                                  st.floats(0, 1, exclude_max=True),
                                  st.integers(0, 255)), max_size=6))
    for op, where, value in ops:
        if op == "insert":
            data.insert(int(where * (len(data) + 1)), value)
        elif data:
            pos = int(where * len(data))
            if op == "flip":
                data[pos] ^= 1 << (value % 8)
            else:
                del data[pos]
    garbage = draw(st.sampled_from([b"", b"\x00", b"\x13\x37", bytes(range(1, 40)) + b"\x00"]))
    data = garbage + bytes(data)
    cuts = draw(st.lists(st.integers(0, len(data)), max_size=8))
    return sent, data, cuts, bool(ops) or garbage not in (b"", b"\x00")


def is_subsequence(sub, seq) -> bool:
    it = iter(seq)
    return all(any(x == y for y in it) for x in sub)


# CRC-16 lets a random corruption of a correctly sized frame through with
# probability 2**-16; derandomize keeps this test deterministic.
@settings(max_examples=200, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(corrupted_streams())
def test_corrupted_streams_never_deliver_corrupted_frames(case):
    sent, data, cuts, corrupted = case
    out, c = feed_in_chunks(data, cuts)  # no exception may escape

    # Only frames that were sent, in the order they were sent.
    assert is_subsequence(out, sent)
    assert c["frames_ok"] == len(out)
    if not corrupted:
        assert out == sent
        assert c["crc_errors"] == c["malformed"] == c["seq_gaps"] == 0

    # Losses are accounted for: between the first and the last delivered
    # frame of a stream, every missing frame is a sequence gap.
    delivered = set(out)
    expected_gaps = {w: 0 for w in range(sf.N_WHEELS)}
    for key in {(f.kind, f.wheel) for f in sent}:
        stream = [f for f in sent if (f.kind, f.wheel) == key]
        got = [i for i, f in enumerate(stream) if f in delivered]
        if got:
            expected_gaps[key[1]] += sum(1 for f in stream[got[0]:got[-1] + 1] if f not in delivered)
    assert c["seq_gaps_by_wheel"] == expected_gaps
    assert c["seq_gaps"] == sum(expected_gaps.values())
    assert c["seq_backwards"] == 0
    if len(out) < len(sent):
        assert c["crc_errors"] + c["malformed"] > 0 or c["pending_bytes"] > 0

    # Every byte is accounted for.
    good_bytes = sum(23 if f.kind == sf.FRAME_IMU_SAMPLE else 19 for f in out)
    assert c["bytes_in"] == len(data)
    assert c["bytes_in"] == good_bytes + c["bytes_discarded"] + c["pending_bytes"] + data.count(0)

    # However the stream is chunked, the same frames and counters.
    assert_chunking_does_not_matter(data, out, c)


# --------------------------------------------------------------------------- large capture


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_decoder_on_large_mixed_corrupted_capture(seed):
    rng = np.random.default_rng(seed)
    n = 20_000
    az, theta, slip = rng.normal(9.81, 5.0, n), rng.uniform(-np.pi, np.pi, n), rng.uniform(0, 1, n // 10)
    sent = []
    chunks = []
    for i in range(n):  # one reference frame after every 10 IMU frames
        rec = sf.ImuSample(i % 6, i // 6, i * 167, f32(az[i]), f32(theta[i]))
        chunks.append(sf.encode_imu_sample(*rec))
        sent.append(rec)
        if i % 10 == 9:
            j = i // 10
            ref = sf.SlipReference(j % 6, j // 6, 5, f32(slip[j]))
            chunks.append(sf.encode_slip_reference(*ref))
            sent.append(ref)
    clean = b"".join(chunks)
    out, c = feed_in_chunks(clean, [])
    assert out == sent
    assert c["frames_ok"] == n + n // 10 and c["seq_gaps"] == 0
    assert sum(1 for f in out if f.kind == sf.FRAME_SLIP_REFERENCE) == n // 10
    data = bytearray(clean)
    for pos in rng.choice(len(data), len(data) // 100, replace=False):
        data[pos] ^= 1 << int(rng.integers(8))
    corrupted = bytes(data)
    cuts = rng.integers(0, len(corrupted), 500).tolist()
    out, c = feed_in_chunks(corrupted, cuts)
    assert 0 < len(out) < n + n // 10
    assert c["crc_errors"] > 0 and c["malformed"] > 0 and c["seq_gaps"] > 0
    assert is_subsequence(out, sent)  # nothing corrupted gets through
    good_bytes = sum(23 if f.kind == sf.FRAME_IMU_SAMPLE else 19 for f in out)
    assert c["bytes_in"] == good_bytes + c["bytes_discarded"] + c["pending_bytes"] + corrupted.count(0)
    assert feed_in_chunks(corrupted, []) == (out, c)  # however the capture is chunked


# --------------------------------------------------------------------------- serial.threaded


def test_frame_protocol_with_reader_thread_on_a_pty():
    master, slave = os.openpty()
    tty.setraw(slave)
    port = serial.Serial(os.ttyname(slave), timeout=0.1)
    received = []
    done = threading.Event()
    n = 300

    def on_frame(frame):
        received.append(frame)
        if len(received) == n:
            done.set()

    data = imu_frames(np.arange(n) % 6, np.arange(n) // 6, np.arange(n) * 1000, 9.81, 0.1)
    try:
        with serial.threaded.ReaderThread(port, lambda: sf.FrameProtocol(on_frame)) as proto:
            for i in range(0, len(data), 1000):  # the pty buffers ~20 KB only
                os.write(master, data[i:i + 1000])
            assert done.wait(5.0), f"got {len(received)} of {n} frames"
            assert proto.decoder.counters()["frames_ok"] == n
    finally:
        os.close(master)
        os.close(slave)
    assert [(f.wheel, f.seq) for f in received] == [(i % 6, i // 6) for i in range(n)]
