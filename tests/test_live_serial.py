"""`slipest serial` on a live stream: firmware-sim in one process, the estimator in another, a real pty."""

from __future__ import annotations

import json
import math
import signal
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.cli import estimate_output
from slipest.io.device_stream import WheelSamples, WheelStream
from slipest.io.log_csv import read_log
from slipest.live.recording import record_path
from tests.hil_support import Stopping, firmware_sim, serial_device, slipest_cmd, stop_once_said

PERIOD = 2 * math.pi / (4 * 0.63)  # one leg cycle [s]


def window(k: int, frac: float = 0.5) -> float:
    """Scenario time inside the feature window (propulsive half-stance) of cycle k."""
    return (k + 0.5 + 0.5 * frac) * PERIOD


def rows(proc) -> dict[tuple[int, int], dict]:
    """The estimate rows a live command printed: (wheel, cycle) -> row."""
    return {(int(r["wheel"]), int(r["cycle"])): r for r in estimate_output.parse_rows(proc.lines, ("wheel",))}


# --- the per-wheel stream (pure) -----------------------------------------------------------------


def feed(stream: WheelStream, seq, t, az, theta, batch: int) -> WheelSamples:
    parts = [stream.add(seq[i:i + batch], t[i:i + batch], az[i:i + batch], theta[i:i + batch], t[i:i + batch])
             for i in range(0, len(t), batch)]
    return WheelSamples.concatenate(parts + [stream.flush()])


@pytest.mark.parametrize("batch", [1, 7, 500])
def test_a_single_lost_frame_becomes_one_nan_sample_at_its_time(batch):
    n = 3000
    t = 10.0 + np.arange(n) * 1e-3
    theta = np.mod(0.63 * t + math.pi, 2 * math.pi) - math.pi
    az = 9.81 + np.random.default_rng(0).normal(0, 0.1, n)
    keep = np.ones(n, bool)
    keep[1234] = False
    s = feed(WheelStream(), np.arange(n)[keep], t[keep], az[keep], theta[keep], batch)
    assert len(s) == n
    assert np.flatnonzero(np.isnan(s.az)).tolist() == [1234] and s.filled.sum() == 1
    assert s.t[1234] == pytest.approx(t[1234])
    assert np.allclose(s.theta, 0.63 * t - 2 * math.pi * round((0.63 * t[0] - theta[0]) / (2 * math.pi)), atol=1e-9)


def test_an_eight_bit_counter_and_wrapped_time_still_count_a_long_outage():
    n = 5000
    t = np.arange(n) * 1e-3
    keep = np.ones(n, bool)
    keep[1000:1700] = False  # 700 frames: the 8-bit counter wrapped twice, TimeMod once
    seq = np.arange(n) % 256
    tmod = np.mod(t, 0.65536)
    stream = WheelStream(seq_modulus=256, time_modulus=0.65536)
    s = feed(stream, seq[keep], tmod[keep], np.full(keep.sum(), 9.81) + t[keep], np.zeros(keep.sum()), 13)
    assert stream.counters()["frames_lost"] == 700 and len(s) == n
    assert np.allclose(s.t, t, atol=1e-9)


def test_duplicates_and_backward_times_are_dropped_and_counted():
    stream = WheelStream()
    t = [0.0, 0.001, 0.002, 0.002, 0.001, 0.003]
    s = stream.add([0, 1, 2, 2, 1, 3], t, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0], [0.0] * 6, 0.0)
    assert s.t.tolist() == [0.0, 0.001, 0.002, 0.003] and stream.counters()["out_of_order"] == 2


def test_a_stuck_sensor_is_never_handed_on_and_normal_data_is_not_delayed():
    n = 400
    az = 9.81 + np.random.default_rng(1).normal(0, 0.1, n)
    az[100:260] = az[100]
    stream = WheelStream(stuck_samples=50)
    t = np.arange(n) * 1e-3
    out = [stream.add([i], t[i:i + 1], az[i:i + 1], [0.001 * i], t[i]) for i in range(n)]
    lengths = [len(o) for o in out]
    assert lengths[:101] == [1] * 101  # noisy data goes straight through
    assert sum(lengths[101:148]) == 0  # a growing run is held back...
    s = WheelSamples.concatenate(out)
    assert len(s) == n and np.flatnonzero(np.isnan(s.az)).tolist() == list(range(101, 260))  # ...then dropped
    assert stream.counters()["stuck_runs"] == 1


#: What can happen to a device's stream (see frames_with_events).
EVENTS = ("run", "lose", "dup", "swap", "delay", "restart", "reboot", "stuck", "repeat", "burst", "stall", "jump",
          "late", "early")
#: How a link carries the frames: WheelStream options, and whether arrival times are given.
LINKS = {"serial": ({}, True), "serial, no arrival times": ({}, False),
         "can": ({"seq_modulus": 256, "time_modulus": 0.65536}, True),
         "can, put back in order": ({"seq_modulus": 256, "time_modulus": 0.65536, "reorder_window": 4}, True),
         "can, no counter": ({"seq_modulus": 0, "time_modulus": 0.65536}, True),
         "serial, stuck at 4 samples": ({"stuck_samples": 4}, True)}


def frames_with_events(events, wrapped: bool, seed: int):
    """A device's frames with events in it: (seq, t, az, theta, intake) lists in arrival order.

    Starts with 200 plain frames at 1 kHz, then each (event, k): ``run`` k plain frames; ``lose`` k
    frames never sent; ``dup`` the last frame again; ``swap`` two frames in swapped order; ``delay`` a frame
    sent after the k % 7 + 1 frames that follow it (within a window of 4 frames or beyond it); ``restart``
    the counter back to k; ``reboot`` the counter back to 0 and the device clock to k ms; ``stuck`` k
    frames with the same az; ``repeat`` k % 14 + 1 frames with the same az (around the stuck length: a
    short repeat is held and released, a long one is stuck); ``burst`` k frames arriving together (one
    intake, up to 0.4 s late); ``stall`` the same, 0.3-0.7 s late (longer than half CAN's time period);
    ``jump`` an angle step of 2 rad; ``late`` / ``early`` a frame 1.7 / 0.4 periods after the last.
    ``wrapped``: an 8-bit counter and times modulo 0.65536 s (CAN), else 16 bits and absolute (serial)."""
    rng = np.random.default_rng(seed)
    out = []
    dev = {"seq": int(rng.integers(0, 1 << 16)), "t": 5.0 + float(rng.random()), "theta": float(rng.normal(0, 3)),
           "omega": float(rng.uniform(-3, 3)), "az": None, "intake": None, "host": 0.0}

    def make(dt=1e-3, dtheta=None):
        dev["seq"] += 1
        dev["t"] += dt
        dev["theta"] += dev["omega"] * dt if dtheta is None else dtheta
        az = dev["az"] if dev["az"] is not None else 9.81 + float(rng.normal(0, 0.1))
        intake = dev["intake"]
        if intake is None:
            intake = dev["t"] + dev["host"] + 0.002 + float(rng.random()) * 1e-4
        seq = dev["seq"] % (256 if wrapped else 1 << 16)
        t = math.fmod(dev["t"], 0.65536) if wrapped else dev["t"]
        theta = math.remainder(dev["theta"], 2 * math.pi)
        return [seq, t, az, theta, intake]

    out += [make() for _ in range(200)]
    for event, k in events:
        if event == "run":
            out += [make() for _ in range(k)]
        elif event == "lose":
            for _ in range(k):
                make()
        elif event == "dup":
            out.append(list(out[-1]))
        elif event == "swap":
            a, b = make(), make()
            out += [b, a]
        elif event == "delay":
            late = make()
            out += [make() for _ in range(k % 7 + 1)] + [late]
        elif event == "restart":
            dev["seq"] = k - 1
            out.append(make())
        elif event == "reboot":
            dev["host"] += dev["t"] - k * 1e-3
            dev["seq"], dev["t"] = -1, k * 1e-3 - 1e-3
            out.append(make())
        elif event in ("stuck", "repeat"):
            dev["az"] = 9.81 + float(rng.normal(0, 0.1))
            out += [make() for _ in range(k if event == "stuck" else k % 14 + 1)]
            dev["az"] = None
        elif event in ("burst", "stall"):
            dev["intake"] = dev["t"] + dev["host"] + k * 1e-3 + (0.302 if event == "stall" else 0.002)
            out += [make() for _ in range(k)]
            dev["intake"] = None
        elif event == "jump":
            out.append(make(dtheta=2.0))
        elif event == "late":
            out.append(make(dt=1.7e-3))
        elif event == "early":
            out.append(make(dt=0.4e-3))
    for i in range(1, len(out)):  # arrival times never go backwards
        out[i][4] = max(out[i][4], out[i - 1][4])
    return [list(col) for col in zip(*out)]


def stream_state(s: WheelStream) -> tuple:
    return (s._period, s._omega, s._last_seq, s._last_t, s._last_theta, s._last_raw_t, s._last_intake,
            s._prev_az, s._stuck, tuple(s._held), tuple(sorted(s.counters().items())), s._t_offset, s._anchor_t,
            s._anchor_steps, tuple(s.events))


def same_samples(a: WheelSamples, b: WheelSamples) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
               for f in ("t", "az", "theta", "slip", "filled", "intake"))


@settings(max_examples=100, deadline=None)
@given(events=st.lists(st.tuples(st.sampled_from(EVENTS), st.integers(1, 400)), max_size=25),
       splits=st.lists(st.integers(1, 400), min_size=1, max_size=30), link=st.sampled_from(sorted(LINKS)),
       seed=st.integers(0, 2**32 - 1))
def test_batches_give_what_frame_by_frame_gives_bit_for_bit(events, splits, link, seed):
    """The vectorised run of plain frames (calls of 32 frames or more) against the rules applied
    one frame at a time: the same samples to the bit, the same counters and state, whatever the
    events and however the frames are split between calls."""
    kwargs, timed = LINKS[link]
    seq, t, az, theta, intake = frames_with_events(events, "time_modulus" in kwargs, seed)
    if not timed:
        intake = None
    one, batched = WheelStream(**kwargs), WheelStream(**kwargs)

    def part(i, j):
        return seq[i:j], t[i:j], az[i:j], theta[i:j], None if intake is None else intake[i:j]

    ref = [one.add(*part(i, i + 1)) for i in range(len(t))]
    got, i = [], 0
    for size in [200] + splits * (len(t) // sum(splits) + 1):  # 200 plain frames in one call first
        got.append(batched.add(*part(i, i + size)))
        i += size
        if i >= len(t):
            break
    ref.append(one.flush())
    got.append(batched.flush())
    assert same_samples(WheelSamples.concatenate(ref), WheelSamples.concatenate(got))
    assert stream_state(one) == stream_state(batched)
    assert one._fast_frames == 0 and batched._fast_frames >= 200 - 32 - 1  # both ways were taken


def test_record_paths():
    assert record_path("run.csv", 0) == "run.csv"
    assert record_path("run.csv", 2) == "run.wheel2.csv"
    assert record_path("run_{wheel}.csv", 0) == "run_0.csv"


# --- live, over a real pty, device and estimator in their own processes -------------------------


def test_live_serial_estimates_every_intact_cycle_and_never_a_damaged_one(tmp_path):
    device_report = tmp_path / "device.json"
    live_report = tmp_path / "live.json"
    with Stopping() as procs:
        dev = procs.add(firmware_sim(
            "serial", "--cycles", "6", "--speed", "16", "--noise", "0.01", "--seed", "4", "--wheels", "2",
            "--send-reference", "--report", str(device_report), "--linger", "0.3",
            "--fault", f"drop@{window(1):.3f}:n=1,wheel=0",  # one lost frame
            "--fault", f"corrupt@{window(3):.3f}:n=2,wheel=1",  # corrupted bytes
            "--fault", f"stuck@{window(4, 0.2):.3f}:n=150,wheel=0",  # a stuck sensor
            "--fault", f"unknown-ids@{window(2):.3f}:n=6"))  # frames of an unknown type
        port = serial_device(dev)
        est = procs.add(slipest_cmd("serial", port, "--cycles", "6", "--idle-timeout", "3", "--duration", "60",
                                    "--report", str(live_report)))
        assert dev.wait(60) == 0, dev.stderr
        stop_once_said(est, ": disconnected (")  # the device's end read: the 6th cycle is closed at the stop
        assert est.wait(60) == 0, est.stderr
    got = rows(est)
    # a lost frame and two corrupted ones are short holes: bridged, the cycle estimated and marked 'repaired';
    # 150 ms of a stuck sensor is a long one: flagged, never estimated
    bad = {(0, 4): "nan"}
    repaired = {(0, 1): 1, (1, 3): 2}
    for key, quality in bad.items():
        assert got[key]["quality"] == quality and got[key]["slip"] == "nan"
    for wheel in (0, 1):
        for k in range(6):
            if (wheel, k) in bad:
                continue
            r = got[(wheel, k)]
            want = "repaired" if (wheel, k) in repaired else "ok"
            assert r["quality"] == want and 0.1 < float(r["slip"]) < 0.45, r  # true slip 0.25
            assert int(r["n_repaired"]) == repaired.get((wheel, k), 0)
    rep = json.loads(live_report.read_text())
    dev_rep = json.loads(device_report.read_text())
    src, wheels = rep["source"], rep["estimation"]
    assert src["crc_errors"] + src["malformed"] >= 2 + 6 and src["malformed"] >= 6
    lost = wheels["wheel0"]["frames_lost"] + wheels["wheel1"]["frames_lost"]
    assert lost == dev_rep["injected"]["frames_lost"] == 3  # every loss accounted for, per wheel too
    assert wheels["wheel0"]["frames_lost"] == 1 and wheels["wheel1"]["frames_lost"] == 2
    assert wheels["wheel0"]["stuck_runs"] == 1 and wheels["wheel0"]["stuck_samples"] >= 100
    assert wheels["wheel0"]["restarts"] == wheels["wheel1"]["restarts"] == 0  # no other device read as this one
    assert "counters:" in est.stderr


def test_live_serial_survives_the_device_disconnecting_and_coming_back(tmp_path):
    link = tmp_path / "imu"
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--link", str(link), "--cycles", "7", "--speed", "8", "--noise", "0.01",
                                     "--seed", "5", "--fault", f"disconnect@{window(2):.3f}:down=1.0", "--settle",
                                     "0.05", "--linger", "0.3"))
        serial_device(dev)
        est = procs.add(slipest_cmd("serial", str(link), "--cycles", "7", "--idle-timeout", "3", "--duration", "60"))
        dev.wait_line("streaming", timeout=60)
        time.sleep(0.3)
        est.signal(signal.SIGUSR1)  # counters on demand, without stopping
        assert dev.wait(60) == 0
        stop_once_said(est, "reopened", ": disconnected (")  # after the fault's outage, the device's end
        assert est.wait(60) == 0, est.stderr
    got = rows(est)
    assert got[(0, 2)]["quality"] != "ok"  # the cycle of the outage
    assert all(got[(0, k)]["quality"] == "ok" for k in (4, 5))  # estimating again after the reconnection
    assert "disconnected" in est.stderr and "reopened" in est.stderr
    assert any("link back" in line for line in dev.lines)
    assert est.stderr.count("counters:") == 2  # on SIGUSR1, and at exit


def test_a_pseudo_terminal_that_went_away_is_not_reopened_under_another_program(tmp_path):
    """A /dev/pts/N that went away never comes back: the next pseudo-terminal any program opens gets its number.
    Reopening it read that program's frames as this device's, a restart of it, which flags the cycle it falls in
    'gap' (the live test above, under load, when a neighbour's firmware-sim got the number before the stop). The
    source ends instead; a link to a pseudo-terminal is reopened as before (the disconnection test above)."""
    import os
    import select

    from slipest.io.serial_source import SerialSource, pty_node

    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    os.symlink(path, tmp_path / "imu")
    assert pty_node(path) and not pty_node(str(tmp_path / "imu")) and not pty_node("/dev/ttyUSB0")
    source = SerialSource(path, reopen_interval=0.01)
    held = []
    try:
        source.start(wait_open=5)
        os.close(master)  # the device goes...
        deadline = time.monotonic() + 10
        while source.counters()["disconnects"] == 0 and time.monotonic() < deadline:
            time.sleep(0.005)
        while not held or os.ttyname(held[-1]) != path:  # ...and another program's pseudo-terminal gets its number
            assert len(held) < 512
            held += os.openpty()
        os.close(held.pop())
        other = held[-1]
        poll = select.poll()
        poll.register(other, select.POLLHUP)  # POLLHUP while no reader has the slave open
        deadline = time.monotonic() + 0.5
        while poll.poll(0) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert poll.poll(0), "the source opened another program's pseudo-terminal"
        assert source.ended.wait(5) and source.counters()["reopen_attempts"] == 0
        said = " ".join(source.notices())
        assert f"{path}: disconnected (" in said and "not reopened" in said and "--link" in said
    finally:
        source.close()
        for fd in held:
            os.close(fd)


def test_record_is_complete_after_sigterm_and_replays_to_the_same_estimates(tmp_path):
    rec = tmp_path / "run.csv"
    report = tmp_path / "live.json"
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--cycles", "30", "--speed", "8", "--noise", "0.01", "--seed", "6",
                                     "--fault", f"drop@{window(1):.3f}:n=2"))
        port = serial_device(dev)
        est = procs.add(slipest_cmd("serial", port, "--record", str(rec), "--report", str(report)))
        est.wait_line(r"^0,3,", timeout=60)  # a few cycles estimated live
        est.signal(signal.SIGTERM)
        assert est.wait(30) == 0
    live = json.loads(report.read_text())
    assert live["reason"] == "interrupted (SIGTERM)"
    log = read_log(rec)
    assert len(log) == live["estimation"]["wheel0"]["rows_recorded"] == live["estimation"]["wheel0"]["samples_out"]
    assert np.isnan(log.az).sum() == 2  # the lost frames, as the estimator saw them
    assert log.metadata["nL"] == "4" and (np.diff(log.t) > 0).all()
    # `slipest replay` reads the recording back and gives what was printed live, column for column
    replay = slipest_cmd("replay", str(rec))
    assert replay.wait(60) == 0, replay.stderr
    replayed = estimate_output.parse_rows(replay.lines)
    printed = rows(est)
    assert len(replayed) >= 4 and replay.lines[0] == estimate_output.header()
    for r in replayed:
        live_row = printed[(0, int(r["cycle"]))]
        assert live_row["quality"] == r["quality"] and live_row["n_samples"] == r["n_samples"]
        for col in ("slip", "slip_std", "dphi", "dphi_std", "kS", "delta_a"):
            assert float(live_row[col]) == pytest.approx(float(r[col]), rel=1e-4, nan_ok=True), col
