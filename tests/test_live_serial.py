"""`slipest serial` on a live stream: firmware-sim in one process, the estimator in another, a real pty."""

from __future__ import annotations

import json
import math
import signal
import time

import numpy as np
import pytest

from slipest.cli import estimate_output
from slipest.io.device_stream import WheelSamples, WheelStream
from slipest.io.log_csv import read_log
from slipest.live.recording import record_path
from tests.hil_support import Stopping, firmware_sim, serial_device, slipest_cmd

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
        assert est.wait(60) == 0, est.stderr
    got = rows(est)
    bad = {(0, 1): "nan", (1, 3): "nan", (0, 4): "nan"}
    for key, quality in bad.items():
        assert got[key]["quality"] == quality and got[key]["slip"] == "nan"  # flagged, never estimated
    for wheel in (0, 1):
        for k in range(5):
            if (wheel, k) in bad:
                continue
            r = got[(wheel, k)]
            assert r["quality"] == "ok" and 0.1 < float(r["slip"]) < 0.45, r  # true slip 0.25
    rep = json.loads(live_report.read_text())
    dev_rep = json.loads(device_report.read_text())
    src, wheels = rep["source"], rep["estimation"]
    assert src["crc_errors"] + src["malformed"] >= 2 + 6 and src["malformed"] >= 6
    lost = wheels["wheel0"]["frames_lost"] + wheels["wheel1"]["frames_lost"]
    assert lost == dev_rep["injected"]["frames_lost"] == 3  # every loss accounted for, per wheel too
    assert wheels["wheel0"]["frames_lost"] == 1 and wheels["wheel1"]["frames_lost"] == 2
    assert wheels["wheel0"]["stuck_runs"] == 1 and wheels["wheel0"]["stuck_samples"] >= 100
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
        assert est.wait(60) == 0, est.stderr
    got = rows(est)
    assert got[(0, 2)]["quality"] != "ok"  # the cycle of the outage
    assert all(got[(0, k)]["quality"] == "ok" for k in (4, 5))  # estimating again after the reconnection
    assert "disconnected" in est.stderr and "reopened" in est.stderr
    assert any("link back" in line for line in dev.lines)
    assert est.stderr.count("counters:") == 2  # on SIGUSR1, and at exit


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
