"""Tests of the CAN messages (slipest/io/data/slipest.dbc + slipest.io.can_messages)."""

from __future__ import annotations

import math

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.io import can_messages as cm

# name prefix -> (base ID, DLC, {signal: (start bit, length, signed, scale)})
DOCUMENTED = {
    "SlipEstimate": (0x110, 8, {
        "Slip": (0, 14, False, 1e-4), "SlipStd": (14, 9, False, 1e-3),
        "Dphi": (23, 15, True, 1e-4), "DphiStd": (38, 10, False, 1e-3),
        "Quality": (48, 4, False, 1), "Saturated": (52, 1, False, 1),
        "Wheel": (53, 3, False, 1), "Counter": (56, 8, False, 1)}),
    "SlipReference": (0x120, 6, {
        "Slip": (0, 16, True, 1e-4), "TimeMod": (16, 16, False, 1e-5),
        "Counter": (32, 8, False, 1), "Wheel": (40, 3, False, 1),
        "Saturated": (43, 1, False, 1), "Invalid": (44, 1, False, 1)}),
    "ImuSample": (0x130, 8, {
        "Az": (0, 16, True, 0.005), "Theta": (16, 16, True, 1e-4),
        "TimeMod": (32, 16, False, 1e-5), "Counter": (48, 8, False, 1),
        "Wheel": (56, 3, False, 1), "AzSaturated": (59, 1, False, 1),
        "AzInvalid": (60, 1, False, 1), "ThetaInvalid": (61, 1, False, 1)}),
}


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


# --------------------------------------------------------------------------- DBC


def test_dbc_loads_from_package_data_with_documented_messages():
    db = cm.load_database()
    assert len(db.messages) == 3 * cm.N_WHEELS
    ids = [m.frame_id for m in db.messages]
    assert len(set(ids)) == len(ids)
    for prefix, (base, dlc, signals) in DOCUMENTED.items():
        for wheel in range(cm.N_WHEELS):
            msg = db.get_message_by_name(f"{prefix}_W{wheel}")
            assert msg.frame_id == base + wheel == cm.frame_id(prefix, wheel)
            assert not msg.is_extended_frame and msg.length == dlc
            got = {s.name: (s.start, s.length, s.is_signed, s.scale) for s in msg.signals}
            assert got == signals
            assert all(s.byte_order == "little_endian" and s.offset == 0 for s in msg.signals)
            bits = sum(s.length for s in msg.signals)
            assert bits <= 8 * dlc
            assert msg.get_signal_by_name("Wheel").maximum == cm.N_WHEELS - 1
        assert cm.base_id(prefix) == base


def test_dbc_scalings_meet_the_requirements():
    db = cm.load_database()
    imu = db.get_message_by_name("ImuSample_W0")
    az, theta = imu.get_signal_by_name("Az"), imu.get_signal_by_name("Theta")
    assert az.scale <= 0.005 and az.minimum <= -157 and az.maximum >= 157 and az.unit == "m/s^2"
    assert theta.scale <= 1e-4 and theta.minimum <= -math.pi and theta.maximum >= math.pi
    est = db.get_message_by_name("SlipEstimate_W0")
    slip, dphi = est.get_signal_by_name("Slip"), est.get_signal_by_name("Dphi")
    assert slip.scale <= 1e-4 and (slip.minimum, slip.maximum) == (0, 1)
    assert dphi.minimum <= -1 and dphi.maximum >= 1 and dphi.unit == "rad"
    assert est.get_signal_by_name("Quality").choices[cm.QUALITY_INVALID] == "INVALID"
    # the quality codes are the DBC's value table, on every wheel's message
    for w in range(cm.N_WHEELS):
        choices = {int(k): str(v) for k, v in
                   db.get_message_by_name(f"SlipEstimate_W{w}").get_signal_by_name("Quality").choices.items()}
        assert choices == {cm.QUALITY_OK: "OK", cm.QUALITY_REPAIRED: "REPAIRED", cm.QUALITY_MISFIT: "MISFIT",
                           cm.QUALITY_REPAIRED_MISFIT: "REPAIRED_MISFIT", cm.QUALITY_INVALID: "INVALID"}


def test_an_estimate_is_sent_with_the_quality_a_rover_must_know():
    from slipest.io.can_source import estimate_message
    from slipest.online import Estimate

    base = dict(cycle=3, t_end=1.0, delta_a=1.0, slip=0.3, slip_std=0.05, dphi=0.2, dphi_std=0.02, t_start=0.0,
                kS=900.0, kS_std=10.0, phiS=0.5, phiS_std=0.01, change_prob=0.0, slip_ref=math.nan,
                used_reference=False, n_samples=2500)
    cases = [(dict(quality="ok", misfit=1.0), cm.QUALITY_OK), (dict(quality="repaired", misfit=1.0, n_repaired=2),
             cm.QUALITY_REPAIRED), (dict(quality="ok", misfit=3.5), cm.QUALITY_MISFIT),
             (dict(quality="repaired", misfit=2.0, n_repaired=1), cm.QUALITY_REPAIRED_MISFIT),
             (dict(quality="gap", slip=math.nan, slip_std=math.nan, dphi=math.nan, dphi_std=math.nan),
              cm.QUALITY_INVALID)]
    for fields, code in cases:
        rec = cm.decode(estimate_message(2, Estimate(**{**base, **fields})))
        assert rec.quality == code and rec.wheel == 2


# --------------------------------------------------------------------------- round trips


@settings(max_examples=300, deadline=None)
@given(wheel=st.integers(0, 5), counter=st.integers(0, 10**6),
       az=st.floats(-157.0, 157.0), theta=st.floats(-math.pi, math.pi, exclude_max=True),
       t=st.floats(0.0, 1e5))
def test_imu_round_trip_at_resolution(wheel, counter, az, theta, t):
    msg = cm.encode_imu(wheel, counter, az, theta, t=t)
    assert msg.arbitration_id == 0x130 + wheel and msg.dlc == 8 and not msg.is_extended_id
    rec = cm.decode(msg)
    assert isinstance(rec, cm.ImuMessage)
    assert rec.wheel == wheel and rec.counter == counter % 256
    assert abs(rec.az - az) <= 0.0025 + 1e-9
    assert angle_diff(rec.theta, theta) <= 5e-5 + 1e-9
    assert abs(rec.theta) <= math.pi + 5e-5
    time_err = abs((rec.time_mod - t + 0.3) % cm.TIME_MOD_PERIOD - 0.3)
    assert time_err <= 5e-6 + 1e-9
    assert not rec.az_saturated


@settings(max_examples=300, deadline=None)
@given(wheel=st.integers(0, 5), counter=st.integers(-1000, 10**6),
       slip=st.floats(0.0, 1.0), slip_std=st.floats(0.0, 0.5), dphi=st.floats(-1.0, 1.0),
       dphi_std=st.floats(0.0, 1.0), quality=st.integers(0, 14))
def test_slip_estimate_round_trip_at_resolution(wheel, counter, slip, slip_std, dphi, dphi_std, quality):
    msg = cm.encode_slip_estimate(wheel, counter, slip, slip_std, dphi, dphi_std, quality)
    assert msg.arbitration_id == 0x110 + wheel
    rec = cm.decode(msg)
    assert isinstance(rec, cm.SlipEstimateMessage)
    assert (rec.wheel, rec.counter, rec.quality, rec.saturated) == (wheel, counter % 256, quality, False)
    assert abs(rec.slip - slip) <= 5e-5 + 1e-12
    assert abs(rec.dphi - dphi) <= 5e-5 + 1e-12
    assert abs(rec.slip_std - slip_std) <= 5e-4 + 1e-12
    assert abs(rec.dphi_std - dphi_std) <= 5e-4 + 1e-12


@settings(max_examples=100, deadline=None)
@given(wheel=st.integers(0, 5), counter=st.integers(0, 255), slip=st.floats(-3.0, 3.0),
       t=st.floats(0.0, 1e4))
def test_slip_reference_round_trip(wheel, counter, slip, t):
    rec = cm.decode(cm.encode_slip_reference(wheel, counter, slip, t=t))
    assert isinstance(rec, cm.SlipReferenceMessage)
    assert (rec.wheel, rec.counter, rec.saturated) == (wheel, counter, False)
    assert abs(rec.slip - slip) <= 5e-5 + 1e-12


def test_numpy_integers_are_accepted_as_wheel_and_counter():
    rec = cm.decode(cm.encode_imu(np.int64(4), np.uint16(300), 1.0, 0.5))
    assert (rec.wheel, rec.counter) == (4, 44)


def test_theta_is_wrapped_not_saturated():
    rec = cm.decode(cm.encode_imu(0, 0, 0.0, 1.5 * math.pi))
    assert rec.theta == pytest.approx(-0.5 * math.pi, abs=5e-5)
    rec = cm.decode(cm.encode_imu(0, 0, 0.0, -100.0))
    assert angle_diff(rec.theta, -100.0) <= 5e-5
    assert not rec.az_saturated


# --------------------------------------------------------------------------- saturation / NaN


@pytest.mark.parametrize("az, expected", [(200.0, 163.835), (-1e9, -163.84), (math.inf, 163.835),
                                          (-math.inf, -163.84)])
def test_az_is_saturated_and_flagged(az, expected):
    rec = cm.decode(cm.encode_imu(1, 0, az, 0.0))
    assert rec.az == pytest.approx(expected) and rec.az_saturated


def test_slip_estimate_values_are_saturated_and_flagged():
    rec = cm.decode(cm.encode_slip_estimate(2, 0, 1.5, 9.0, -5.0, 9.0))
    assert rec.saturated
    assert rec.slip == pytest.approx(1.0)
    assert rec.slip_std == pytest.approx(0.511)
    assert rec.dphi == pytest.approx(-1.6384)
    assert rec.dphi_std == pytest.approx(1.023)
    rec = cm.decode(cm.encode_slip_estimate(2, 0, -0.1, 0.0, 5.0, 0.0))
    assert rec.saturated and rec.slip == 0.0 and rec.dphi == pytest.approx(1.6383)
    rec = cm.decode(cm.encode_slip_reference(2, 0, 7.0))
    assert rec.saturated and rec.slip == pytest.approx(3.2767)


def test_nan_is_never_encoded_as_a_value():
    rec = cm.decode(cm.encode_imu(0, 0, math.nan, 1.0))
    assert math.isnan(rec.az) and rec.theta == pytest.approx(1.0)
    rec = cm.decode(cm.encode_imu(0, 0, 1.0, math.nan))
    assert rec.az == pytest.approx(1.0) and math.isnan(rec.theta)
    for args in [(math.nan, 0.1, 0.1, 0.1), (0.5, 0.1, math.nan, 0.1), (0.5, 0.1, 0.1, math.nan)]:
        rec = cm.decode(cm.encode_slip_estimate(3, 1, *args, quality=0))
        assert rec.quality == cm.QUALITY_INVALID
        assert all(math.isnan(v) for v in (rec.slip, rec.slip_std, rec.dphi, rec.dphi_std))
    rec = cm.decode(cm.encode_slip_estimate(3, 1, 0.5, 0.1, 0.1, 0.1, quality=cm.QUALITY_INVALID))
    assert math.isnan(rec.slip)
    rec = cm.decode(cm.encode_slip_reference(3, 1, math.nan))
    assert math.isnan(rec.slip) and not rec.saturated


@pytest.mark.parametrize("call, match", [
    (lambda: cm.encode_imu(6, 0, 0.0, 0.0), "wheel"),
    (lambda: cm.encode_imu(-1, 0, 0.0, 0.0), "wheel"),
    (lambda: cm.encode_imu("1", 0, 0.0, 0.0), "wheel"),
    (lambda: cm.encode_imu(0, 0, 0.0, 0.0, t=math.nan), "time"),
    (lambda: cm.encode_slip_reference(0, 0, 0.0, t=math.inf), "time"),
    (lambda: cm.encode_slip_estimate(0, 0, 0.5, 0.1, 0.0, 0.1, quality=16), "quality"),
    (lambda: cm.encode_slip_estimate(0, 0, 0.5, 0.1, 0.0, 0.1, quality=-1), "quality"),
])
def test_bad_arguments_raise_clear_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# --------------------------------------------------------------------------- decoding


def test_frames_that_are_not_ours_decode_to_none_and_are_counted():
    dec = cm.CanDecoder()
    others = [
        can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False),
        can.Message(arbitration_id=0x130, data=bytes(8), is_extended_id=True),  # extended 0x130
        can.Message(arbitration_id=0x109, data=b"", is_extended_id=False),
    ]
    for msg in others:
        assert cm.decode(msg) is None
        assert dec.decode(msg) is None
    remote = can.Message(arbitration_id=0x130, is_remote_frame=True, dlc=8, is_extended_id=False)
    error = can.Message(arbitration_id=0x130, is_error_frame=True, data=bytes(8), is_extended_id=False)
    assert dec.decode(remote) is None and dec.decode(error) is None
    c = dec.counters()
    assert c["unknown_id"] == 3 and c["not_data"] == 2 and c["ok"] == 0


def test_bad_length_and_wheel_mismatch_are_errors_not_crashes():
    good = cm.encode_imu(2, 0, 1.0, 1.0)
    short = can.Message(arbitration_id=good.arbitration_id, data=good.data[:7], is_extended_id=False)
    long_ = can.Message(arbitration_id=0x120, data=bytes(8), is_extended_id=False)  # ref is 6 bytes
    moved = can.Message(arbitration_id=0x133, data=good.data, is_extended_id=False)  # Wheel=2 on wheel 3's ID
    for msg in (short, long_, moved):
        with pytest.raises(cm.CanFrameError):
            cm.decode(msg)
    dec = cm.CanDecoder()
    assert [dec.decode(m) for m in (short, long_, moved)] == [None, None, None]
    assert dec.counters()["bad_frame"] == 3 and "Wheel" in dec.last_error
    assert dec.decode(good) == cm.decode(good)


def test_counter_gaps_per_wheel_with_wrap():
    dec = cm.CanDecoder()
    for counter in (253, 254, 0, 1, 5, 5, 6):  # 255 missing, 2..4 missing, 5 repeated
        assert dec.decode(cm.encode_imu(1, counter, 0.0, 0.0)) is not None
    for counter in (0, 10):  # 9 missing
        dec.decode(cm.encode_slip_estimate(4, counter, 0.5, 0.1, 0.0, 0.1))
    for counter in (100, 101):  # its own counter: no gap against wheel 1's IMU counter
        dec.decode(cm.encode_slip_reference(1, counter, 0.2))
    c = dec.counters()
    assert c["ok"] == 11
    assert c["counter_gaps"] == 4 + 9
    assert c["counter_gaps_by_wheel"] == {0: 0, 1: 4, 2: 0, 3: 0, 4: 9, 5: 0}
    assert c["counter_backwards"] == 1
    c["counter_gaps_by_wheel"][1] = 99
    assert dec.counters()["counter_gaps_by_wheel"][1] == 4


def test_saturated_and_invalid_are_counted():
    dec = cm.CanDecoder()
    dec.decode(cm.encode_imu(0, 0, 500.0, 0.0))
    dec.decode(cm.encode_imu(0, 1, math.nan, 0.0))
    dec.decode(cm.encode_slip_estimate(0, 0, math.nan, 0, 0, 0))
    dec.decode(cm.encode_slip_reference(0, 0, 9.0))
    c = dec.counters()
    assert c["saturated"] == 2 and c["invalid"] == 2


def test_unwrap_time_mod_recovers_device_time():
    t_dev = 1234.5 + np.arange(0, 5.0, 0.013)  # 5 s, crossing the 0.65536 s wrap several times
    t_prev = t_dev[0]
    for k, t in enumerate(t_dev):
        rec = cm.decode(cm.encode_imu(0, k, 0.0, 0.0, t=t))
        t_prev = cm.unwrap_time_mod(rec.time_mod, t_prev + 0.013 if k else t)
        assert t_prev == pytest.approx(t, abs=6e-6)


def test_messages_travel_over_a_python_can_bus():
    with can.Bus(interface="virtual", channel="slipest-test", receive_own_messages=False) as tx, \
            can.Bus(interface="virtual", channel="slipest-test") as rx:
        sent = [cm.encode_imu(w, 7, 9.81, 0.25, t=1.0) for w in range(6)]
        sent.append(cm.encode_slip_estimate(3, 9, 0.2, 0.01, 0.05, 0.002, quality=1))
        for msg in sent:
            tx.send(msg)
        got = [cm.decode(rx.recv(1.0)) for _ in sent]
    assert [type(r).__name__ for r in got] == ["ImuMessage"] * 6 + ["SlipEstimateMessage"]
    assert [r.wheel for r in got[:6]] == list(range(6))
    assert got[6].slip == pytest.approx(0.2) and got[6].quality == 1
    assert all(r.timestamp > 0 for r in got)  # reception time from the bus


def test_decoder_builds_the_dbc_tables_up_front():
    # built lazily, the tables cost the first decoded frame ~15 ms of latency (found by tools/bench_hil.py)
    from slipest.io import can_messages

    can_messages._table.cache_clear()
    can_messages.CanDecoder()
    assert can_messages._table.cache_info().currsize == 1
