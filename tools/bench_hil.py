#!/usr/bin/env python
"""Hardware-in-the-loop benchmark: the virtual device at 1 kHz, the live estimator, real links.

Runs (each ``--duration`` seconds of real time, default 600 s = 10 minutes):

``serial``   firmware-sim over a pseudo-terminal (its own process) -> the live estimator
             (this process: SerialSource + LiveEstimation, as ``slipest serial``);
``can``      firmware-sim -> ``slipest can-server`` (its own process) -> the live estimator,
             which publishes one SlipEstimate per leg cycle back on the bus; a listener in
             a fourth process stamps the estimates' arrival;
``corrupt``  ``serial`` with ``--corrupt-rate`` (default 1 %) of the bytes on the wire corrupted;
``corrupt-intact``  the same at a rate low enough that most cycles stay intact
             (``--intact-rate``, default 2e-5 per byte), to compare the accuracy on intact
             cycles with the clean run (at 1 % of the bytes, ~21 % of the 24-byte frames are
             lost and every 1247-sample feature window loses some: no cycle is intact).

Figures (all clocks are the host's CLOCK_MONOTONIC, shared by the processes):

* reconciliation: frames the device sent intact vs frames the receiver delivered, frames
  the device lost on purpose (dropped, corrupted, or taken along by a corrupted delimiter)
  vs the losses the receiver counted; ``unexplained`` must be 0;
* latency device send -> estimator intake, per frame (device send log joined with the
  receiver's intake times): median, p99 (target p99 < 2 ms);
* time from the cycle's closing sample being sent to the estimate: ready in the estimator
  (serial) / received from the bus by another process (CAN) (target < 5 ms);
* the three slowest frames, each with the garbage collections of this (the estimator's)
  process that overlapped it and, over CAN, its split into device -> server and server ->
  intake (from the server's forwarding stamp in each frame);
* corruption: crashes (exceptions, estimator errors), estimates whose feature window holds a
  frame that did not arrive intact (must be 0), corrupted frames delivered (must be 0), slip
  RMSE on intact cycles vs the clean run.

    python tools/bench_hil.py                  # 10 minutes per run (the issue's figure)
    python tools/bench_hil.py --duration 60    # a quicker look
    python tools/bench_hil.py --runs serial,can --duration 30 --json out.json
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
import traceback

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from slipest.io.bus_args import BusConfig  # noqa: E402
from slipest.io.can_messages import COUNTER_MODULUS, TIME_MOD_PERIOD, CanDecoder, ImuMessage  # noqa: E402
from slipest.io.can_source import CanSource  # noqa: E402
from slipest.io.serial_source import SerialSource  # noqa: E402
from slipest.live import LiveEstimation, StopConditions, run_live  # noqa: E402

PY = sys.executable
SLIP = 0.3
PERIOD = 2 * math.pi / (4 * 0.63)
SENT, CORRUPTED = 0, 2  # firmware_sim.device status codes

LISTENER = r"""
import sys, time, can
bus = can.Bus(interface="socketcand", host="127.0.0.1", port=int(sys.argv[1]), channel="vcan0", tcp_tune=True)
print("ready", flush=True)
while True:
    m = bus.recv(0.5)
    if m is not None and 0x110 <= m.arbitration_id <= 0x115:
        print(m.data[7], time.monotonic_ns(), repr(m.timestamp), flush=True)
"""


class Child:
    def __init__(self, args):
        self.p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
        self.q: queue.Queue = queue.Queue()
        self.err: list[str] = []
        threading.Thread(target=self._pump, args=(self.p.stdout, self.q.put), daemon=True).start()
        threading.Thread(target=self._pump, args=(self.p.stderr, self.err.append), daemon=True).start()

    @staticmethod
    def _pump(stream, sink):
        for line in stream:
            sink(line.rstrip("\n"))

    def expect(self, text, timeout=120.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=0.2)
            except queue.Empty:
                if self.p.poll() is not None:
                    break
                continue
            if text in line:
                return line
        raise RuntimeError(f"{text!r} not seen; stderr: {self.err[-5:]}")

    def lines(self):
        out = []
        while True:
            try:
                out.append(self.q.get_nowait())
            except queue.Empty:
                return out

    def stop(self):
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(10)


def pct(values, q):
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if v.size else math.nan


class Receiver:
    """The live estimator of one run, instrumented: every sample's intake time, every estimate."""

    def __init__(self, source, sim_speed=1.0):
        self.intake = []  # (seq mod M, intake [s]) in arrival order
        self.estimates = []  # (estimate, ready monotonic [s])
        self.live = LiveEstimation(source, sim_speed=sim_speed, on_estimate=self._on_estimate)
        orig = self.live.samples

        def samples(wheel, seq, t, az, theta, intake):
            self.intake.extend(zip(list(seq), list(np.broadcast_to(np.asarray(intake, float), (len(seq),)))))
            orig(wheel, seq, t, az, theta, intake)

        self.live.samples = samples
        self.live.warmup()

    def _on_estimate(self, wheel, est, info):
        self.estimates.append((est, info["ready"]))
        if self.publish is not None:
            self.publish(wheel, est)

    publish = None


class HopRecorder:
    """Where a frame's time went (bench instrumentation, not product code).

    ``gc``: this process's garbage collections of 2 ms or more, as (start monotonic [s],
    duration [s], generation); the live estimator and the source's reader thread both
    stop while one runs. For CAN, ``frames``: per IMU frame decoded, (counter, server
    forwarding time, decode time) [s, monotonic]: the socketcand server stamps each frame
    it forwards with its wall clock (``< frame ID sec.usec ... >``), converted here with
    the wall-minus-monotonic offset read at the start and the end of the run.
    """

    def __init__(self):
        self.gc = []
        self.frames = []
        self._gc_t0 = 0.0
        self.offsets = [(time.monotonic(), time.time() - time.monotonic())]

    def gc_callback(self, phase, info):
        now = time.perf_counter()
        if phase == "start":
            self._gc_t0 = now
        elif now - self._gc_t0 >= 2e-3:
            self.gc.append((time.monotonic() - (now - self._gc_t0), now - self._gc_t0, info["generation"]))

    def wrap(self, decoder):
        """``decoder`` with its ``decode`` recording every IMU frame's server stamp and decode time."""
        inner = decoder.decode
        frames = self.frames

        def decode(msg):
            rec = inner(msg)
            if isinstance(rec, ImuMessage):
                frames.append((rec.counter, msg.timestamp, time.monotonic()))
            return rec

        decoder.decode = decode
        return decoder

    def finish(self):
        self.offsets.append((time.monotonic(), time.time() - time.monotonic()))

    def server_mono(self, wall, at):
        """A server wall-clock stamp [s] as monotonic [s], the offset interpolated at monotonic ``at``."""
        (m0, o0), (m1, o1) = self.offsets[0], self.offsets[-1]
        off = o0 if m1 <= m0 else o0 + (o1 - o0) * (at - m0) / (m1 - m0)
        return wall - off

    def explain(self, send, intake, seq, modulus):
        """Hop split and overlapping collections of one frame sent at ``send`` and taken in at ``intake`` [s]."""
        out = {"send_s": send, "latency_ms": (intake - send) * 1e3}
        if self.frames:
            cands = [(abs(dec - intake), srv, dec) for c, srv, dec in self.frames if c == seq % modulus
                     and abs(dec - intake) < 1.0]
            if cands:
                _, srv, dec = min(cands)
                srv_m = self.server_mono(srv, dec)
                out["device_to_server_ms"] = (srv_m - send) * 1e3
                out["server_to_decode_ms"] = (dec - srv_m) * 1e3
        out["gc_in_window"] = [(round((t - send) * 1e3, 2), round(d * 1e3, 2), g) for t, d, g in self.gc
                               if t + d >= send and t <= intake]
        return out


def join_intake(log, intake, modulus):
    """Per device IMU frame of wheel 0: intake time [s] (NaN: not received), by order and counter."""
    sel = (log["kind"] == 1) & (log["wheel"] == 0)
    seq = log["seq"][sel]
    got = np.full(seq.size, np.nan)
    d = 0
    for s, t_in in intake:
        while d < seq.size and seq[d] % modulus != s:
            d += 1
        if d >= seq.size:
            break
        got[d] = t_in
        d += 1
    return sel, got


def run_one(name, link, duration, tmp, corrupt_rate=0.0, seed=1):
    """One run; returns its figures."""
    cycles = max(2, math.ceil(duration / PERIOD))
    report_path = os.path.join(tmp, f"{name}-device.json")
    log_path = os.path.join(tmp, f"{name}-send.npz")
    dev_args = [PY, "-m", "firmware_sim", link, "--cycles", str(cycles), "--duration", f"{duration:g}",
                "--slip", str(SLIP), "--noise", "0.01", "--seed", str(seed), "--speed", "1", "--quiet",
                "--report", report_path, "--send-log", log_path, "--linger", "0.5"]
    if corrupt_rate:
        dev_args += ["--corrupt-rate", f"{corrupt_rate:g}", "--fault-seed", "3"]
    children = []
    listener = None
    crashed = None
    t_start = time.monotonic()
    hops = HopRecorder()
    gc.callbacks.append(hops.gc_callback)
    try:
        if link == "serial":
            source = SerialSource(os.path.join(tmp, f"{name}-pty"))
            rx = Receiver(source)
            dev = Child(dev_args + ["--link", os.path.join(tmp, f"{name}-pty"), "--settle", "0.05"])
            children.append(dev)
            dev.expect("serial device")
            source.start(wait_open=30)
        else:
            server = Child([PY, "-m", "slipest.cli.main", "can-server", "--port", "0"])
            children.append(server)
            port = int(server.expect("listening on").rsplit(":", 1)[1])
            config = BusConfig("socketcand", "vcan0", {"host": "127.0.0.1", "port": port})
            source = CanSource(config, decoder=hops.wrap(CanDecoder()))
            rx = Receiver(source)
            source.start(wait_open=10)
            rx.publish = source.publish
            listener = Child([PY, "-c", LISTENER, str(port)])
            children.append(listener)
            listener.expect("ready")
            dev = Child(dev_args + ["-i", "socketcand", "-c", "vcan0", "--bus-option", "host=127.0.0.1",
                                    "--bus-option", f"port={port}"])
            children.append(dev)
        print(f"  [{name}] streaming {duration:g} s at 1 kHz over {link} ...", flush=True)

        def device_done(state):
            quiet = state.now - (state.last_data or state.started)
            if dev.p.poll() is not None and quiet > 1.0:
                return "the device finished"
            return "no data for 60 s" if quiet > 60 else None

        try:  # the loop of slipest serial / can, which closes the source and the estimation
            result = run_live(source, rx.live, StopConditions(until=device_done), handle_signals=False)
            if result.reason != "the device finished":
                raise RuntimeError(result.reason)
        except Exception:  # a crash of the live estimator is a finding, not a reason to stop the bench
            crashed = traceback.format_exc()
        source_counters = source.counters()
        time.sleep(0.3)
        bus_estimates = {}
        if listener is not None:
            for line in listener.lines():
                parts = line.split()
                if len(parts) == 3:  # cycle mod 256, arrival [ns monotonic], server stamp [s wall clock]
                    arrival = int(parts[1]) * 1e-9
                    bus_estimates.setdefault(int(parts[0]), []).append((arrival, hops.server_mono(float(parts[2]),
                                                                                                   arrival)))
    finally:
        gc.callbacks.remove(hops.gc_callback)
        hops.finish()
        for c in reversed(children):
            c.stop()
    with open(report_path) as fh:
        report = json.load(fh)
    log = dict(np.load(log_path))
    modulus = (1 << 16) if link == "serial" else COUNTER_MODULUS
    sel, intake = join_intake(log, rx.intake, modulus)
    status = log["status"][sel]
    send = np.where(log["send_ns"][sel] >= 0, log["send_ns"][sel] * 1e-9, np.nan)
    t_scn = (log["t_us"][sel] - report["t0_us"]) * 1e-6
    delivered = np.isfinite(intake)
    lat = (intake - send)[delivered & (status == SENT)]
    lat_warm = (intake - send)[delivered & (status == SENT) & (t_scn >= 1.0)]
    # reconciliation
    first, last_i = (np.flatnonzero(delivered)[[0, -1]] if delivered.any() else (0, -1))
    inner = slice(first, last_i + 1)
    not_delivered = (~delivered[inner]).sum()
    device_lost = (status[inner] != SENT).sum()
    counted = rx.live.counters().get("wheel0", {}).get("frames_lost", 0)
    corrupted_delivered = int((delivered & (status == CORRUPTED)).sum())
    # estimates
    ok = [(e, ready) for e, ready in rx.estimates if e.ok and 0 <= e.cycle]
    windows_bad = 0
    close_lat = []
    close_parts = []  # CAN: (total, closing sample sent -> estimate ready, ready -> server, server -> listener) [s]
    errs = []
    for e, ready in ok:
        k = e.cycle
        w = (t_scn >= (k + 0.5) * PERIOD) & (t_scn < (k + 1) * PERIOD)
        if not delivered[w].all():
            windows_bad += 1
        errs.append(e.slip - SLIP)
    t_dev = log["t_us"][sel] * 1e-6  # device time of each frame [s]
    if link == "can" and delivered.any():
        f = int(np.flatnonzero(delivered)[0])  # receiver time starts at that frame's TimeMod
        shift = t_dev[f] - round((t_dev[f] % TIME_MOD_PERIOD) / 1e-5) * 1e-5
    else:
        shift = 0.0
    for e, ready in rx.estimates:
        j = int(np.searchsorted(t_dev, e.t_end + shift - 5e-4))  # the cycle's closing sample
        if not 0 <= j < send.size or abs(t_dev[j] - (e.t_end + shift)) > 5e-4 or not np.isfinite(send[j]):
            continue
        if link == "serial":
            close_lat.append(ready - send[j])
        else:
            later = [(a, srv) for a, srv in bus_estimates.get(e.cycle % 256, []) if a >= send[j]]
            if later:
                a, srv = min(later)
                close_lat.append(a - send[j])
                close_parts.append((a - send[j], ready - send[j], srv - ready, a - srv, e.cycle))
    errs = np.array(errs)
    seqs = log["seq"][sel]
    late = np.flatnonzero(delivered & (status == SENT))
    worst = late[np.argsort(-(intake - send)[late])[:3]] if late.size else []
    slowest = [hops.explain(float(send[i]), float(intake[i]), int(seqs[i]), modulus) for i in worst]
    for w in slowest:
        w["send_s"] = round(w["send_s"] - float(np.nanmin(send)), 3)  # since the first frame sent
    streaming_gc = [d for t, d, _ in hops.gc if t >= np.nanmin(send)]
    return {
        "run": name,
        "link": link,
        "duration_s": duration,
        "wall_s": time.monotonic() - t_start,
        "crashed": crashed,
        "estimator_errors": rx.live.counters()["estimator_errors"],
        "frames_generated": int(sel.sum()),
        "frames_delivered": int(delivered.sum()),
        "device_lost_on_purpose": int(device_lost),
        "receiver_lost_counted": int(counted),
        "unexplained_losses": int(not_delivered - device_lost),
        "corrupted_frames_delivered": corrupted_delivered,
        "corrupt_rate": corrupt_rate,
        "frames_corrupted": report["injected"]["frames_corrupted"],
        "decoder_rejects": source_counters.get("crc_errors", 0) + source_counters.get("malformed", 0),
        "device_lateness": report["lateness"],
        "latency_send_to_intake_ms": {"median": float(np.median(lat) * 1e3) if lat.size else math.nan,
                                      "p99": pct(lat, 99) * 1e3,
                                      "max": float(lat.max() * 1e3) if lat.size else math.nan,
                                      "n": int(lat.size),
                                      "p99_after_first_second": pct(lat_warm, 99) * 1e3},
        "closing_sample_to_estimate_ms": {"median": pct(close_lat, 50) * 1e3, "p99": pct(close_lat, 99) * 1e3,
                                          "max": float(np.max(close_lat) * 1e3) if close_lat else math.nan,
                                          "n": len(close_lat),
                                          "where": ("ready in the estimator" if link == "serial"
                                                    else "received from the bus")},
        "cycles": len(rx.estimates),
        "cycles_estimated": len(ok),
        "estimates_from_damaged_windows": windows_bad,
        "slip_rmse": float(np.sqrt(np.mean(errs ** 2))) if errs.size else math.nan,
        "slowest_frames": slowest,
        "slowest_estimate_ms": (dict(zip(("total", "to_ready", "ready_to_server", "server_to_listener", "cycle"),
                                         [round(v * 1e3, 3) for v in max(close_parts)[:4]] + [max(close_parts)[4]]))
                                if close_parts else None),
        "gc_pauses_while_streaming": {"n": len(streaming_gc), "max_ms": max(streaming_gc, default=0.0) * 1e3},
    }


def print_run(r):
    print(f"\n== {r['run']} ({r['link']}, {r['duration_s']:g} s at 1 kHz"
          + (f", {100 * r['corrupt_rate']:g}% of bytes corrupted" if r["corrupt_rate"] else "") + ")")
    print(f"  crashes: {'none' if not r['crashed'] else 'YES: ' + r['crashed'].splitlines()[-1]}, "
          f"estimator errors: {r['estimator_errors']}")
    print(f"  frames: {r['frames_generated']} generated, {r['frames_delivered']} delivered; lost on purpose by the "
          f"device {r['device_lost_on_purpose']}, counted lost by the receiver {r['receiver_lost_counted']}, "
          f"unexplained {r['unexplained_losses']}")
    if r["corrupt_rate"]:
        print(f"  corruption: {r['frames_corrupted']} frames lost to corruption, {r['decoder_rejects']} segments "
              f"rejected by the decoder, corrupted frames delivered: {r['corrupted_frames_delivered']}, estimates "
              f"from windows with a damaged frame: {r['estimates_from_damaged_windows']}")
    lat = r["latency_send_to_intake_ms"]
    print(f"  device send -> estimator intake: median {lat['median']:.3f} ms, p99 {lat['p99']:.3f} ms "
          f"({lat['p99_after_first_second']:.3f} ms after the first second), max {lat['max']:.1f} ms "
          f"(n={lat['n']})  [target p99 < 2 ms]")
    c = r["closing_sample_to_estimate_ms"]
    print(f"  closing sample sent -> estimate {c['where']}: median {c['median']:.2f} ms, p99 {c['p99']:.2f} ms, "
          f"max {c['max']:.1f} ms (n={c['n']})  [target < 5 ms]")
    for w in r["slowest_frames"]:
        hop = (f", device -> server {w['device_to_server_ms']:.2f} ms, server -> intake "
               f"{w['server_to_decode_ms']:.2f} ms" if "device_to_server_ms" in w else "")
        print(f"  slow frame at {w['send_s']:.3f} s: {w['latency_ms']:.2f} ms{hop}; "
              f"this process's GC during it (start ms, duration ms, generation): {w['gc_in_window'] or 'none'}")
    se = r.get("slowest_estimate_ms")
    if se:
        print(f"  slowest estimate (cycle {se['cycle']}): {se['total']:.2f} ms = closing sample sent -> estimate ready {se['to_ready']:.2f} ms"
              f" + publish -> server {se['ready_to_server']:.2f} ms + server -> listener {se['server_to_listener']:.2f} ms")
    g = r["gc_pauses_while_streaming"]
    print(f"  this process's garbage collections of 2 ms or more while streaming: {g['n']}, longest {g['max_ms']:.1f} ms")
    dl = r["device_lateness"]
    if dl.get("n"):
        print(f"  (device pacing lateness: median {dl['median_ms']:.3f} ms, p99 {dl['p99_ms']:.3f} ms)")
    print(f"  cycles: {r['cycles']} closed, {r['cycles_estimated']} estimated; slip RMSE {r['slip_rmse']:.4f} "
          f"(true slip {SLIP})")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=600.0, help="seconds of real time per run (default 600)")
    p.add_argument("--runs", default="serial,can,corrupt,corrupt-intact",
                   help="comma-separated runs: serial, can, corrupt, corrupt-intact")
    p.add_argument("--corrupt-rate", type=float, default=0.01, help="byte corruption of the 'corrupt' run")
    p.add_argument("--intact-rate", type=float, default=2e-5, help="byte corruption of the 'corrupt-intact' run")
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = p.parse_args(argv)
    runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    results = []
    print(f"bench_hil: {len(runs)} run(s) of {args.duration:g} s each (host: {os.cpu_count()} CPUs, "
          f"load {os.getloadavg()[0]:.2f})", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-hil-") as tmp:
        for name in runs:
            if name == "serial":
                r = run_one("serial", "serial", args.duration, tmp)
            elif name == "can":
                r = run_one("can", "can", args.duration, tmp)
            elif name == "corrupt":
                r = run_one("corrupt", "serial", args.duration, tmp, corrupt_rate=args.corrupt_rate)
            elif name == "corrupt-intact":
                r = run_one("corrupt-intact", "serial", args.duration, tmp, corrupt_rate=args.intact_rate)
            else:
                p.error(f"unknown run {name!r}")
            results.append(r)
            print_run(r)
    by = {r["run"]: r for r in results}
    if "serial" in by and "corrupt-intact" in by:
        a, b = by["serial"]["slip_rmse"], by["corrupt-intact"]["slip_rmse"]
        n_intact, n_clean = by["corrupt-intact"]["cycles_estimated"], by["serial"]["cycles_estimated"]
        print(f"\naccuracy on intact cycles: slip RMSE {b:.4f} with corruption ({n_intact} intact cycles) vs "
              f"{a:.4f} without ({n_clean} cycles)")
    failures = [r["run"] for r in results if r["crashed"] or r["unexplained_losses"] or r["corrupted_frames_delivered"]
                or r["estimates_from_damaged_windows"] or r["estimator_errors"]]
    print("\nverdict: " + ("all invariants hold" if not failures else f"invariants broken in {failures}"))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
