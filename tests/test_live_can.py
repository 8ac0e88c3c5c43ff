"""`slipest can` on live buses: the CAN server in its own process, a closed loop, can.player, bus failures."""

from __future__ import annotations

import json
import math
import subprocess
import time

import can
import numpy as np
import pytest

from slipest.cli.estimate_output import parse_rows
from slipest.io.bus_args import BusConfig, BusOpenError, ReconnectingBus, parse_bus_option, parse_bus_value
from slipest.io.can_messages import (
    TIME_MOD_PERIOD,
    SlipEstimateMessage,
    decode,
    encode_imu,
)
from slipest.io.can_source import CanSource
from slipest.io.socketcand_server import start_in_thread
from slipest.live import LiveEstimation
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.online import SlipEstimator
from tests.hil_support import PY, Proc, can_server, firmware_sim, slipest_cmd, socketcand_args, vcan0_available

PERIOD = 2 * math.pi / (4 * 0.63)


def window(k: int, frac: float = 0.5) -> float:
    return (k + 0.5 + 0.5 * frac) * PERIOD


def printed(proc) -> dict[tuple[int, int], dict]:
    """The estimate rows a live command printed: (wheel, cycle) -> row."""
    return {(int(r["wheel"]), int(r["cycle"])): r for r in parse_rows(proc.lines, ("wheel",))}


# --- bus arguments (pure) -------------------------------------------------------------------------


@pytest.mark.parametrize("text,value", [("500000", 500000), ("0x1F", 31), ("1.5", 1.5), ("true", True),
                                        ("off", False), ("none", None), ("127.0.0.1", "127.0.0.1")])
def test_bus_option_values_are_typed(text, value):
    assert parse_bus_value(text) == value and type(parse_bus_value(text)) is type(value)


def test_bus_option_needs_key_equals_value():
    assert parse_bus_option("port=29536") == ("port", 29536)
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_bus_option("port")


def test_a_missing_socketcand_server_fails_at_once_with_a_hint():
    t0 = time.monotonic()
    with pytest.raises(BusOpenError, match="slipest can-server"):
        BusConfig("socketcand", "vcan0", {"host": "127.0.0.1", "port": 9}).open()
    assert time.monotonic() - t0 < 3  # python-can alone would retry for 10 s


def test_socketcan_without_the_kernel_says_what_to_do_instead():
    ok, _ = vcan0_available()
    if ok:
        pytest.skip("SocketCAN is available here")
    with pytest.raises(BusOpenError, match="can-server"):
        BusConfig("socketcan", "vcan0", {}).open()


# --- over the CAN server, every part in its own process ---------------------------------------------


def test_closed_loop_estimates_come_back_on_the_bus_and_decode_with_the_dbc(tmp_path):
    server, port = can_server()
    report = tmp_path / "live.json"
    dev_report = tmp_path / "device.json"
    est = dev = None
    listener = None
    try:
        listener = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
        est = slipest_cmd("can", *socketcand_args(port), "--cycles", "7", "--idle-timeout", "3", "--duration", "60",
                          "--report", str(report), "--sim-speed", "12")
        est.wait_err("listening on CAN bus", timeout=60)
        dev = firmware_sim("can", *socketcand_args(port), "--cycles", "7", "--speed", "12", "--noise", "0.01",
                           "--seed", "8", "--send-reference", "--report", str(dev_report),
                           "--fault", f"drop@{window(2):.3f}:n=1", "--fault", f"unknown-ids@{window(1):.3f}:n=13")
        estimates = {}
        deadline = time.monotonic() + 60
        drain_until = None
        while time.monotonic() < deadline and (drain_until is None or time.monotonic() < drain_until):
            msg = listener.recv(0.1)
            rec = decode(msg) if msg is not None else None
            if isinstance(rec, SlipEstimateMessage):
                estimates[rec.counter] = rec
            if drain_until is None and est.p.poll() is not None:
                drain_until = time.monotonic() + 0.5  # the last estimates may still be on their way
        assert dev.wait(30) == 0 and est.wait(30) == 0, est.stderr
    finally:
        for p in (dev, est, server):
            if p is not None:
                p.stop()
        if listener is not None:
            listener.shutdown()
    rows = printed(est)
    assert {k for _, k in rows} >= set(range(6))
    for (_, k), row in rows.items():
        msg = estimates[k % 256]  # one SlipEstimate per leg cycle, back on the bus
        if row["quality"] in ("ok", "repaired"):  # DBC Quality 0 OK, 1 REPAIRED
            assert msg.quality == ("ok", "repaired").index(row["quality"])
            assert msg.slip == pytest.approx(float(row["slip"]), abs=1e-4)
            assert msg.dphi == pytest.approx(float(row["dphi"]), abs=1e-4)
        else:
            assert msg.quality == 15 and math.isnan(msg.slip)  # flagged: INVALID, no number
    assert rows[(0, 2)]["quality"] == "repaired", (rows, est.stderr)  # the cycle that lost a message: bridged
    assert all(rows[(0, k)]["quality"] == "ok" for k in (0, 1, 3, 4, 5))
    live = json.loads(report.read_text())
    dev_rep = json.loads(dev_report.read_text())
    assert live["source"]["unknown_id"] == dev_rep["injected"]["unknown_sent"] == 13
    assert live["estimation"]["wheel0"]["frames_lost"] == dev_rep["injected"]["frames_lost"] == 1
    assert live["estimation"]["wheel0"]["references"] == 7
    assert live["source"]["published"] == len(rows)


def test_the_estimator_and_device_reconnect_when_the_server_dies_and_comes_back(tmp_path):
    server, port = can_server()
    report = tmp_path / "live.json"
    est = dev = server2 = None
    try:
        est = slipest_cmd("can", *socketcand_args(port), "--cycles", "18", "--idle-timeout", "8",
                          "--duration", "60", "--report", str(report), "--sim-speed", "4")
        est.wait_err("listening on CAN bus", timeout=60)
        # 20 cycles: the outage (a new server's start-up and the device's back-off, 2-4 s of wall time under load,
        # 5-10 cycles at 4x) leaves cycles to estimate after it
        dev = firmware_sim("can", *socketcand_args(port), "--cycles", "20", "--speed", "4", "--noise", "0.01",
                           "--seed", "9")
        dev.wait_line("streaming", timeout=60)
        est.wait_line(r"^0,1,", timeout=30)
        server.stop()  # the bus is gone: recv returns None forever, send raises BrokenPipeError
        server2 = Proc([PY, "-m", "slipest.cli.main", "can-server", "--port", str(port)])
        server2.wait_line("listening on", timeout=20)
        assert dev.wait(60) == 0
        assert est.wait(60) == 0, est.stderr
    finally:
        for p in (dev, est, server, server2):
            if p is not None:
                p.stop()
    live = json.loads(report.read_text())
    rows = printed(est)
    assert live["source"]["bus_reconnects"] >= 1 and live["source"]["bus_errors"] >= 1
    assert "reconnected" in est.stderr
    assert any("reconnected" in line for line in dev.lines)
    last = max(k for _, k in rows)
    quality = [rows[(0, k)]["quality"] for k in range(last + 1)]
    assert live["estimation"]["wheel0"]["frames_lost"] > 0  # the outage is a counted loss...
    flagged = [k for k in range(2, last) if quality[k] != "ok"]
    assert flagged, quality  # ...and its cycles are flagged
    assert last >= 16 and quality[flagged[-1] + 1:flagged[-1] + 3] == ["ok", "ok"], quality  # estimating again


# --- python-can's own tools, in-process pieces ---------------------------------------------------


def test_can_player_replays_a_recorded_log_into_the_estimator(tmp_path):
    sc = Scenario.constant(4, noise_g=0.01, seed=11)
    s = simulate_stream(sc)
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as writer:
        for i in range(len(s)):
            msg = encode_imu(0, i, s.az[i], s.theta[i], s.t[i])
            msg.timestamp = 1000.0 + s.t[i] * 0.1  # replayed 10x faster than it was driven
            msg.channel = "vcan0"
            writer.on_message_received(msg)
    host, port, stop = start_in_thread()
    got = []
    source = CanSource(BusConfig("socketcand", "vcan0", {"host": host, "port": port})).start(wait_open=5)
    live = LiveEstimation(source, sim_speed=None, on_estimate=lambda w, e, i: got.append(e))
    try:
        stop.wait_for_clients(1)
        player = subprocess.Popen([PY, "-m", "can.player", "-i", "socketcand", "-c", "vcan0", "--bus-kwargs",
                                   f"host={host}", f"port={port}", "--", str(log)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            batches = source.get(0.1)
            if batches:
                live.feed(batches)
            elif player.poll() is not None:
                break
        assert player.wait(10) == 0, player.stderr.read()
    finally:
        source.close()
        live.close()
        stop()
    # the same samples, as the messages carry them, estimated offline
    dec = [decode(encode_imu(0, i, s.az[i], s.theta[i], s.t[i])) for i in range(len(s))]
    t = np.cumsum(np.r_[dec[0].time_mod, np.mod(np.diff([d.time_mod for d in dec]), TIME_MOD_PERIOD)])
    offline = SlipEstimator()
    expected = offline.push_many(t, [d.az for d in dec], [d.theta for d in dec]) + offline.finish()
    assert [e.quality for e in got] == [e.quality for e in expected]
    assert sum(e.quality == "ok" for e in got) == 4  # 4 cycles driven, 4 estimated (the live run's close finishes)
    for a, b in zip(got, expected):
        if a.quality == "ok":
            assert a.slip == pytest.approx(b.slip, abs=1e-6)
    assert source.counters()["ok"] == len(s) and live.counters()["wheel0"]["frames_lost"] == 0


def test_reconnecting_bus_reports_a_dead_server_instead_of_spinning():
    host, port, stop = start_in_thread()
    events = []
    bus = ReconnectingBus(BusConfig("socketcand", "vcan0", {"host": host, "port": port}), on_event=events.append,
                          max_backoff=0.2)
    try:
        assert bus.open(wait=5)
        stop()
        t0 = time.thread_time()
        for _ in range(5):
            assert bus.recv(0.1) is None
        assert time.thread_time() - t0 < 0.25  # no busy loop
        assert bus.errors == 1 and not bus.connected and "reconnecting" in events[0]
        assert bus.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False)) is False
        assert bus.send_failed == 1
    finally:
        bus.shutdown()


@pytest.mark.skipif(not vcan0_available()[0], reason=vcan0_available()[1] or "vcan0 available")
def test_live_over_socketcan_vcan0(tmp_path):
    est = slipest_cmd("can", "-i", "socketcan", "-c", "vcan0", "--idle-timeout", "1", "--duration", "60")
    dev = None
    try:
        time.sleep(3)
        dev = firmware_sim("can", "-i", "socketcan", "-c", "vcan0", "--cycles", "4", "--speed", "10", "--noise", "0.01")
        assert dev.wait(60) == 0 and est.wait(60) == 0, est.stderr
    finally:
        for p in (dev, est):
            if p is not None:
                p.stop()
    assert sum(row["quality"] == "ok" for row in printed(est).values()) >= 2
