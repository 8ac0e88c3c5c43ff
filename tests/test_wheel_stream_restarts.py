"""WheelStream (pure): a device restart is not a loss, a late start is counted, a stuck sensor is caught in time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipest.io.device_stream import WheelSamples, WheelStream
from slipest.stuck import STUCK_MIN_SAMPLES, STUCK_TIME, stuck_run_length

RATE = 1000.0


def device(n: int, *, seq0: int = 0, t0: float = 100.0, seed: int = 0, modulus: int = 1 << 16, wrapped: bool = False):
    """A device's n frames at 1 kHz: (seq, t, az, theta) columns; az noisy, theta turning at 0.63 rad/s."""
    t = t0 + np.arange(n) / RATE
    seq = (seq0 + np.arange(n)) % modulus
    az = 9.81 + np.random.default_rng(seed).normal(0, 0.1, n)
    theta = np.mod(0.63 * t + math.pi, 2 * math.pi) - math.pi
    return seq, (np.mod(t, 0.65536) if wrapped else t), az, theta, t


def late_frames(n: int, late_by: int, every: int = 700):
    """A CAN device's n frames (8-bit counter, wrapped times) with frames 400, 400 + every, ... each arriving
    ``late_by`` frames late: the columns in arrival order, the az as sent, the late frames' indices."""
    seq, t, az, th, host = device(n, seed=8, modulus=256, wrapped=True)
    order = list(range(n))
    late = list(range(400, n - 400, every))
    for j in late:
        order.remove(j)
        order.insert(order.index(j + late_by) + 1, j)
    return tuple(c[order] for c in (seq, t, az, th, host)), az, late


def feed(stream: WheelStream, parts, intakes) -> WheelSamples:
    out = [stream.add(seq, t, az, th, intake) for (seq, t, az, th, _), intake in zip(parts, intakes)]
    return WheelSamples.concatenate(out + [stream.flush()])


def feed_frames(stream: WheelStream, cols, one_by_one: bool) -> WheelSamples:
    """Frames ``cols`` (seq, t, az, theta, arrival) fed in one call, or one call per frame, then flushed."""
    if not one_by_one:
        return feed(stream, [cols], [cols[4]])
    return WheelSamples.concatenate([stream.add(*(c[i:i + 1] for c in cols[:4]), cols[4][i:i + 1])
                                     for i in range(len(cols[0]))] + [stream.flush()])


def test_a_restart_after_a_long_outage_is_neither_a_loss_nor_nan_rows():
    # the case: a device restarted 43 s after it stopped (its clock goes on, its counter starts at 0)
    before = device(20000, seq0=0, t0=100.0, seed=1)
    after = device(5000, seq0=0, t0=100.0 + 20 + 43.332, seed=2)
    stream = WheelStream()
    s = feed(stream, [before, after], [before[4] + 0.002, after[4] + 0.002])
    c = stream.counters()
    assert c["restarts"] == 1 and c["frames_lost"] == 0 and c["samples_filled"] == 0
    assert len(s) == 25000 and not np.isnan(s.az).any()
    assert c["frames_missed_at_start"] == 0
    assert any("restarted" in e for e in stream.events)


@pytest.mark.parametrize("outage_s", [0.5, 12.0, 43.332, 70.0])
def test_a_long_outage_of_a_device_that_kept_counting_is_counted_exactly(outage_s):
    n_lost = int(round(outage_s * RATE))
    seq, t, az, th, host = device(30000 + n_lost, seq0=40000, seed=3)
    keep = np.ones(t.size, bool)
    keep[20000:20000 + n_lost] = False  # the counter wrapped during the longer outages
    stream = WheelStream()
    cols = [c[keep] for c in (seq, t, az, th, host)]
    s = feed(stream, [cols], [cols[4] + 0.002])
    c = stream.counters()
    assert c["frames_lost"] == n_lost and c["restarts"] == 0 and c["loss_events"] == 1
    assert c["samples_filled"] == min(n_lost, 10000) and np.isnan(s.az).sum() == min(n_lost, 10000)


def test_a_reboot_that_restarts_the_clock_is_taken_and_time_keeps_increasing():
    # a real device's clock counts from its boot: after a reboot its times start again near 0
    before = device(8000, seq0=0, t0=500.0, seed=4)
    after = device(4000, seq0=0, t0=0.001, seed=5)
    host_before = before[4] + 0.002
    host_after = host_before[-1] + 3.0 + np.arange(4000) / RATE  # it came back 3 s later
    stream = WheelStream()
    s = feed(stream, [before, after], [host_before, host_after])
    c = stream.counters()
    assert c["restarts"] == 1 and c["out_of_order"] == 0 and c["frames_lost"] == 0
    assert len(s) == 12000 and (np.diff(s.t) > 0).all()
    assert s.t[8000] - s.t[7999] == pytest.approx(3.0, abs=2e-3)  # the gap the arrival times show
    assert np.allclose(np.diff(s.t[8000:]), 1e-3)


def test_a_reordered_or_repeated_frame_is_still_dropped():
    seq, t, az, th, host = device(300, seed=6)
    order = list(range(150)) + [150, 149, 151, 151] + list(range(152, 300))
    stream = WheelStream()
    s = feed(stream, [tuple(c[order] for c in (seq, t, az, th, host))], [host[order]])
    assert stream.counters()["out_of_order"] == 2 and stream.counters()["restarts"] == 0 and len(s) == 300


@pytest.mark.parametrize("one_by_one", [False, True])
def test_a_can_frame_sent_late_is_dropped_as_out_of_order_not_a_restart(one_by_one):
    """Wrapped times cannot go back: a CAN frame that arrives 3 frames late was unwrapped a whole TimeMod period
    (0.655 s) ahead, a restart that shifted every later time (80 late frames of 40,000 lost every cycle). Now its
    counter and wrapped time going back together make it a reordering: dropped, the frame it came after having
    counted it lost."""
    cols, _, late = late_frames(6000, 3)  # frame j comes 3 frames late
    host = device(6000, seed=8, modulus=256, wrapped=True)[4]
    stream = WheelStream(seq_modulus=256, time_modulus=0.65536)
    s = feed_frames(stream, cols, one_by_one)
    c = stream.counters()
    assert c["out_of_order"] == len(late) and c["restarts"] == 0 and c["frames_lost"] == len(late)
    np.testing.assert_allclose(s.t - s.t[0], host - host[0], atol=1e-9)  # every time in place, none shifted
    assert np.isnan(s.az).sum() == len(late) and np.isnan(s.az[late]).all()


@pytest.mark.parametrize("where", [0, 1, 2500, 5999])
def test_a_frame_without_an_angle_is_lost_not_a_crash(where):
    """CAN's ThetaInvalid (theta NaN) crashed the stream's angle unwrapping (a traceback out of replay); such a
    frame is not taken: counted, and a NaN sample in its place. Frame by frame and in bursts alike."""
    for wrapped, modulus in ((True, 256), (False, 1 << 16)):
        seq, t, az, th, host = device(6000, seed=9, modulus=modulus, wrapped=wrapped)
        th = th.copy()
        th[where] = math.nan
        results = []
        for chunk in (6000, 1):
            stream = WheelStream(seq_modulus=modulus, time_modulus=0.65536 if wrapped else None)
            parts = [stream.add(seq[i:i + chunk], t[i:i + chunk], az[i:i + chunk], th[i:i + chunk],
                                host[i:i + chunk]) for i in range(0, 6000, chunk)]
            s = WheelSamples.concatenate(parts + [stream.flush()])
            assert stream.counters()["frames_invalid"] == 1 and np.isfinite(s.theta).all()
            assert len(s) == 6000 - (where in (0, 5999))  # a first or last frame has no neighbour to fill it
            results.append(s)
        np.testing.assert_array_equal(results[0].az, results[1].az)
        np.testing.assert_array_equal(results[0].t, results[1].t)


def test_a_late_start_counts_the_frames_the_counter_shows_were_missed():
    seq, t, az, th, host = device(3000, seq0=2200, seed=7)  # started 2.2 s after the device
    stream = WheelStream()
    feed(stream, [(seq, t, az, th, host)], [host])
    assert stream.counters()["frames_missed_at_start"] == 2200 and stream.counters()["frames_lost"] == 0
    assert stream.events == ["first frame has counter 2200: at least 2200 frame(s) were sent before it, missed "
                             "(started after the device)"]
    can = WheelStream(seq_modulus=256, time_modulus=0.65536)
    seq, t, az, th, host = device(3000, seq0=2200, seed=7, modulus=256, wrapped=True)
    feed(can, [(seq, t, az, th, host)], [host])
    assert can.counters()["frames_missed_at_start"] == 2200 % 256  # 8 bits: at least that many


def test_a_can_restart_is_told_from_an_outage_in_most_cases():
    # CAN: 8-bit counter, time modulo 0.65536 s unwrapped with the arrival times
    told = 0
    for k in range(100):
        outage = 2.0 + 0.071 * k
        before = device(5000, seq0=17 * k, t0=50.0, seed=k, modulus=256, wrapped=True)
        after = device(3000, seq0=0, t0=55.0 + outage, seed=100 + k, modulus=256, wrapped=True)
        stream = WheelStream(seq_modulus=256, time_modulus=0.65536)
        feed(stream, [before, after], [before[4] + 0.002, after[4] + 0.002])
        c = stream.counters()
        told += c["restarts"] == 1 and c["frames_lost"] == 0
    assert told >= 85  # the counter agrees by chance with one of the steps the arrival allows in ~6 %


def test_the_stuck_rule_is_a_duration_at_the_imu_rate_with_a_floor():
    assert STUCK_TIME == 0.02 and stuck_run_length(STUCK_TIME, 1e-3) == 20
    assert stuck_run_length(STUCK_TIME, 1e-2) == STUCK_MIN_SAMPLES  # 100 Hz: the floor
    assert stuck_run_length(STUCK_TIME, None) == STUCK_MIN_SAMPLES


@pytest.mark.parametrize("rate,run,caught", [(1000, 25, True), (1000, 19, False), (100, 12, True), (100, 11, False)])
def test_a_stuck_run_is_caught_when_it_lasts_the_stuck_time(rate, run, caught):
    n = 600
    t = np.arange(n) / rate
    az = 9.81 + np.random.default_rng(8).normal(0, 0.1, n)
    az[200:200 + run] = az[200]
    stream = WheelStream()
    s = WheelSamples.concatenate([stream.add(np.arange(n), t, az, 0.63 * t, t), stream.flush()])
    c = stream.counters()
    assert len(s) == n
    if caught:
        assert c["stuck_runs"] == 1 and np.flatnonzero(np.isnan(s.az)).tolist() == list(range(201, 200 + run))
    else:
        assert c["stuck_runs"] == 0 and not np.isnan(s.az).any()


def test_a_fixed_stuck_run_length_still_overrides_the_time_rule():
    n = 300
    t = np.arange(n) / 1000
    az = 9.81 + np.random.default_rng(9).normal(0, 0.1, n)
    az[100:140] = az[100]
    for kwargs, runs in (({"stuck_samples": 50}, 0), ({"stuck_samples": 30}, 1), ({"stuck_time": 0}, 0), ({}, 1)):
        stream = WheelStream(**kwargs)
        stream.add(np.arange(n), t, az, 0.63 * t, t)
        assert stream.counters()["stuck_runs"] == runs, kwargs


def test_firmware_sim_restarted_on_the_same_link_is_one_restart_not_a_loss(tmp_path):
    """The issue's case, live: firmware-sim stopped, started again > 16 s of device time later (speed 16) on the
    same --link path; slipest serial reopens it. Before: 37,603 frames lost, 10,000 NaN rows, 21 invented cycles
    (a 12 s outage at speed 4). The first run sends its 6 cycles to the end, the case that made a 13th cycle:
    the second run's first angle, a hair before a cycle's start as a float32, opened the cycle before it with
    that one sample (a SIGTERM after 0.5 s, as this test sent, left 3-4 cycles to the first run, and the bound
    of 12 held unless load delayed the signal past the run's end)."""
    import json
    import time

    from slipest.io.log_csv import read_log
    from tests.hil_support import Stopping, firmware_sim, slipest_cmd, stop_once_said

    link, rec, report = tmp_path / "imu", tmp_path / "run.csv", tmp_path / "live.json"
    device = ("serial", "--link", str(link), "--cycles", "6", "--speed", "16", "--noise", "0.01", "--settle", "0.05")
    with Stopping() as procs:
        first = procs.add(firmware_sim(*device, "--seed", "1"))
        first.wait_line("serial device", timeout=60)
        est = procs.add(slipest_cmd("serial", str(link), "--record", str(rec), "--report", str(report),
                                    "--idle-timeout", "60", "--format", "none"))
        first.wait_line("streaming", timeout=60)
        assert first.wait(30) == 0  # 6 cycles: 0.93 s at speed 16
        assert "firmware-sim: done" in first.lines  # it sent them all (not stopped)
        time.sleep(1.5)  # 24 s of device time (the old rule took a restart for an outage beyond 16.4 s)
        second = procs.add(firmware_sim(*device, "--seed", "2"))
        assert second.wait(60) == 0
        # stopped once the second run's end is read (its restart said, then its disconnection), not by an idle
        # timeout: one of 10 s ended the run before a second device that took longer to start under load was read
        stop_once_said(est, "the device restarted", ": disconnected (")
        assert est.wait(60) == 0, est.stderr
    wheel = json.loads(report.read_text())["estimation"]["wheel0"]
    log = read_log(rec)
    assert wheel["restarts"] == 1 and wheel["frames_lost"] == 0 and wheel["samples_filled"] == 0
    assert len(log) == wheel["samples_in"] and not np.isnan(log.az).any() and (np.diff(log.t) > 0).all()
    assert wheel["cycles"] == 6 + 6  # each run's 6 cycles: none invented for the outage (it was 10 more)
    assert "wheel 0: the device restarted (counter 0" in est.stderr


@pytest.mark.parametrize("stall_s", [0.02, 0.1, 0.4])
def test_a_sped_up_device_read_in_a_burst_after_a_stall_is_no_restart(stall_s):
    # firmware-sim at --speed 20 (the demo): a receiver that stalls stall_s of host time reads the frames sent
    # meanwhile in one burst; the first one's arrival step is 20 x stall_s device seconds, its true step 1 ms
    speed = 20.0
    seq, t, az, th, dev_t = device(6000, t0=30.0, seed=3, modulus=256, wrapped=True)
    host = dev_t / speed
    late = (dev_t >= 32.0) & (dev_t < 32.0 + stall_s * speed)
    host = np.where(late, 32.0 / speed + stall_s, host)  # held up, then read at once
    stream = WheelStream(seq_modulus=256, time_modulus=0.65536, time_scale=speed)
    out = feed(stream, [(seq, t, az, th, dev_t)], [host])
    c = stream.counters()
    assert c["restarts"] == 0 and c["frames_lost"] == 0
    np.testing.assert_allclose(out.t - out.t[0], dev_t - dev_t[0], atol=1e-9)  # the device's own time, no jump


@pytest.mark.parametrize("bad_t", [3600.0, 1.8446744073709552e13, -50.0])
@pytest.mark.parametrize("one_by_one", [False, True])
def test_one_corrupted_timestamp_is_a_time_glitch_not_a_restart(bad_t, one_by_one):
    """A frame whose time alone is corrupted (an hour on, 2**64 - 1 us, back in the past; its counter one step on):
    dropped as a time glitch, a NaN sample in its place at its own time; no restart, nothing shifted, the same
    samples frame by frame as in one call. (It used to count two restarts and shift every later time by as much.)"""
    seq, t, az, th, host = device(3000, seed=7)
    bad = t.copy()
    bad[1500] = t[1500] + bad_t if bad_t > 0 else bad_t
    stream = WheelStream()
    if one_by_one:
        s = WheelSamples.concatenate([stream.add([sq], [tt], [a], [h], i) for sq, tt, a, h, i
                                      in zip(seq, bad, az, th, host + 0.002)] + [stream.flush()])
    else:
        s = feed(stream, [(seq, bad, az, th, None)], [host + 0.002])
    c = stream.counters()
    assert c["time_glitches"] == 1 and c["restarts"] == 0 and c["frames_lost"] == 1
    assert len(s) == 3000 and np.allclose(s.t, t, atol=1e-9)
    assert np.flatnonzero(np.isnan(s.az)).tolist() == [1500]
    assert not any("restarted" in e for e in stream.events)


def test_a_restart_whose_counter_is_by_chance_one_step_on_is_still_a_restart():
    """A device rebooted with its counter, by chance, one step on: its next frame follows the new clock, not the
    old one, so the held frame is taken as a restart (a frame later), not dropped."""
    before = device(2000, seq0=0, t0=500.0, seed=8)
    after = device(2000, seq0=2000, t0=0.001, seed=9)
    stream = WheelStream()
    s = feed(stream, [before, after], [before[4] + 0.002, after[4] + 600.0])
    c = stream.counters()
    assert c["restarts"] == 1 and c["time_glitches"] == 0 and len(s) == 4000 and not np.isnan(s.az).any()
    assert np.all(np.diff(s.t) > 0)
