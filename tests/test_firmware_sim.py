"""The virtual device (firmware_sim): frames, pacing, faults, report; real ptys and buses."""

from __future__ import annotations

import json
import math
import os
import select
import threading
import time
import tty

import can
import numpy as np
import pytest
import serial

from firmware_sim.can_link import CanLink
from firmware_sim.device import KIND_IMU, Device, ScenarioFeed, wrap_angle
from firmware_sim.faults import FaultInjector, FaultPlan, parse_fault
from firmware_sim.link import FRAME_TABLE_DTYPE, Link
from firmware_sim.serial_link import PtyLink
from slipest.io.bus_args import BusConfig
from slipest.io.can_messages import CanDecoder, ImuMessage, SlipReferenceMessage
from slipest.io.serial_frames import FrameDecoder, ImuSample, SlipReference, encode_imu_sample
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from tests.hil_support import firmware_sim, serial_device

PERIOD = 2 * math.pi / (4 * 0.63)  # one leg cycle of the default wheel-leg [s]


def two_cycles(seed=1, slip=(0.2, 0.3)) -> Scenario:
    return Scenario.per_cycle(StickSlipParams(), imu={"noise_g": 0.01, "seed": seed}, slip=list(slip))


# --- the feed (pure) ------------------------------------------------------------------------------


def test_feed_interleaves_wheels_in_time_order_with_a_reference_before_each_cycle():
    feed = ScenarioFeed([two_cycles(1), two_cycles(2)], send_reference=True)
    tables = list(feed)
    assert all(tb.dtype == FRAME_TABLE_DTYPE for tb in tables)
    kind, wheel, seq, t, theta, slip = (np.concatenate([tb[name] for tb in tables])
                                        for name in ("kind", "wheel", "seq", "t", "theta", "slip"))
    assert (np.diff(t) >= 0).all()
    imu = kind == KIND_IMU
    for w in (0, 1):
        s = seq[imu & (wheel == w)]
        assert (s == np.arange(s.size)).all()  # one counter per wheel, +1 per frame
        assert (seq[~imu & (wheel == w)] == [0, 1]).all()  # one reference per cycle
    assert imu.sum() == feed.expected_imu_frames
    assert theta[imu].min() >= -math.pi and theta[imu].max() < math.pi  # wrapped like a device
    refs = np.flatnonzero(~imu)
    assert (kind[refs[:2] + 2] == KIND_IMU).all() and t[refs[2]] == pytest.approx(PERIOD, abs=1e-3)
    assert slip[refs].tolist() == pytest.approx([0.2, 0.2, 0.3, 0.3])
    # the wheels' noise differs (own seeds), the physics does not
    az0 = np.concatenate([tb["az"][(tb["kind"] == KIND_IMU) & (tb["wheel"] == 0)] for tb in tables])
    az1 = np.concatenate([tb["az"][(tb["kind"] == KIND_IMU) & (tb["wheel"] == 1)] for tb in tables])
    assert not np.array_equal(az0, az1) and abs(az0.mean() - az1.mean()) < 0.01


def test_feed_duration_stops_the_stream():
    feed = ScenarioFeed([two_cycles()], duration=1.0)
    t = np.concatenate([tb["t"] for tb in feed])
    assert t.size == 1000 and t[-1] < 1.0


def test_feed_follows_a_changing_leg_speed_and_wheels_must_share_it():
    omegas = [0.5, 0.5, 1.0, 0.8]
    drive = [Scenario.per_cycle(StickSlipParams(), imu={"noise_g": 0.01, "seed": s}, slip=[0.2] * 4, omega=omegas)
             for s in (1, 2)]
    tables = list(ScenarioFeed(drive))
    imu = np.concatenate(tables)
    imu = imu[imu["kind"] == KIND_IMU]
    duration = sum(2 * math.pi / (4 * w) for w in omegas)
    # one frame per wheel every millisecond over the four cycles' total duration, in time order
    assert imu.size == ScenarioFeed(drive).expected_imu_frames == 2 * math.ceil(duration * 1000 - 1e-9)
    assert np.all(np.diff(imu["t"]) >= 0)
    last = imu[imu["cycle"] == 2]
    assert last["t"].max() - last["t"].min() == pytest.approx(2 * math.pi / (4 * 1.0), abs=2e-3)
    # a duration inside cycle 2 keeps cycles 0-2
    assert ScenarioFeed(drive, duration=2 * math.pi / (4 * 0.5) * 2 + 0.1).n_cycles == 3
    other = Scenario.per_cycle(StickSlipParams(), imu={"noise_g": 0.01, "seed": 3}, slip=[0.2] * 4, omega=[0.5] * 4)
    with pytest.raises(ValueError, match="wheel 1: .*same rate, legs, leg speeds"):
        ScenarioFeed([drive[0], other])


def test_wrap_angle_is_minus_pi_to_pi():
    got = wrap_angle([math.pi, -math.pi, 3 * math.pi + 0.1]).tolist()
    assert got == pytest.approx([-math.pi, -math.pi, -math.pi + 0.1])


# --- the Link contract ---------------------------------------------------------------------------


def _mixed_rows(table) -> list[int]:
    """Some IMU rows of both wheels and the references, in send order."""
    refs = np.flatnonzero(table["kind"] != KIND_IMU)
    assert refs.size >= 2
    return sorted(set(range(0, len(table), 97)) | set(refs.tolist()))


def test_serial_link_encodes_table_rows_as_frames_in_order():
    table = next(iter(ScenarioFeed([two_cycles(1), two_cycles(2)], send_reference=True)))
    t_us = 10**12 + np.arange(len(table), dtype=np.int64) * 167
    table["seq"][-1] = 70000  # a counter beyond 16 bits: the link reduces it
    idx = _mixed_rows(table) + [len(table) - 1]
    items = PtyLink().encode(table, t_us, idx)
    assert len(items) == len(idx) and all(isinstance(item, bytes) for item in items)
    frames = FrameDecoder().feed(b"".join(items))
    want = []
    for k in idx:
        r = table[k]
        if r["kind"] == KIND_IMU:
            want.append(ImuSample(int(r["wheel"]), int(r["seq"]) % 65536, int(t_us[k]),
                                  float(np.float32(r["az"])), float(np.float32(r["theta"]))))
        else:
            want.append(SlipReference(int(r["wheel"]), int(r["seq"]), int(t_us[k]), float(np.float32(r["slip"]))))
    assert frames == want


def test_can_link_encodes_table_rows_as_dbc_messages_in_order():
    table = next(iter(ScenarioFeed([two_cycles(1), two_cycles(2)], send_reference=True)))
    t_us = 10**12 + np.arange(len(table), dtype=np.int64) * 167
    idx = _mixed_rows(table)
    link = CanLink(BusConfig("virtual", "fsim-encode", {}))
    try:
        items = link.encode(table, t_us, idx)
    finally:
        link.close()
    dec = CanDecoder()
    got = [dec.decode(msg) for msg in items]
    assert len(got) == len(idx)
    for k, rec in zip(idx, got):
        r = table[k]
        assert rec.wheel == r["wheel"] and rec.counter == r["seq"] % 256
        assert rec.time_mod == pytest.approx((t_us[k] * 1e-6) % 0.65536, abs=1e-5)
        if r["kind"] == KIND_IMU:
            assert isinstance(rec, ImuMessage)
            assert (rec.az, rec.theta) == pytest.approx((r["az"], r["theta"]), abs=0.005)
        else:
            assert isinstance(rec, SlipReferenceMessage) and rec.slip == pytest.approx(r["slip"], abs=1e-4)


def test_links_declare_the_link_contract_and_the_device_checks_it():
    assert issubclass(PtyLink, Link) and issubclass(CanLink, Link)
    assert PtyLink.corrupts and not CanLink.corrupts

    class Incomplete(Link):  # no transport: cannot be created
        def encode_imu(self, wheel, seq, t_us, az, theta):
            return b""

    with pytest.raises(TypeError, match="abstract"):
        Incomplete()
    with pytest.raises(TypeError, match="Link"):
        Device(ScenarioFeed([two_cycles()]), object())


# --- faults (pure) --------------------------------------------------------------------------------


@pytest.mark.parametrize("text", ["bogus@1", "drop", "drop@x", "drop@1:n=0", "drop@1:size=3", "stuck@1:wheel=all",
                                  "disconnect@-1"])
def test_bad_fault_specs_are_refused_with_a_reason(text):
    with pytest.raises(ValueError, match="fault"):
        parse_fault(text)


def test_fault_spec_parsing():
    f = parse_fault("drop@2.5:n=7,wheel=all")
    assert (f.kind, f.at, f.params) == ("drop", 2.5, {"n": 7, "wheel": None})
    assert parse_fault("disconnect@1:down=0.25").params == {"down": 0.25}


def test_corrupted_frames_are_exactly_the_ones_the_decoder_rejects():
    n = 2000
    frames = [encode_imu_sample(0, i, i * 1000, 9.81, 0.0) for i in range(n)]
    inj = FaultInjector(FaultPlan(corrupt_rate=0.01, seed=5), 1)
    out, lost = inj.corrupt_bytes(frames, np.zeros(n, bool))
    changed = np.array([a != b for a, b in zip(out, frames)])
    dec = FrameDecoder()
    got = dec.feed(b"".join(out) + b"\x00")
    delivered = {f.seq for f in got}
    assert 100 < changed.sum() < 600 and inj.tally.bytes_corrupted >= changed.sum()
    # a changed frame never gets through; neither does the one after a corrupted delimiter
    assert delivered == set(np.flatnonzero(~lost).tolist())
    assert (lost >= changed).all() and lost.sum() > changed.sum()
    assert dec.counters()["seq_gaps"] == lost[1:].sum() - (lost[-1] and 1) * 0 - _trailing(lost)


def _trailing(mask) -> int:
    """Lost frames at the end: no later frame reveals them as a gap."""
    return int(np.argmax(~mask[::-1])) if mask[-1] else 0


# --- PtyLink in this process ---------------------------------------------------------------------


def _imu_burst(n: int, seq0: int = 0) -> bytes:
    return b"".join(encode_imu_sample(0, seq, seq * 1000, 9.81, 0.0) for seq in range(seq0, seq0 + n))


def _pty_reader(path: str, got: bytearray, opened: threading.Event) -> None:
    """Read the slave until the master goes away."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    opened.set()
    try:
        while True:
            try:
                data = os.read(fd, 65536)
            except OSError:  # EIO: the master is closed
                return
            if not data:
                return
            got += data
    finally:
        os.close(fd)


def test_pty_disconnect_waits_for_the_bytes_still_in_flight_to_the_reader():
    # A write to a pty master returns before a kernel worker has moved the bytes to the
    # reader's queue (FIONREAD does not see them yet): under load the drain took that for
    # "all read" and the master's close destroyed the last burst.  Many short rounds: the
    # race lost a burst in ~1% of rounds on an idle machine, more under load.
    link = PtyLink(settle=0.0)
    burst = _imu_burst(12)
    try:
        for r in range(200):
            link.open()
            got, opened = bytearray(), threading.Event()
            th = threading.Thread(target=_pty_reader, args=(link.path, got, opened), daemon=True)
            th.start()
            assert opened.wait(5)
            link.send([burst])
            link.disconnect()
            th.join(5)
            assert bytes(got) == burst, f"round {r}: {len(got)} of {len(burst)} bytes read"
    finally:
        link.close()
    assert link.bytes_discarded_at_disconnect == 0 and link.frames_discarded_at_disconnect == 0
    assert link.drains_unverified == 0


def test_pty_disconnect_counts_what_a_stalled_reader_never_read():
    # more than the reader's line discipline holds (4 KB): the rest waits in the flip buffer
    link = PtyLink(settle=0.0, drain_timeout=0.05)
    link.open()
    fd = os.open(link.path, os.O_RDWR | os.O_NOCTTY)  # a reader that never reads
    try:
        link.send([_imu_burst(400)])
        link.disconnect()
    finally:
        os.close(fd)
        link.close()
    assert link.bytes_discarded_at_disconnect == 400 * 24
    assert link.frames_discarded_at_disconnect == 400
    assert link.describe()["frames_discarded_at_disconnect"] == 400


# --- over a real pseudo-terminal, device in its own process ---------------------------------------


def _read_all(port: str, until, timeout: float = 30.0) -> tuple[list, dict]:
    dec = FrameDecoder()
    frames = []
    ser = serial.Serial(port, timeout=0.1)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline and not until():
            try:
                frames += dec.feed(ser.read(ser.in_waiting or 1))
            except (serial.SerialException, OSError):  # OSError: in_waiting (TIOCINQ) on a hung-up pty: EIO
                break  # the device closed its end: everything it sent has been read
    finally:
        ser.close()
    return frames, dec.counters()


def test_serial_device_in_another_process_reports_what_it_sent_and_injected(tmp_path):
    report, send_log = tmp_path / "report.json", tmp_path / "sent.npz"
    # window of cycle 1 (the propulsive half-stance) starts at 1.5 T
    proc = firmware_sim("serial", "--cycles", "3", "--speed", "25", "--noise", "0.01", "--seed", "3", "--wheels", "2",
                        "--send-reference", "--report", str(report), "--send-log", str(send_log), "--linger", "0.2",
                        "--fault", f"drop@{1.6 * PERIOD:.3f}:n=5,wheel=1",
                        "--fault", f"corrupt@{1.7 * PERIOD:.3f}:n=4,wheel=0",
                        "--fault", "unknown-ids@3.0:n=7",
                        "--fault", f"stuck@{2.6 * PERIOD:.3f}:n=120,wheel=0")
    try:
        frames, c = _read_all(serial_device(proc), until=lambda: proc.p.poll() is not None)
        assert proc.wait() == 0, proc.stderr
    finally:
        proc.stop()
    rep = json.loads(report.read_text())
    sent, inj = rep["sent"], rep["injected"]
    imu = [f for f in frames if isinstance(f, ImuSample)]
    refs = [f for f in frames if isinstance(f, SlipReference)]
    assert sent["imu_frames_generated"] == 2 * 7480 and sent["ref_frames_generated"] == 6
    assert (inj["frames_dropped"], inj["frames_corrupted"], inj["unknown_sent"]) == (5, 4, 7)
    assert inj["dropped_by_wheel"] == [0, 5] and inj["corrupted_by_wheel"] == [4, 0]
    # reconciliation: everything sent intact arrived, every loss is counted
    assert len(imu) + len(refs) == sent["imu_frames_sent"] + sent["ref_frames_sent"] - inj["frames_corrupted"]
    assert c["seq_gaps"] == inj["frames_lost"] == 9
    assert c["seq_gaps_by_wheel"][0] == 4 and c["seq_gaps_by_wheel"][1] == 5
    assert c["crc_errors"] + c["malformed"] >= 4 + 7
    assert len(refs) == 6 and sorted({round(r.slip, 4) for r in refs}) == [0.25]
    # the stuck sensor: 120 identical az values of wheel 0
    az0 = np.array([f.az for f in imu if f.wheel == 0], np.float32)
    run = np.flatnonzero(np.diff(az0) == 0)
    assert inj["stuck_samples"] == 120 and run.size >= 119
    assert rep["lateness"]["n"] > 0 and rep["t0_us"] > 0
    # the send log: one row per frame with the values sent; every IMU frame received is a row sent intact,
    # bit for bit, and the corrupted ones are the frames that never arrived
    log = np.load(send_log)
    status = np.asarray(log["status_names"])[log["status"]]
    is_imu = log["kind"] == 1
    rows = {(int(w), int(q)): (int(t), float(np.float32(a)), float(np.float32(th)), str(st))
            for w, q, t, a, th, st in zip(log["wheel"][is_imu], log["seq"][is_imu] % 65536, log["t_us"][is_imu],
                                          log["az"][is_imu], log["theta"][is_imu], status[is_imu])}
    assert all(rows[(f.wheel, f.seq)] == (f.t_us, f.az, f.theta, "sent") for f in imu)
    got = {(f.wheel, f.seq) for f in imu}
    corrupted = {k for k, v in rows.items() if v[3] == "corrupted"}
    assert len(corrupted) == 4 and not corrupted & got
    assert len(got) == sum(v[3] == "sent" for v in rows.values())


def test_serial_disconnect_announces_a_new_pty_behind_a_stable_link(tmp_path):
    link = tmp_path / "imu"
    report = tmp_path / "report.json"
    proc = firmware_sim("serial", "--link", str(link), "--cycles", "2", "--speed", "5", "--noise", "0.01",
                        "--fault", "disconnect@1.0:down=0.2", "--report", str(report), "--linger", "0.3")
    try:
        first = serial_device(proc)
        assert link.resolve() == type(link)(first).resolve()
        dec = FrameDecoder()
        frames = []
        errors = 0
        deadline = time.monotonic() + 30
        ser = serial.Serial(str(link), timeout=0.1)
        while time.monotonic() < deadline and proc.p.poll() is None:
            try:
                frames += dec.feed(ser.read(ser.in_waiting or 1))
            except (serial.SerialException, OSError):  # the device went away: reopen the link when it is back
                # (OSError: pyserial's in_waiting, TIOCINQ on a hung-up pty, raises a bare EIO; SerialSource
                # catches it too)
                errors += 1
                ser.close()
                dec.reset()
                while time.monotonic() < deadline and proc.p.poll() is None:
                    try:
                        ser = serial.Serial(str(link), timeout=0.1)
                        break
                    except (serial.SerialException, OSError):
                        time.sleep(0.02)
        ser.close()
        assert proc.wait() == 0
    finally:
        proc.stop()
    rep = json.loads(report.read_text())
    inj = rep["injected"]
    assert inj["disconnects"] == 1 and inj["reconnects"] == 1 and inj["frames_lost_disconnected"] > 300
    assert rep["link"]["bytes_discarded_at_disconnect"] == 0  # every sent byte was read before the cut
    assert rep["link"]["drains_unverified"] == 0
    assert errors >= 1
    assert any("fault: link back" in line for line in proc.lines)
    seqs = np.array([f.seq for f in frames])
    jumps = np.diff(seqs)
    assert (jumps >= 1).all()
    # the one hole in the sequence is the outage, exactly as long as the device says
    assert int((jumps - 1).sum()) == inj["frames_lost_disconnected"]
    assert len(frames) + inj["frames_lost_disconnected"] == rep["sent"]["imu_frames_generated"]


def test_device_stops_cleanly_on_sigterm_and_still_writes_its_report(tmp_path):
    report = tmp_path / "report.json"
    proc = firmware_sim("serial", "--cycles", "8", "--speed", "1", "--report", str(report))
    try:
        port = serial_device(proc)
        ser = serial.Serial(port, timeout=0.1)
        proc.wait_line("streaming")
        time.sleep(0.3)
        proc.signal()
        assert proc.wait(20) == 0
        ser.close()
    finally:
        proc.stop()
    rep = json.loads(report.read_text())
    assert rep["finished"] is False and 0 < rep["sent"]["imu_frames_sent"] < 8 * 2493
    assert proc.lines[-1] == "firmware-sim: stopped"


def test_a_serial_device_with_no_reader_says_it_waits_for_one_and_streams_once_one_comes():
    """A device ready to stream whose reader never came (or left before it streamed) says so, then streams once one
    comes."""
    proc = firmware_sim("serial", "--cycles", "1", "--speed", "16")
    try:
        port = serial_device(proc)
        proc.wait_line(rf"^firmware-sim: ready to stream; waiting for a peer on {port}$", timeout=60)
        assert not any("streaming" in line for line in proc.lines)
        got = b""
        with serial.Serial(port, timeout=0.1) as ser:
            deadline = time.monotonic() + 60
            while proc.p.poll() is None and time.monotonic() < deadline:  # read it all: the device ends then
                try:
                    got += ser.read(65536)
                except serial.SerialException:  # the device closed its end
                    break
        assert proc.wait(30) == 0
        assert any(line.startswith("firmware-sim: streaming") for line in proc.lines)
        assert len(FrameDecoder().feed(got)) > 1000  # one leg cycle at 1 kHz
    finally:
        proc.stop()


def _refused_in_process(capsys, monkeypatch, *argv) -> tuple[int, list[str], list[str]]:
    """``firmware-sim ARGV`` refused before it streams, run in this process (the CLI's code path without a new
    interpreter's start-up): (exit status, stdout lines, stderr lines). No link is made and nothing runs here:
    a refusal that did not come would fail the test at ``make_link``. A traceback would be an exception out of
    the test."""
    from firmware_sim import cli

    def taken(args):
        raise AssertionError(f"{argv} was taken: a link was being made")

    monkeypatch.setattr(cli, "make_link", taken)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        cli.main(list(argv))
    out, err = capsys.readouterr()
    return exc.value.code, out.splitlines(), err.splitlines()


def test_cli_names_itself_and_the_file_for_a_scenario_it_cannot_use_and_a_link_it_cannot_make(tmp_path, capsys,
                                                                                              monkeypatch):
    """QA s25: a missing scenario file was reported as "slipest simulate: cannot read scenario"; one that is not
    UTF-8 without its name; ``--link /proc/x`` only when the device opened ("No such file or directory:
    '/dev/pts/0' -> '/proc/x.26051.tmp'"). Each is refused before the run, in firmware-sim's words."""
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff[[segment]]\ncycles = 2\n")
    cases = [(["--scenario", str(tmp_path / "missing.toml")],
              f"error: cannot read scenario {tmp_path / 'missing.toml'}: No such file or directory"),
             (["--scenario", str(binary)], f"error: {binary}: not UTF-8 text (byte 0xff at offset 0)"),
             (["--link", str(tmp_path / "no_dir" / "imu")],
              f"error: --link {tmp_path / 'no_dir' / 'imu'}: no directory")]
    if os.path.isdir("/proc"):
        cases.append((["--link", "/proc/slipest_link"], "error: --link /proc/slipest_link: cannot write in /proc"))
    for argv, message in cases:
        rc, lines, err = _refused_in_process(capsys, monkeypatch, "serial", "--cycles", "1", "--wait-peer", "1", *argv)
        stderr = "\n".join(err)
        assert rc == 2 and err[-1].startswith("firmware-sim: ") and message in err[-1], stderr
        assert "slipest simulate" not in stderr and "Traceback" not in stderr and not lines


def test_cli_refuses_byte_corruption_on_can(capsys, monkeypatch):
    rc, _, err = _refused_in_process(capsys, monkeypatch, "can", "-i", "virtual", "-c", "x", "--corrupt-rate", "0.01")
    assert rc == 2
    assert "serial fault" in "\n".join(err)


# --- on a python-can bus ------------------------------------------------------------------------


def test_can_device_sends_dbc_messages_references_and_unknown_ids_on_a_virtual_bus():
    channel = "fsim-test"
    rx = can.Bus(interface="virtual", channel=channel)
    link = CanLink(BusConfig("virtual", channel, {}))
    plan = FaultPlan(scheduled=(parse_fault("unknown-ids@1.0:n=9"), parse_fault("drop@1.5:n=3")))
    feed = ScenarioFeed([two_cycles(1), two_cycles(2)], send_reference=True)
    dev = Device(feed, link, plan, speed=0, linger=0)
    dec = CanDecoder()
    got = []
    done = threading.Event()

    def receive():
        while True:
            msg = rx.recv(0.3)
            if msg is None:
                if done.is_set():
                    return
                continue
            rec = dec.decode(msg)
            if rec is not None:
                got.append(rec)

    th = threading.Thread(target=receive)
    th.start()
    try:
        rep = dev.run()
    finally:
        done.set()
        th.join(10)
        rx.shutdown()
    c = dec.counters()
    imu = [r for r in got if isinstance(r, ImuMessage)]
    refs = [r for r in got if isinstance(r, SlipReferenceMessage)]
    assert rep["injected"]["unknown_sent"] == 9 and c["unknown_id"] == 9
    assert len(refs) == 4 and sorted(r.slip for r in refs) == pytest.approx([0.2, 0.2, 0.3, 0.3], abs=1e-4)
    assert len(imu) == 2 * 4987 - 3 and c["counter_gaps"] == 3 and c["counter_gaps_by_wheel"][0] == 3
    assert {r.wheel for r in imu} == {0, 1}
    assert all(-math.pi <= r.theta <= math.pi for r in imu)


def test_device_writes_to_a_given_port_with_pyserial(tmp_path):
    master, slave = os.openpty()
    tty.setraw(slave)
    report = tmp_path / "report.json"
    proc = firmware_sim("serial", "--port", os.ttyname(slave), "--cycles", "1", "--speed", "20",
                        "--report", str(report), "--linger", "0")
    dec = FrameDecoder()
    frames = []
    expected = math.ceil(2 * math.pi / (4 * 0.63) * 1000)  # one leg cycle at 1 kHz: 2494 frames
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and len(frames) < expected:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                frames += dec.feed(os.read(master, 65536))
        assert proc.wait(30) == 0, proc.stderr
    finally:
        proc.stop()
        os.close(master)
        os.close(slave)
    assert [f.seq for f in frames] == list(range(expected)) and dec.counters()["crc_errors"] == 0
    assert json.loads(report.read_text())["link"]["type"] == "port"


# --- the command line refuses what it cannot do, before it streams -----------------------------------


def test_cli_checks_the_report_and_send_log_paths_before_the_run(tmp_path, capsys, monkeypatch):
    # a missing directory (the report used to be lost after the whole run, with a traceback), a directory named
    # as the file (the CLI in this process: see _refused_in_process)
    for option, path, why in (("--report", tmp_path / "missing" / "r.json", "no directory"),
                              ("--send-log", tmp_path / "missing" / "sent.npz", "no directory"),
                              ("--send-log", tmp_path, "is a directory")):
        rc, lines, err_lines = _refused_in_process(capsys, monkeypatch, "serial", "--cycles", "1", "--speed", "0",
                                                   option, str(path))
        stderr = "\n".join(err_lines)
        assert rc == 2
        assert f"error: {option} {path}" in stderr and why in stderr, stderr
        assert "Traceback" not in stderr and not any("serial device" in line for line in lines)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device that is always full)")
def test_a_report_that_cannot_be_written_at_the_end_is_named_in_one_line_and_the_exit_status_is_1(tmp_path):
    send_log = tmp_path / "sent.npz"
    proc = firmware_sim("serial", "--cycles", "1", "--speed", "0", "--linger", "0", "--report", "/dev/full",
                        "--send-log", str(send_log))
    try:
        frames, _ = _read_all(serial_device(proc), until=lambda: proc.p.poll() is not None)
        assert proc.wait(30) == 1, proc.stderr
    finally:
        proc.stop()
    assert "Traceback" not in proc.stderr
    assert "firmware-sim: cannot write the report /dev/full: No space left on device" in proc.err_lines
    assert proc.lines[-1] == "firmware-sim: done" and len(frames) > 2000
    assert np.load(send_log)["status"].size == 2494  # the other file is written all the same
    assert any(line.startswith("firmware-sim: sent ") for line in proc.err_lines)  # and the summary given


@pytest.mark.parametrize("option, value, why", [
    ("--speed", "-1", "time factor >= 0"),  # was a traceback out of the Device
    ("--duration", "-5", "duration > 0"),  # was taken: 0 frames sent, exit 0
    ("--seed", "-1", "not a seed"),  # was a numpy traceback once a reader had connected
])
def test_cli_refuses_a_negative_speed_duration_or_seed_in_one_line(option, value, why, capsys, monkeypatch):
    # the CLI in this process: see _refused_in_process
    rc, lines, err_lines = _refused_in_process(capsys, monkeypatch, "serial", "--cycles", "1", "--wait-peer", "5",
                                               option, value)
    stderr = "\n".join(err_lines)
    assert rc == 2
    assert f"error: argument {option}: " in err_lines[-1] and why in err_lines[-1], stderr
    assert "Traceback" not in stderr and not lines


@pytest.mark.parametrize("option, value", [
    ("--speed", "nan"), ("--speed", "inf"), ("--duration", "0"), ("--duration", "nan"), ("--duration", "inf"),
    ("--wait-peer", "0"), ("--wait-peer", "-1"), ("--wait-peer", "nan"), ("--linger", "-1"), ("--linger", "nan"),
    ("--linger", "inf"), ("--settle", "-1"), ("--settle", "nan"), ("--baudrate", "0"), ("--baudrate", "-5"),
    ("--wheels", "0"), ("--wheels", "7"), ("--corrupt-rate", "nan"), ("--drop-rate", "2"), ("--fault-seed", "-1"),
    ("--fault", "drop@1:n=2,wheel=1"),
])
def test_cli_refuses_meaningless_numbers_as_it_parses_them(option, value, capsys, monkeypatch):
    from firmware_sim import cli

    def taken(args):
        raise AssertionError(f"{option} {value} was taken")  # (no link, no run in this process)

    monkeypatch.setattr(cli, "make_link", taken)
    with pytest.raises(SystemExit) as exc:
        cli.main(["serial", "--cycles", "1", "--speed", "0", option, value])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and err[-1].startswith("firmware-sim"), err
    assert option in err[-1] and value.split(":")[0] in err[-1], err
