"""What a live run tells people, in real processes: a flapping port, a quiet bus, a late start, a dead server,
a short stuck sensor on both links."""

from __future__ import annotations

import json
import math
import os
import re
import select
import signal
import time

from tests.hil_support import Stopping, can_server, firmware_sim, serial_device, slipest_cmd, socketcand_args

PERIOD = 2 * math.pi / (4 * 0.63)  # one leg cycle [s]


def window(k: int, frac: float = 0.5) -> float:
    """Scenario time inside the feature window of cycle k."""
    return (k + 0.5 + 0.5 * frac) * PERIOD


def test_a_port_that_keeps_going_away_says_so_a_few_times_not_hundreds(tmp_path):
    """A path that points at a pty whose other end closes as soon as the reader opens it, again and again:
    every disconnection is counted, a few are said (then one per 10 s, with how many were left out)."""
    link = tmp_path / "imu"
    report = tmp_path / "live.json"
    flaps = 0

    def new_pty() -> int:
        master, slave = os.openpty()
        path = os.ttyname(slave)
        os.close(slave)
        os.symlink(path, f"{link}.tmp")
        os.replace(f"{link}.tmp", link)
        return master

    master = new_pty()
    with Stopping() as procs:
        est = procs.add(slipest_cmd("serial", str(link), "--duration", "60", "--report", str(report)))
        est.wait_err("reading ", timeout=60)  # started (a loaded machine takes seconds): then 4 s of flapping
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline:
            p = select.poll()
            p.register(master, select.POLLHUP)
            opened = time.monotonic() + 1.0
            while p.poll(0) and time.monotonic() < opened:  # POLLHUP until a reader opens the slave
                time.sleep(0.005)
            time.sleep(0.02)
            os.close(master)  # the reader's read fails: "device reports readiness to read but returned no data"
            flaps += 1
            master = new_pty()
        est.signal(signal.SIGTERM)  # the flapping is over: stop (a normal stop, the left-out notices summed up)
        assert est.wait(30) == 0, est.stderr
        os.close(master)
    src = json.loads(report.read_text())["source"]
    said = est.stderr.count("disconnected (")
    assert flaps >= 10 and src["disconnects"] >= 10
    assert said <= 4 and src["notices_suppressed"] >= src["disconnects"] - 4
    assert "more like this not shown, the last: " in est.stderr  # summed up at the end


def test_can_says_it_waits_when_the_bus_is_quiet_and_counts_what_a_late_start_missed(tmp_path):
    server, port = can_server()
    report = tmp_path / "live.json"
    with Stopping([server]) as procs:
        dev = procs.add(firmware_sim("can", *socketcand_args(port), "--cycles", "40", "--speed", "4", "--noise",
                                     "0.01", "--seed", "2", "--wait-bus", "20"))
        dev.wait_line("streaming", timeout=60)
        time.sleep(0.5)  # the estimator starts after the device (the README's order)
        est = procs.add(slipest_cmd("can", *socketcand_args(port), "--idle-timeout", "3", "--quiet-notice", "2",
                                    "--report", str(report)))
        # a cycle estimated (not the late start's first, partial one): the device stops there, the bus goes quiet
        est.wait_line(r"^0,\d+,.*,(ok|repaired)(,|$)", timeout=60)
        dev.signal(signal.SIGTERM)
        assert dev.wait(30) == 0
        assert est.wait(60) == 0, est.stderr
    wheel = json.loads(report.read_text())["estimation"]["wheel0"]
    assert wheel["frames_lost"] == 0 and wheel["samples_in"] > 1000
    missed = wheel["frames_missed_at_start"]
    assert 0 <= missed < 256  # the 8-bit counter shows the late start modulo 256
    assert (f"wheel 0: first frame has counter {missed}" in est.stderr) == (missed > 0)
    # once the device is done, the bus is quiet: said once, with what ends the run
    quiet = re.findall(r"no data for 2\.\d s \(the device stopped, or the link went quiet\); waiting "
                       r"\(it stops after 3 s without data\)", est.stderr)
    assert len(quiet) == 1, est.stderr
    assert "no data for 3 s" in est.stderr  # the reason it stopped


def test_firmware_sim_reports_a_killed_server_on_one_line(tmp_path):
    server, port = can_server()
    with Stopping([server]) as procs:
        dev = procs.add(firmware_sim("can", *socketcand_args(port), "--cycles", "4", "--speed", "1", "--noise",
                                     "0.01"))
        dev.wait_line("streaming", timeout=60)
        time.sleep(0.5)
        server.p.kill()  # the bus vanishes under the device
        server.p.wait(10)
        time.sleep(1.5)
        dev.signal()
        assert dev.wait(30) == 0
    text = "\n".join(dev.lines + dev.err_lines)
    assert "Traceback" not in text and "File \"" not in text
    assert any("reconnecting" in line for line in dev.lines)
    assert all(line.startswith("firmware-sim:") for line in dev.lines + dev.err_lines)


def _stuck_run(link: str, tmp_path) -> dict:
    """A 30 ms stuck sensor (30 samples at 1 kHz: shorter than the old 50-sample rule) in cycle 1's window."""
    report = tmp_path / f"{link}.json"
    fault = ["--fault", f"stuck@{window(1, 0.3):.3f}:n=30"]
    with Stopping() as procs:
        if link == "serial":
            dev = procs.add(firmware_sim("serial", "--cycles", "4", "--speed", "8", "--noise", "0.01", "--seed", "3",
                                         "--settle", "0.05", *fault))
            est = procs.add(slipest_cmd("serial", serial_device(dev), "--cycles", "3", "--idle-timeout", "3",
                                        "--duration", "60", "--report", str(report), "--format", "none"))
        else:
            server, port = can_server()
            procs.add(server)
            est = procs.add(slipest_cmd("can", *socketcand_args(port), "--cycles", "3", "--idle-timeout", "3",
                                        "--duration", "60", "--report", str(report), "--sim-speed", "8", "--format", "none"))
            est.wait_err("listening on CAN bus", timeout=60)
            dev = procs.add(firmware_sim("can", *socketcand_args(port), "--cycles", "4", "--speed", "8", "--noise",
                                         "0.01", "--seed", "3", *fault))
        assert est.wait(60) == 0, est.stderr
        dev.wait(30)
    return json.loads(report.read_text())["estimation"]["wheel0"]


def test_a_short_stuck_sensor_is_caught_over_serial(tmp_path):
    wheel = _stuck_run("serial", tmp_path)
    assert wheel["stuck_runs"] == 1 and wheel["stuck_samples"] == 29  # from its first repeat on
    assert wheel["qualities"].get("nan", 0) >= 1  # its cycle is flagged, not estimated


def test_a_short_stuck_sensor_is_caught_over_can(tmp_path):
    """On CAN az comes in 0.005 m/s^2 steps (noise 0.01 g repeats a value ~1.4 % of the time): only the fault."""
    wheel = _stuck_run("can", tmp_path)
    assert wheel["stuck_runs"] == 1 and wheel["stuck_samples"] == 29
    assert wheel["qualities"].get("nan", 0) >= 1


def test_one_line_takes_the_traceback_out_and_keeps_what_follows():
    import traceback

    from slipest.io.source import one_line

    try:
        raise ConnectionResetError(104, "Connection reset by peer")
    except ConnectionResetError as exc:
        embedded = f"Failed to receive: {exc}  {traceback.format_exc()}"  # what python-can's client does
    text = f"CAN bus x: receive failed: CanError: {embedded}; reconnecting"
    assert "\n" in text and "File " in text
    assert one_line(text) == ("CAN bus x: receive failed: CanError: Failed to receive: [Errno 104] Connection reset "
                              "by peer; reconnecting")
