"""The live view (`--view`): a real Foxglove WebSocket client over loopback, against `slipest can` fed by
firmware-sim over the CAN server, every part in its own process; a viewer that stops reading; the
install without the extra."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from slipest.io.log_csv import read_log
from slipest.online import ESTIMATE_FIELDS, ESTIMATED
from tests.hil_support import PY, Stopping, can_server, firmware_sim, serial_device, slipest_cmd, socketcand_args

pytest.importorskip("foxglove", reason="the live view needs foxglove-sdk: pip install '.[view]'")
pytest.importorskip("websockets", reason="the test client needs websockets (pip install '.[test]')")
pytest.importorskip("google.protobuf", reason="the test client decodes protobuf (pip install '.[test]')")

from tests.foxglove_client import FoxgloveClient, decode  # noqa: E402

PERIOD = 2 * math.pi / (4 * 0.63)
RATE = 100.0  # the view's default: decimated samples per second of device time


def window(k: int, frac: float = 0.5) -> float:
    return (k + 0.5 + 0.5 * frac) * PERIOD


def view_port(proc) -> int:
    proc.wait_err("live view on ws://", timeout=60)
    return int(re.search(r"live view on ws://127\.0\.0\.1:(\d+)", proc.stderr).group(1))


def jsonl_rows(proc) -> dict[int, dict]:
    return {r["cycle"]: r for r in (json.loads(line) for line in proc.lines if line.startswith("{"))}


def test_a_foxglove_client_gets_the_estimates_and_the_decimated_samples_the_estimator_used(tmp_path):
    rec = tmp_path / "samples.csv"
    report = tmp_path / "live.json"
    with Stopping() as procs:
        server, port = can_server()
        procs.add(server)
        est = procs.add(slipest_cmd("can", *socketcand_args(port), "--view", "0", "--format", "jsonl", "--record",
                                    str(rec), "--report", str(report), "--cycles", "5", "--idle-timeout", "3",
                                    "--duration", "60"))
        client = FoxgloveClient(view_port(est))
        assert client.ready.wait(10) and client.error is None
        est.wait_err("listening on CAN bus", timeout=30)
        dev = procs.add(firmware_sim("can", *socketcand_args(port), "--cycles", "6", "--speed", "10", "--noise", "0.01",
                                     "--seed", "4", "--fault", f"drop@{window(2):.3f}:n=1"))
        assert est.wait(60) == 0, est.stderr
        dev.wait(30)
        time.sleep(0.3)
        client.close()
    assert client.subprotocol in ("foxglove.websocket.v1", "foxglove.sdk.v1")
    assert client.server_info["name"] == "slipest"
    topics = {"/slipest/wheel0/estimate", "/slipest/wheel0/imu", "/slipest/wheel0/joint_states", "/slipest/log"}
    assert client.topics() == topics
    schemas = {t: (client.channel(t)["encoding"], client.channel(t)["schemaName"]) for t in topics}
    assert schemas == {"/slipest/wheel0/estimate": ("json", "slipest.Estimate"),
                       "/slipest/wheel0/imu": ("json", "slipest.ImuSample"),
                       "/slipest/wheel0/joint_states": ("protobuf", "foxglove.JointStates"),
                       "/slipest/log": ("protobuf", "foxglove.Log")}
    schema = json.loads(client.channel("/slipest/wheel0/estimate")["schema"])
    assert set(ESTIMATE_FIELDS) <= set(schema["properties"])

    # the estimates: what was printed, field for field (NaN as null), with the 95 % band
    printed = jsonl_rows(est)
    ch = client.channel("/slipest/wheel0/estimate")
    shown = {m["cycle"]: m for m in (decode(ch, data) for _, data in client.of("/slipest/wheel0/estimate"))}
    # (a new channel's first messages wait for the viewers to subscribe; unless foxglove-sdk made the client
    # subscribe twice, see tests/foxglove_client.py, when the first one may come before it)
    may_miss = {-1} if client.resubscribed else set()
    # five whole cycles, then (the run stopped at --cycles 5) the start of the sixth, reported 'partial'; unless
    # the batch that closed the fifth also held the sixth's end (a loaded machine reads its socket late, and
    # --cycles stops once N are reached, estimating what came rather than dropping it): then the sixth is whole
    live = json.loads(report.read_text())
    assert sorted(printed) == [0, 1, 2, 3, 4, 5]
    assert live["estimation"]["wheel0"]["cycles"] == 6
    if live["estimation"]["wheel0"]["qualities"].get("partial", 0):
        assert printed[5]["quality"] == "partial"
    else:
        assert printed[5]["quality"] in ESTIMATED and printed[5]["slip"] is not None
    assert set(printed) - may_miss <= set(shown) <= set(printed)
    for k, m in shown.items():
        row = printed[k]
        assert {key: m[key] for key in row} == row
        if m["quality"] in ESTIMATED:
            assert m["slip_lo"] == pytest.approx(m["slip"] - 1.96 * m["slip_std"], abs=1e-12)
            assert m["slip_hi"] == pytest.approx(m["slip"] + 1.96 * m["slip_std"], abs=1e-12)
            if k == 5 and m["latency_ms"] is None:  # the whole sixth, closed when the stream ended: no closing
                assert live["estimation"]["wheel0"]["qualities"].get("partial", 0) == 0  # sample to time from
            else:
                assert 0 < m["latency_ms"] < 1e4
        else:
            assert m["slip"] is None and m["slip_lo"] is None
    # the lost frame: bridged, and the cycle estimated all the same, saying so
    assert shown[2]["quality"] == "repaired" and shown[2]["n_repaired"] == 1
    assert sum(m["quality"] == "ok" for k, m in shown.items() if k in (0, 1, 3, 4)) == 4 - len({0, 1, 3, 4} - set(shown))

    # the decimated samples: each one a sample the estimator got (the recording), min/max over its interval
    log = read_log(str(rec))
    t, az, theta = log.t, log.az, log.theta
    ch = client.channel("/slipest/wheel0/imu")
    imu = [(ts, decode(ch, data)) for ts, data in client.of("/slipest/wheel0/imu")]
    device_seconds = t[-1] - t[0]
    assert len(imu) >= 0.9 * device_seconds * RATE
    buckets = [math.floor(m["t"] * RATE) for _, m in imu]
    assert np.all(np.diff(buckets) == 1)  # every interval, in order, none twice
    for (_, m), (_, nxt) in zip(imu, imu[1:]):
        i = int(np.searchsorted(t, m["t"] - 5e-7))
        j = int(np.searchsorted(t, nxt["t"] - 5e-7))
        assert abs(t[i] - m["t"]) < 1e-6 and m["n"] == j - i
        assert m["theta"] == pytest.approx((theta[i] + math.pi) % (2 * math.pi) - math.pi, abs=2e-6)
        seg = az[i:j]
        assert m["lost"] == int(np.isnan(seg).sum())
        if math.isnan(az[i]):
            assert m["az"] is None
        else:
            assert m["az"] == pytest.approx(az[i], abs=1e-6)
        assert m["az_min"] == pytest.approx(np.nanmin(seg), abs=1e-6)
        assert m["az_max"] == pytest.approx(np.nanmax(seg), abs=1e-6)
    assert sum(m["lost"] for _, m in imu) == 1

    # the leg angle as a well-known JointStates message, at the same log times
    ch = client.channel("/slipest/wheel0/joint_states")
    joints = [(ts, decode(ch, data)) for ts, data in client.of("/slipest/wheel0/joint_states")]
    assert len(joints) >= len(imu) - 50  # (foxglove-sdk takes a subscription a moment after it was sent)
    assert [ts for ts, _ in joints] == [ts for ts, _ in imu[len(imu) - len(joints):]]
    for (_, js), (_, m) in zip(joints, imu[len(imu) - len(joints):]):
        (joint,) = js.joints
        assert joint.name == "wheel0_leg" and joint.position == m["theta"]
    # log times: wall clock of arrival, in order, near now
    stamps = np.array([ts for ts, _ in imu], np.int64)
    assert np.all(np.diff(stamps) >= 0) and abs(stamps[-1] / 1e9 - time.time()) < 120

    # the run's notices, as foxglove.Log
    ch = client.channel("/slipest/log")
    logs = [decode(ch, data) for _, data in client.of("/slipest/log")]
    assert any(x.message == "slipest can: 5 cycles reached" and x.level == 2 for x in logs)  # 2: INFO

    assert live["view"]["estimates"] == len(printed) and live["view"]["imu"] >= len(imu)
    assert live["view"]["queue_dropped"] == 0 and live["view"]["errors"] == 0


def test_a_viewer_that_stops_reading_slows_nothing_down(tmp_path):
    """A viewer subscribes to everything and stops reading (its socket buffer shrunk) for 1 s while the
    device streams at 20x over a pty: the server drops that viewer's backlog, the estimator loses no frame
    and estimates every cycle, and no sample waits long to be taken in; a reading viewer gets everything."""
    report = tmp_path / "live.json"
    cycles = 16
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--cycles", str(cycles + 1), "--speed", "20", "--noise", "0.01",
                                     "--seed", "5", "--settle", "1.0"))
        est = procs.add(slipest_cmd("serial", serial_device(dev), "--view", "0", "--format", "none", "--report",
                                    str(report), "--cycles", str(cycles), "--idle-timeout", "3", "--duration", "90",
                                    "--sim-speed", "20"))
        vport = view_port(est)
        stalled = FoxgloveClient(vport, stall="/slipest/wheel0/", rcvbuf=2048)
        reading = FoxgloveClient(vport)
        assert stalled.ready.wait(10) and reading.ready.wait(10)
        assert stalled.stalled.wait(30)
        # 20 s of device data meanwhile (the backlog holds 1024 messages: 5 s): 1 s at 20x, longer on a loaded
        # machine, where the device streams slower (a fixed 1 s there stalled the viewer for less than its backlog)
        start, deadline = len(reading.of("/slipest/wheel0/imu")), time.monotonic() + 30
        while (len(reading.of("/slipest/wheel0/imu")) < start + 20 * RATE and est.p.poll() is None
               and time.monotonic() < deadline):
            time.sleep(0.05)
        stalled.resume()  # read again while the run goes on: what did the server keep?
        assert est.wait(90) == 0, est.stderr
        dev.wait(30)
        time.sleep(0.3)
        stalled.close()
        reading.close()
    live = json.loads(report.read_text())
    w = live["estimation"]["wheel0"]
    assert w["frames_lost"] == 0 and live["source"]["crc_errors"] == 0
    assert w["cycles"] >= cycles and w["qualities"].get("ok", 0) >= cycles - 1  # (cycle -1: the partial start)
    assert live["view"]["queue_dropped"] == 0 and live["view"]["errors"] == 0
    published = live["view"]["imu"]
    ch = reading.channel("/slipest/wheel0/imu")
    got_reading = [decode(ch, data)["t"] for _, data in reading.of("/slipest/wheel0/imu")]
    got_stalled = [decode(ch, data)["t"] for _, data in stalled.of("/slipest/wheel0/imu")]
    assert len(got_reading) >= published - 50  # (what came before it subscribed)
    # the server dropped what the stalled viewer did not read (it keeps the newest, up to its backlog): one
    # hole, counted from the reading viewer's first message (a few messages may have reached the stalled
    # viewer's socket before it stopped reading: those come before the hole; up to 50 missing at the start
    # are the subscription's lag, as for the reading viewer); reading again, it was served to the end
    buckets = np.floor(np.r_[got_reading[0], got_stalled] * RATE).astype(np.int64)
    steps = np.diff(buckets) - 1  # intervals missing before each message of the stalled viewer
    steps[0] += 1  # (the reading viewer's first may be missing too)
    skipped = int(steps.sum())
    detail = (f"published {published}, reading {len(got_reading)}, stalled {len(got_stalled)}, missing before "
              f"message i: {[(i, int(d)) for i, d in enumerate(steps) if d][:10]}")
    assert np.all(steps >= 0), detail  # in order, none twice
    assert len(got_stalled) < 0.8 * published and skipped > 0.2 * published and steps.max() > skipped - 50, detail
    assert got_stalled[-1] == got_reading[-1], detail  # served to the end
    lat = live["latency"]
    print(f"\nstalled viewer: {len(got_stalled)} of {published} imu messages, {skipped} dropped; "
          f"reading viewer {len(got_reading)}; device->intake median {lat['device_to_intake']['median_ms']:.2f} ms, "
          f"p99 {lat['device_to_intake']['p99_ms']:.2f} ms, max {lat['device_to_intake']['max_ms']:.2f} ms; "
          f"intake->estimate p99 {lat['intake_to_estimate']['p99_ms']:.2f} ms")
    assert lat["device_to_intake"]["max_ms"] < 1000  # never held up (a blocked publisher would hold frames for seconds)


def test_the_demo_shows_its_truth_beside_the_estimates_and_its_notices():
    """``slipest demo --faults --view``: the truth of every cycle on its own topic, the estimates of the intact
    cycles near it, the damaged ones (a dropped frame, corrupted bytes, a stuck sensor) not estimated, and the
    link's notices (the disconnection) on /slipest/log with the run's start and stop (it had the link's only).
    The demo's printed quality column says what each estimate says (it printed 'ok' for 'repaired' ones)."""
    from slipest.cli.demo import DEMO_SCENARIO

    with Stopping() as procs:
        demo = procs.add(slipest_cmd("demo", "--speed", "20", "--cycles", "6", "--faults", "--view", "0"))
        client = FoxgloveClient(int(demo.wait_line(r"live view on ws://127\.0\.0\.1:(\d+)", 60).group(1)))
        assert client.ready.wait(10)
        assert demo.wait(120) == 0, demo.stderr
        client.close()
    ch = client.channel("/slipest/demo/truth")
    truth = {m["cycle"]: m for m in (decode(ch, data) for _, data in client.of("/slipest/demo/truth"))}
    seg = DEMO_SCENARIO["segment"][0]
    assert set(range(5)) <= set(truth)
    for m in truth.values():
        assert (m["slip"], m["kS"], m["phiS"], m["phiD"]) == (seg["slip"], seg["kS"], seg["phiS"], seg["phiD"])
        assert m["dphi"] == pytest.approx(seg["phiS"] - seg["phiD"], abs=1e-12)
    ch = client.channel("/slipest/wheel0/estimate")
    shown = {m["cycle"]: m for m in (decode(ch, data) for _, data in client.of("/slipest/wheel0/estimate"))}
    # the faults' cycles: the dropped frame and the corrupted bytes bridged (estimated, saying so), the stuck sensor
    # (200 samples) not estimated
    assert [shown[k]["quality"] for k in (1, 2)] == ["repaired", "repaired"]
    assert shown[3]["quality"] not in ESTIMATED and shown[3]["slip"] is None
    assert shown[4]["quality"] == "ok"
    assert all(abs(m["slip"] - seg["slip"]) < 4 * m["slip_std"] for m in shown.values() if m["quality"] in ESTIMATED)
    ch = client.channel("/slipest/log")
    logs = [decode(ch, data) for _, data in client.of("/slipest/log")]
    assert any(x.message.startswith("slipest demo: ") and "disconnected" in x.message and x.level == 3
               for x in logs), [x.message for x in logs]  # 3: WARNING
    said = [x.message for x in logs if x.level == 2]  # 2: INFO
    assert any(m.startswith("slipest demo: started: 6 leg cycles") and "virtual device pid" in m for m in said), said
    assert "slipest demo: stopping (the device finished)" in said and said[-1] == "slipest demo: the device finished"
    printed = {int(line.split()[0]): line.split()[-1] for line in demo.lines
               if re.match(r"^\s+\d+\s+[\d.]+\s+[\d.]+ ±", line)}
    assert printed and all(printed[k] == shown[k]["quality"] for k in printed), (printed, shown)


def test_without_foxglove_the_option_says_what_to_install(tmp_path):
    code = ("import sys; sys.modules['foxglove'] = None\n"
            "from slipest.cli.main import main\n"
            "sys.exit(main(['serial', '/dev/null', '--view', '0', '--duration', '1']))")
    r = subprocess.run([PY, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0
    assert "pip install 'slipest[view]'" in r.stderr and "live view" in r.stderr
    # the rover's install runs without it: no view asked, nothing imported
    code = ("import sys; sys.modules['foxglove'] = None\n"
            "from slipest.cli.main import main\n"
            "sys.exit(main(['serial', 'loop://', '--duration', '0.3', '--format', 'none']))")
    r = subprocess.run([PY, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("text,address", [("8765", ("127.0.0.1", 8765)), ("0", ("127.0.0.1", 0)),
                                          ("0.0.0.0:9000", ("0.0.0.0", 9000)), ("[::1]:8765", ("::1", 8765))])
def test_view_addresses(text, address):
    from slipest.cli.live_args import parse_view_address

    assert parse_view_address(text) == address


@pytest.mark.parametrize("text", ["", "host:", "99999", "x:y", ":80"])
def test_bad_view_addresses_are_refused(text):
    import argparse

    from slipest.cli.live_args import parse_view_address

    with pytest.raises(argparse.ArgumentTypeError, match=r"\[HOST:\]PORT"):
        parse_view_address(text)


def test_the_decimation_against_a_plain_loop():
    from slipest.live.view import decimate

    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.0005, 0.0015, 3000))
    az = rng.normal(9.8, 1.0, t.size)
    az[rng.choice(t.size, 40, replace=False)] = np.nan
    theta = np.linspace(-3, 40, t.size)
    intake = t + 100.0
    rows, carry = [], None
    for lo in range(0, t.size, 137):  # in pushes of any size
        got, carry = decimate(t[lo:lo + 137], az[lo:lo + 137], theta[lo:lo + 137], intake[lo:lo + 137], 50.0, carry)
        rows += got
    bucket = np.floor(t * 50.0)
    starts = [0] + [i for i in range(1, t.size) if bucket[i] != bucket[i - 1]]
    assert len(rows) == len(starts) - 1  # the last interval waits for more
    for row, a, b in zip(rows, starts, starts[1:]):
        seg = az[a:b]
        assert row["t"] == t[a] and row["n"] == b - a and row["lost"] == int(np.isnan(seg).sum())
        assert row["az"] == (None if math.isnan(az[a]) else az[a])
        assert row["az_min"] == np.nanmin(seg) and row["az_max"] == np.nanmax(seg)
        assert row["theta"] == pytest.approx((theta[a] + math.pi) % (2 * math.pi) - math.pi, abs=1e-12)
        assert row["intake"] == intake[b - 1]


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
