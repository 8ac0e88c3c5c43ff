#!/usr/bin/env python
"""The CAN server's memory with many clients that never read, and what the live estimator loses meanwhile.

Runs, each in its own process: ``slipest can-server`` (the server measured), ``slipest can`` (the
live estimator, reading and publishing as usual), ``firmware-sim can`` (the device), and, in this
process, ``--clients`` TCP clients that open the channel in raw mode and then never read a byte
(a crashed logger, a stuck viewer...).  While the device streams, the server's resident memory is
read from ``/proc/PID/status`` (VmRSS, and VmHWM: its peak) every 0.2 s.  Printed:

* the server's RSS before the clients, its peak and at the end [MB], and its counters
  (frames dropped for slow clients, clients disconnected for the memory budget, refused...);
* the estimator's losses: per wheel, frames the device sent vs frames the estimator received
  (``samples_in``) and ``frames_lost`` (the target: none lost).

    python tools/bench_can_clients.py                      # 200 clients (the issue's figure)
    python tools/bench_can_clients.py --clients 50 --cycles 10
    python tools/bench_can_clients.py --server-option=--max-buffer=1000000000   # no total budget
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from tests.hil_support import Stopping, can_server, firmware_sim, slipest_cmd, socketcand_args  # noqa: E402


def rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process [MB]."""
    fields = {}
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                fields[key] = int(value.split()[0]) / 1024.0
    return fields["VmRSS"], fields["VmHWM"]


def silent_client(port: int) -> socket.socket:
    """A client that opens vcan0 in raw mode and never reads."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    sock.sendall(b"< open vcan0 >< rawmode >")
    return sock


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=200, help="clients that never read (default 200)")
    ap.add_argument("--wheels", type=int, default=2, help="device wheels (default 2)")
    ap.add_argument("--speed", type=float, default=2.0, help="device speed-up (default 2: 2 kHz per wheel)")
    ap.add_argument("--cycles", type=int, default=30, help="leg cycles streamed (default 30: 37 s at speed 2)")
    ap.add_argument("--server-option", action="append", default=[], metavar="OPT",
                    help="extra option of slipest can-server, e.g. --server-option=--max-clients=100")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    args = ap.parse_args(argv)
    print(f"# load: {os.getloadavg()}")
    tmp = tempfile.mkdtemp(prefix="slipest-clients-")
    live_report = os.path.join(tmp, "live.json")
    dev_report = os.path.join(tmp, "device.json")
    samples = []
    clients = []
    with Stopping() as procs:
        server, port = can_server(*args.server_option)
        procs.add(server)
        est = procs.add(slipest_cmd("can", *socketcand_args(port), "--idle-timeout", "3", "--report", live_report,
                                    "--sim-speed", f"{args.speed:g}", "--format", "none"))
        est.wait_err("listening on CAN bus", timeout=60)
        time.sleep(0.5)
        rss0 = rss_mb(server.p.pid)[0]
        refused = 0
        for _ in range(args.clients):
            try:
                clients.append(silent_client(port))
            except OSError:
                refused += 1
        time.sleep(0.5)
        rss_clients = rss_mb(server.p.pid)[0]
        dev = procs.add(firmware_sim("can", *socketcand_args(port), "--wheels", str(args.wheels), "--speed",
                                     f"{args.speed:g}", "--cycles", str(args.cycles), "--noise", "0.01",
                                     "--seed", "1", "--report", dev_report, "--quiet"))
        t0 = time.monotonic()
        while dev.p.poll() is None and time.monotonic() - t0 < 600:
            samples.append((time.monotonic() - t0, *rss_mb(server.p.pid)))
            time.sleep(0.2)
        dev_rc = dev.wait(60)
        est_rc = est.wait(60)
        rss_end, hwm = rss_mb(server.p.pid)
        connected = sum(1 for c in clients if c.fileno() >= 0)
        server.stop()
        for c in clients:
            c.close()
    stats = next((line for line in server.err_lines if "can-server stopped" in line), "(no counters)")
    with open(dev_report) as fh:
        sent = json.load(fh)["sent"]["imu_sent_by_wheel"]
    with open(live_report) as fh:
        live = json.load(fh)
    peak = max(s[1] for s in samples) if samples else float("nan")
    print(f"clients that never read: {args.clients} ({refused} refused at connect); device: {args.wheels} wheel(s) "
          f"at {args.speed:g} kHz each, {samples[-1][0] if samples else 0:.0f} s; exit codes device {dev_rc}, "
          f"estimator {est_rc}")
    print(f"server RSS [MB]: {rss0:.0f} before the clients, {rss_clients:.0f} with them, peak {peak:.0f} "
          f"(VmHWM {hwm:.0f}), {rss_end:.0f} at the end")
    for t, rss, _ in samples[:: max(1, len(samples) // 12)]:
        print(f"  t={t:5.1f} s  RSS {rss:6.0f} MB")
    print(f"server: {stats}")
    lost_total = 0
    for w in range(args.wheels):
        wc = live["estimation"].get(f"wheel{w}", {})
        got, lost = wc.get("samples_in", 0), wc.get("frames_lost", 0)
        lost_total += lost + (sent[w] - got)
        print(f"estimator wheel {w}: device sent {sent[w]}, estimator received {got}, frames_lost {lost}, "
              f"missed at start {wc.get('frames_missed_at_start')}")
    verdict = "PASS" if peak < 300 and hwm < 300 and lost_total == 0 else "FAIL"
    print(f"target (RSS < 300 MB, no frame lost by the estimator): {verdict}")
    print(f"# load: {os.getloadavg()}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"clients": args.clients, "refused": refused, "rss_before_mb": rss0, "rss_peak_mb": peak,
                       "hwm_mb": hwm, "rss_end_mb": rss_end, "server": stats, "sent": sent,
                       "estimation": live["estimation"], "samples": samples, "connected_at_end": connected}, fh,
                      indent=1)
    return 0 if verdict == "PASS" else 1


if __name__ == "__main__":
    sys.exit(main())
