"""`CanDecoder.decode_many` (ImuSample frames decoded together with numpy from the DBC's bit layout)
against `CanDecoder.decode` frame by frame: the same records, counters and last error, whatever the
frames (every kind and wheel, other IDs, extended, remote and error frames, wrong lengths, random
payloads whose Wheel signal disagrees with the ID); and a CAN log that python-can cannot parse to the
end is estimated up to the bad frame before the error names it."""

from __future__ import annotations

import math

import can
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.cli.main import main
from slipest.io import can_messages as cm
from slipest.io.can_messages import (CanDecoder, base_id, encode_imu, encode_slip_estimate,
                                     encode_slip_reference)
from tests.log_makers import can_frames, stream, write_can_log

IMU = base_id(cm.IMU_SAMPLE)


def _frame(kind: str, wheel: int, n: int, rng: np.random.Generator, t: float) -> can.Message:
    """One frame of a kind: 'imu' encoded (some with NaN, out-of-range values), 'raw' an ImuSample ID
    with random bytes, 'short' an ImuSample ID with too few bytes, 'estimate', 'reference', 'other' an
    unknown ID, 'extended' an ImuSample ID as an extended ID, 'remote', 'error'."""
    if kind == "imu":
        az = float(rng.choice([rng.normal(9.81, 3), math.nan, 400.0, -400.0]))
        theta = float(rng.choice([rng.uniform(-4, 4), math.nan]))
        msg = encode_imu(wheel, n, az, theta, t)
    elif kind == "raw":
        msg = can.Message(arbitration_id=IMU + wheel, is_extended_id=False, data=rng.bytes(8))
    elif kind == "short":
        msg = can.Message(arbitration_id=IMU + wheel, is_extended_id=False, data=rng.bytes(int(rng.integers(0, 8))))
    elif kind == "estimate":
        msg = encode_slip_estimate(wheel, n, float(rng.uniform(0, 1)), 0.02, 0.1, 0.01, int(rng.integers(0, 16)))
    elif kind == "reference":
        msg = encode_slip_reference(wheel, n, float(rng.choice([rng.uniform(0, 1), math.nan])), t)
    elif kind == "other":
        msg = can.Message(arbitration_id=int(rng.integers(0, 0x7FF)), is_extended_id=False, data=rng.bytes(8))
    elif kind == "extended":
        msg = can.Message(arbitration_id=IMU + wheel, is_extended_id=True, data=rng.bytes(8))
    elif kind == "remote":
        msg = can.Message(arbitration_id=IMU + wheel, is_remote_frame=True, dlc=8)
    else:
        msg = can.Message(arbitration_id=0, is_error_frame=True)
    msg.timestamp = float(rng.choice([t, 0.0]))
    return msg


def _same(a, b) -> bool:
    """Records equal field by field, NaN equal to NaN (and of the same type)."""
    if a is None or b is None:
        return a is b
    if type(a) is not type(b):
        return False
    return all(type(x) is type(y) and (x == y or (x != x and y != y))
               for x, y in zip([getattr(a, f) for f in a.__slots__], [getattr(b, f) for f in b.__slots__]))


KINDS = ("imu", "imu", "imu", "imu", "raw", "short", "estimate", "reference", "other", "extended", "remote", "error")


@settings(max_examples=60, deadline=None)
@given(kinds=st.lists(st.sampled_from(KINDS), min_size=0, max_size=300), seed=st.integers(0, 2**32 - 1),
       wheels=st.lists(st.integers(0, 5), min_size=1, max_size=6))
def test_decode_many_gives_what_decode_gives_frame_by_frame(kinds, seed, wheels):
    rng = np.random.default_rng(seed)
    msgs = [_frame(k, wheels[i % len(wheels)], int(rng.integers(0, 300)), rng, 0.001 * i)
            for i, k in enumerate(kinds)]
    one, many = CanDecoder(), CanDecoder()
    ref = [one.decode(m) for m in msgs]
    got = many.decode_many(msgs)
    assert len(got) == len(ref)
    assert all(_same(a, b) for a, b in zip(ref, got))
    assert one.counters() == many.counters() and one.last_error == many.last_error


def test_decode_many_decodes_plain_imu_frames_without_cantools(monkeypatch):
    """The numpy path is the one taken for a log's ImuSample frames (else this equivalence would test
    decode against itself): the frame-by-frame decoder is called only for the frames that are not."""
    rng = np.random.default_rng(3)
    msgs = [encode_imu(i % 2, i, 9.81 + rng.normal(), rng.uniform(-3, 3), 0.001 * i) for i in range(200)]
    msgs[50] = can.Message(arbitration_id=0x7AB, data=b"12345678")
    calls = []
    plain = cm.decode
    monkeypatch.setattr(cm, "decode", lambda m: calls.append(m) or plain(m))
    recs = CanDecoder().decode_many(msgs)
    assert calls == [msgs[50]] and recs[50] is None and sum(r is not None for r in recs) == 199


def test_a_can_log_python_can_cannot_parse_to_the_end_is_estimated_up_to_the_bad_frame(tmp_path, capsys):
    s, _ = stream(6, seed=5)
    frames = can_frames({0: s})
    good = write_can_log(tmp_path / "drive.log", frames)
    lines = open(good).read().splitlines()
    bad_at = int(len(lines) * 0.8)  # python-can's .log has one frame per line
    lines[bad_at] = "garbage"
    bad = tmp_path / "bad.log"
    bad.write_text("\n".join(lines) + "\n")
    assert main(["replay", str(good)]) == 0
    whole = capsys.readouterr().out.splitlines()
    assert main(["replay", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert f"frame {bad_at + 1}" in err and "bad.log" in err
    # every cycle that closed before the bad frame was estimated and printed, as from the whole log (the
    # frames went on in chunks of 4096 and those before the error were dropped: 3 of 4 cycles here)
    samples_before = sum(m.arbitration_id == IMU for m in frames[:bad_at])
    closed = int((s.t[samples_before - 1] - 0.5) // (2 * math.pi / (4 * 0.63)))  # ended 0.5 s before it
    rows = [r for r in out.splitlines() if ",partial," not in r]  # the cycle the error cut short says so
    assert len(rows) - 1 >= closed >= 4 and rows == whole[:len(rows)]
    assert out.count(",partial,") <= 1
