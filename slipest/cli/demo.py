"""``slipest demo``: the whole chain live, with no hardware.

Starts the virtual IMU device (``firmware-sim``) in its own process, driving
a wheel-leg over four stretches of ground where slip and soil change, and
estimates slip and soil from its stream as it comes, over a pseudo-terminal
(default) or over a shared CAN bus (``--bus can``: ``slipest can-server`` in
a third process; the estimates are published back on the bus).  Each leg
cycle prints one line with the estimate beside the truth; the end prints a
summary: slip and dphi RMSE, how often the 95 % intervals cover the truth,
frames lost, and latencies.

About 100 s at real time (40 leg cycles); ``--speed 10`` runs it ten times
faster, ``--cycles N`` (1..40) shortens it.  ``--faults`` makes the device misbehave
(a dropped frame, corrupted bytes or unknown CAN IDs, a stuck sensor, a
disconnection) to show that the estimator survives, counts them and never
estimates from damaged cycles.  ``--view 8765`` also shows the run live in
Foxglove (``pip install 'slipest[view]'``; docs/live-view.md): the
estimates, ``az`` and the leg angle, the truth on
``/slipest/demo/truth``, and the run's notices (start, stop and why, the
link's trouble) on ``/slipest/log``.

``--effect NAME:k=v,...`` has the device simulate a rover with a
sim-to-real effect (``slipest simulate``'s catalog); ``--rover ROVER.json``
(``slipest calibrate``'s file for that rover) then estimates every cycle
twice, with the shipped model and with the rover's, side by side, and the
summary compares them:

    slipest demo --speed 10 --effect imu_lowpass:cutoff=4,order=2 --rover rover.json
"""

from __future__ import annotations

import argparse
import math
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from slipest.cli.command import add_command, interrupt_on_sigterm, seed_number

#: The demo's drive: four stretches of 10 leg cycles (about 25 s each at real time).
DEMO_SCENARIO = {
    "model": {"kappa": 0.3, "nL": 4},
    "imu": {"rate": 1000.0, "noise": 0.01},
    "segment": [
        {"cycles": 10, "slip": 0.25, "kS": 1000.0, "phiS": 0.52, "phiD": 0.35},
        {"cycles": 10, "slip": [0.25, 0.45], "kS": 1000.0, "phiS": 0.52, "phiD": 0.35},
        {"cycles": 10, "slip": 0.30, "kS": 1400.0, "phiS": 0.62, "phiD": 0.38},
        {"cycles": 10, "slip": [0.45, 0.20], "kS": 700.0, "phiS": 0.48, "phiD": 0.36},
    ],
}
_GAVE_UP = "no data from the device for 30 s"
#: Longest wait for the device to start streaming [s]: it simulates the whole run first, and the first run
#: after an install also compiles the simulator's kernels (about 40 s on a 2-core machine).
_START_LIMIT = 300.0
_NO_START = f"the device did not start streaming within {_START_LIMIT:.0f} s"
_STRETCHES = ("firm soil, steady slip", "same soil, slip rising", "stiffer, grippier soil", "soft soil, slip falling")
#: Leg cycles of the demo's drive: the most ``--cycles`` drives (the four stretches are the scenario's whole drive).
DEMO_CYCLES = sum(int(seg["cycles"]) for seg in DEMO_SCENARIO["segment"])


def cycle_count(text: str) -> int:
    """``--cycles``: a whole number of leg cycles in 1..:data:`DEMO_CYCLES` (argparse type)."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 1 <= n <= DEMO_CYCLES:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of leg cycles of the demo's drive "
                                         f"(1..{DEMO_CYCLES})")
    return n


def add_parser(sub) -> None:
    p = add_command(sub, "demo",
                    "run the virtual device and the live estimator side by side (no hardware needed)", __doc__)
    p.add_argument("--bus", choices=("serial", "can"), default="serial",
                   help="link between device and estimator: a pseudo-terminal (default) or the CAN server")
    p.add_argument("--speed", type=float, default=1.0, help="time factor of the device (default 1: real time)")
    p.add_argument("--cycles", type=cycle_count, default=None,
                   help=f"leg cycles to drive, 1..{DEMO_CYCLES} (default: all {DEMO_CYCLES})")
    p.add_argument("--seed", type=seed_number, default=7, help="seed of the IMU noise, >= 0 (default 7)")
    p.add_argument("--faults", action="store_true", help="inject faults (dropped frame, corruption, stuck sensor, "
                   "disconnection) and show they are counted and never estimated from")
    p.add_argument("--effect", action="append", default=[], metavar="NAME:k=v,...",
                   help="the device simulates a rover with this sim-to-real effect (repeatable), e.g. "
                   "imu_lowpass:cutoff=4,order=2")
    p.add_argument("--rover", metavar="ROVER.json",
                   help="also estimate with this rover file (slipest calibrate), side by side with the shipped model")
    from slipest.cli.live_args import add_view_arguments

    add_view_arguments(p)
    p.set_defaults(func=run)


def scenario_toml(doc: dict) -> str:
    """The scenario document as TOML (numbers, strings and [a, b] ramps only)."""
    def value(v):
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, str):
            return '"' + v + '"'
        return repr(v)

    lines = []
    for table in ("model", "imu"):
        if doc.get(table):
            lines.append(f"[{table}]")
            lines += [f"{k} = {value(v)}" for k, v in doc[table].items()]
    for key in ("segment", "effect"):
        for entry in doc.get(key, ()):
            lines.append(f"[[{key}]]")
            lines += [f"{k} = {value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"


class _SideBySide:
    """Two estimators fed the same samples: the rover's (whose estimates go on, as the live runtime's) and the
    shipped model's (kept by cycle in ``shipped``, for the display)."""

    def __init__(self, calibrated, shipped):
        self.cal, self.ref = calibrated, shipped
        self.shipped: dict = {}

    def _keep(self, estimates):
        for e in estimates:
            self.shipped[e.cycle] = e

    def push(self, t, az, theta, slip_ref=None):
        self._keep(self.ref.push(t, az, theta, slip_ref))
        return self.cal.push(t, az, theta, slip_ref)

    def push_many(self, t, az, theta, slip_ref=None, warm: bool = False):
        self._keep(self.ref.push_many(t, az, theta, slip_ref, warm=warm))
        return self.cal.push_many(t, az, theta, slip_ref, warm=warm)

    def finish(self):
        self._keep(self.ref.finish())
        return self.cal.finish()

    @property
    def counters(self):
        return self.cal.counters

    @property
    def hints(self):
        return self.cal.hints


class _DeviceWatch:
    """When the demo stops waiting on its device (times on the host's monotonic clock [s]).

    The device simulates its whole run before it streams, and the first run after an install also
    compiles the simulator's kernels, so silence before it says it streams (``streaming_since``) is
    allowed up to :data:`_START_LIMIT`; once it streams, 30 s without data ends the run
    (:data:`_GAVE_UP`). ``say_waiting`` turns True once, 5 s into the wait, for the caller to tell
    the user why nothing shows yet."""

    def __init__(self):
        self.streaming_since: float | None = None
        self.say_waiting = False
        self._said = False

    def reason(self, now: float, started: float, last_data: float | None, device_exited: bool) -> str | None:
        if device_exited and now - (last_data or started) > 0.5:
            return "the device finished"
        if self.streaming_since is None:
            if not self._said and now - started > 5:
                self._said = self.say_waiting = True
            return _NO_START if now - started > _START_LIMIT else None
        quiet = now - max(last_data or self.streaming_since, self.streaming_since)
        return _GAVE_UP if quiet > 30 else None


class _Child:
    """A child process whose stdout lines are collected in a thread."""

    def __init__(self, args: list[str]):
        self.p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
        self.lines: queue.Queue = queue.Queue()
        self.err: list[str] = []
        self.seen: dict[str, bool] = {}  # prefixes poll_line has seen
        threading.Thread(target=self._pump, args=(self.p.stdout, True), daemon=True).start()
        threading.Thread(target=self._pump, args=(self.p.stderr, False), daemon=True).start()

    def _pump(self, stream, out):
        for line in stream:
            (self.lines.put if out else self.err.append)(line.rstrip("\n"))
        if out:
            self.lines.put(None)

    def poll_line(self, prefix: str) -> bool:
        """True once a stdout line containing ``prefix`` has been read (lines before it are consumed)."""
        while not self.seen.get(prefix):
            try:
                line = self.lines.get_nowait()
            except queue.Empty:
                return False
            if line is None:
                self.lines.put(None)  # the end stays visible to later calls
                return False
            if prefix in line:
                self.seen[prefix] = True
        return True

    def expect(self, prefix: str, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            if line is None:
                break
            if prefix in line:
                return line
        raise RuntimeError(f"{prefix!r} not seen from {self.p.args[2]}; its stderr: " + " | ".join(self.err[-5:]))

    def stop(self, timeout: float = 5.0) -> int | None:
        if self.p.poll() is None:
            self.p.terminate()  # this child only, by its pid
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(timeout)
        return self.p.returncode


class _Display:
    """One line per leg cycle, the estimate beside the truth and its quality (``ok``, ``repaired``: estimated
    without some samples, or why it was not estimated); keeps the results."""

    def __init__(self, scenario, out, side_by_side: bool = False):
        self.cycles = scenario.cycles
        self.period = 2 * math.pi / (scenario.n_legs * scenario.omega)
        self.out = out
        self.rows: list[tuple] = []  # (cycle, estimate, truth slip, truth dphi)
        self.shipped_rows: list[tuple] = []  # with a rover file: the shipped model's (cycle, estimate, truth slip)
        self.side_by_side = side_by_side  # each wheel's estimator is a _SideBySide
        self.live = None  # the LiveEstimation whose wheels' estimators those are
        self.flagged: dict[str, int] = {}
        self._stretch = -1

    def header(self):
        if self.side_by_side:
            print(f"{'cycle':>5} {'t [s]':>7}  {'slip: shipped model':>19} {'rover file':>14} {'true':>6}   "
                  f"{'dphi [rad]: rover':>17} {'true':>6}  quality", file=self.out, flush=True)
            return
        print(f"{'cycle':>5} {'t [s]':>7}  {'slip: estimate':>15} {'true':>6}   "
              f"{'dphi [rad]: estimate':>20} {'true':>6}  quality", file=self.out, flush=True)

    def __call__(self, wheel, est, info):
        k = int(est.cycle)
        if k < 0:
            return  # the stream starts at the very end of the cycle before the first: not a cycle driven
        truth = self.cycles[k] if k < len(self.cycles) else None
        stretch = k // 10 if truth is not None else -1
        if stretch != self._stretch and 0 <= stretch < len(_STRETCHES):
            self._stretch = stretch
            print(f"      -- stretch {stretch + 1}: {_STRETCHES[stretch]} --", file=self.out, flush=True)
        t = (k + 1) * self.period  # scenario time at the end of the cycle [s]
        if not est.ok or truth is None:
            self.flagged[est.quality] = self.flagged.get(est.quality, 0) + 1
            print(f"{k:>5} {t:7.1f}  {'not estimated':>15} {'':>6}   {'':>20} {'':>6}  {est.quality}",
                  file=self.out, flush=True)
            return
        dphi = truth.phiS - truth.phiD
        self.rows.append((k, est, truth.slip, dphi))
        if self.side_by_side:
            other = self.live.wheels[wheel].estimator.shipped.pop(k, None)
            if other is not None and other.ok:
                self.shipped_rows.append((k, other, truth.slip))
                shipped = f"{other.slip:11.3f} ±{other.slip_std:5.3f}"
            else:
                shipped = f"{'not estimated':>18}"
            print(f"{k:>5} {t:7.1f}  {shipped} {est.slip:7.3f} ±{est.slip_std:5.3f} {truth.slip:6.3f}   "
                  f"{est.dphi:9.3f} ±{est.dphi_std:5.3f} {dphi:6.3f}  {est.quality}", file=self.out, flush=True)
            return
        print(f"{k:>5} {t:7.1f}  {est.slip:7.3f} ±{est.slip_std:5.3f} {truth.slip:6.3f}   "
              f"{est.dphi:12.3f} ±{est.dphi_std:5.3f} {dphi:6.3f}  {est.quality}", file=self.out, flush=True)


def _summary(display: _Display, live, source_counters: dict, device_report: dict | None, out) -> dict:
    rows = display.rows
    res = {"estimated": len(rows), "flagged": dict(display.flagged)}
    print("\nsummary", file=out)
    n_total = len(rows) + sum(display.flagged.values())
    flagged = ", ".join(f"{k} {v}" for k, v in sorted(display.flagged.items())) or "none"
    print(f"  leg cycles: {n_total} closed, {len(rows)} estimated, not estimated: {flagged}", file=out)
    if rows:
        e = np.array([(r[1].slip, r[1].slip_std, r[2], r[1].dphi, r[1].dphi_std, r[3]) for r in rows])
        slip_rmse = float(np.sqrt(np.mean((e[:, 0] - e[:, 2]) ** 2)))
        slip_cov = float(np.mean(np.abs(e[:, 0] - e[:, 2]) <= 1.96 * e[:, 1]))
        dphi_rmse = float(np.sqrt(np.mean((e[:, 3] - e[:, 5]) ** 2)))
        dphi_cov = float(np.mean(np.abs(e[:, 3] - e[:, 5]) <= 1.96 * e[:, 4]))
        res.update(slip_rmse=slip_rmse, slip_coverage=slip_cov, dphi_rmse=dphi_rmse, dphi_coverage=dphi_cov)
        who = "slip with the rover file" if display.side_by_side else "slip"
        print(f"  {who}: RMSE {slip_rmse:.3f}, 95% interval covers the truth in {100 * slip_cov:.0f}% of cycles",
              file=out)
        if display.shipped_rows:
            s = np.array([(r[1].slip, r[1].slip_std, r[2]) for r in display.shipped_rows])
            rmse0 = float(np.sqrt(np.mean((s[:, 0] - s[:, 2]) ** 2)))
            cov0 = float(np.mean(np.abs(s[:, 0] - s[:, 2]) <= 1.96 * s[:, 1]))
            res.update(shipped_slip_rmse=rmse0, shipped_slip_coverage=cov0)
            print(f"  slip with the shipped model: RMSE {rmse0:.3f}, 95% interval covers the truth in "
                  f"{100 * cov0:.0f}% of cycles ({len(s)} cycles)", file=out)
        print(f"  dphi: RMSE {dphi_rmse:.3f} rad, 95% interval covers the truth in {100 * dphi_cov:.0f}% of cycles",
              file=out)
    lost = sum(wc.get("frames_lost", 0) for k, wc in live.counters().items() if k.startswith("wheel"))
    stuck = sum(wc.get("stuck_samples", 0) for k, wc in live.counters().items() if k.startswith("wheel"))
    bad = source_counters.get("crc_errors", 0) + source_counters.get("malformed", 0)
    unknown = source_counters.get("unknown_id", 0)
    received = source_counters.get("frames_ok", source_counters.get("ok", 0))
    res.update(frames_received=received, frames_lost=lost)
    line = f"  frames: {received} received, {lost} lost"
    if bad:
        line += f", {bad} corrupted or malformed segments skipped"
    if unknown:
        line += f", {unknown} unknown CAN IDs skipped"
    if stuck:
        line += f", {stuck} stuck-sensor samples not used"
    print(line, file=out)
    if device_report:
        inj = device_report.get("injected", {})
        if inj.get("frames_lost") or inj.get("stuck_samples") or inj.get("unknown_sent") or inj.get("disconnects"):
            print(f"  the device injected: {inj.get('frames_dropped', 0)} dropped, {inj.get('frames_corrupted', 0)} "
                  f"corrupted, {inj.get('frames_lost_disconnected', 0)} lost in {inj.get('disconnects', 0)} "
                  f"disconnection(s), {inj.get('stuck_samples', 0)} stuck samples, {inj.get('unknown_sent', 0)} "
                  "unknown messages", file=out)
    lat = live.latency()
    dev, est = lat.get("device_to_intake", {}), lat.get("intake_to_estimate", {})
    if dev.get("n"):
        res.update(latency_median_ms=dev["median_ms"], latency_p99_ms=dev["p99_ms"])
        print(f"  latency, device sample -> estimator intake: median {dev['median_ms']:.2f} ms, "
              f"p99 {dev['p99_ms']:.2f} ms", file=out)
    if est.get("n"):
        print(f"  latency, cycle's closing sample -> estimate: median {est['median_ms']:.2f} ms, "
              f"p99 {est['p99_ms']:.2f} ms", file=out)
    out.flush()
    return res


def run(args: argparse.Namespace) -> int:
    import json

    from slipest.cli.live_args import view_from_args
    from slipest.live import LiveEstimation, StopConditions, run_live
    from slipest.model.scenario import Scenario

    if args.speed < 0 or not math.isfinite(args.speed):
        raise SystemExit("slipest demo: --speed must be >= 0")
    out = sys.stdout
    doc = {k: (dict(v) if isinstance(v, dict) else list(v)) for k, v in DEMO_SCENARIO.items()}
    doc["imu"]["seed"] = args.seed
    rover = None
    try:
        if args.effect:
            from slipest.model.effects import parse_effect_arg

            doc["effect"] = [parse_effect_arg(text) for text in args.effect]
        scenario = Scenario.from_dict(doc)
        if args.rover:
            from slipest.rover.file import load_rover

            rover = load_rover(args.rover, n_legs=scenario.n_legs)
    except ValueError as exc:  # an unknown effect or parameter, a rover file that cannot be used: named, exit 2
        print(f"slipest demo: {exc}", file=sys.stderr)  # (a usage error, as replay's refusal of the same file)
        raise SystemExit(2) from None
    period = 2 * math.pi / (scenario.n_legs * scenario.omega)
    n_cycles = len(scenario.cycles) if args.cycles is None else args.cycles  # (cycle_count: 1..DEMO_CYCLES)
    duration = n_cycles * period  # the last cycle driven is estimated at the end of the stream (finish)
    speed = args.speed

    old_term = interrupt_on_sigterm()  # while starting up; run_live handles it while streaming
    children: list[_Child] = []
    source = live = result = None
    display = _Display(scenario, out, side_by_side=rover is not None)
    tmp = tempfile.TemporaryDirectory(prefix="slipest-demo-")
    device_report_path = os.path.join(tmp.name, "device.json")
    code = 0

    view = None

    def say(text: str, level: str = "info") -> None:
        """A notice of the run on the live view's ``/slipest/log`` (its start, stop and why, as ``slipest
        serial --view`` publishes them); nothing without a view (the demo prints its own lines)."""
        if view is not None:
            view.notice(f"slipest demo: {text}", level)

    def side_by_side(wheel):
        from slipest.online import SlipEstimator

        return _SideBySide(SlipEstimator(n_legs=scenario.n_legs, model=rover), SlipEstimator(n_legs=scenario.n_legs))

    def estimation(on_estimate):
        nonlocal view
        est = LiveEstimation(source, n_legs=scenario.n_legs, sim_speed=speed or None, on_estimate=on_estimate,
                             estimator_factory=side_by_side if rover is not None else None)
        display.live = est
        est.warmup()
        view = view_from_args("slipest demo", args, est)
        if view is not None:
            print(f"slipest demo: live view on {view.url} (in Foxglove: Open connection, Foxglove WebSocket)",
                  file=out, flush=True)
            est.add_listener(on_estimate=lambda wheel, e, info: _publish_truth(view, scenario, e))
        return est

    try:
        scen_path = os.path.join(tmp.name, "demo.toml")
        with open(scen_path, "w") as fh:
            fh.write(scenario_toml(doc))
        link_name = "a pseudo-terminal" if args.bus == "serial" else "a CAN bus (slipest can-server)"
        faster = f", shown {speed:g}x faster" if speed not in (0, 1) else ""
        drive = f"{n_cycles} leg cycles ({n_cycles * period:.0f} s of driving{faster}) over {link_name}"
        print(f"slipest demo: {drive}", file=out, flush=True)
        if args.effect:
            print(f"slipest demo: the device simulates a rover with {', '.join(args.effect)}"
                  + (f"; estimates with the shipped model and with {args.rover} side by side" if rover else ""),
                  file=out, flush=True)
        dev_args = [sys.executable, "-m", "firmware_sim", args.bus, "--scenario", scen_path, "--speed", f"{speed:g}",
                    "--duration", f"{duration:.6f}", "--send-reference", "--report", device_report_path, "--quiet",
                    "--linger", "0.3"]
        if args.faults:
            dev_args += _fault_args(args.bus, period, n_cycles)
        if args.bus == "serial":
            from slipest.io.serial_source import SerialSource

            link = os.path.join(tmp.name, "imu")
            source = SerialSource(link)
            live = estimation(display)
            device = _Child(dev_args + ["--link", link, "--settle", "0.05"])
            children.append(device)
            device.expect("serial device", 60)
            print(f"slipest demo: virtual device (pid {device.p.pid}) on {link}", file=out, flush=True)
            source.start(wait_open=10)
        else:
            from slipest.io.bus_args import BusConfig
            from slipest.io.can_source import CanSource

            server = _Child([sys.executable, "-m", "slipest.cli.main", "can-server", "--port", "0"])
            children.append(server)
            port = int(server.expect("listening on", 30).rsplit(":", 1)[1])
            source = CanSource(BusConfig("socketcand", "vcan0", {"host": "127.0.0.1", "port": port}))
            live = estimation(lambda w, e, i: (source.publish(w, e), display(w, e, i)))
            source.start(wait_open=10)
            device = _Child(dev_args + ["-i", "socketcand", "-c", "vcan0", "--bus-option", "host=127.0.0.1",
                                        "--bus-option", f"port={port}"])
            children.append(device)
            print(f"slipest demo: CAN server (pid {server.p.pid}) on 127.0.0.1:{port}, virtual device (pid "
                  f"{device.p.pid}); estimates are published back on the bus", file=out, flush=True)
        display.header()
        say(f"started: {drive}, virtual device pid {device.p.pid}")

        watch = _DeviceWatch()

        def device_done(state):
            if watch.streaming_since is None and device.poll_line("streaming"):
                watch.streaming_since = state.now
            reason = watch.reason(state.now, state.started, state.last_data, device.p.poll() is not None)
            if watch.say_waiting:
                watch.say_waiting = False
                print("slipest demo: the device is simulating the run before it streams (the first run after an "
                      "install also compiles its kernels, about a minute)", file=out, flush=True)
            return reason

        result = run_live(source, live, StopConditions(until=device_done), on_notice=_notices_to(view),
                          on_stopping=lambda reason: say(f"stopping ({reason})"))
        if result.reason in (_GAVE_UP, _NO_START):
            print(f"slipest demo: {result.reason}; giving up", file=sys.stderr)
            say(f"{result.reason}; giving up", "error")
            code = 1
        else:
            say(result.reason)  # "the device finished", "interrupted (SIGINT)"
            if result.interrupted:
                print("\nslipest demo: interrupted", file=out)
            elif device.p.wait(10) != 0:
                failure = "the device failed: " + " | ".join(device.err[-5:])
                print(f"slipest demo: {failure}", file=sys.stderr)
                say(failure, "error")
                code = 1
    except KeyboardInterrupt:
        print("\nslipest demo: interrupted", file=out)
        say("interrupted")
    except (OSError, RuntimeError) as exc:
        print(f"slipest demo: {exc}", file=sys.stderr)
        say(str(exc), "error")
        code = 1
    finally:
        for child in reversed(children):
            child.stop()
        if source is not None:
            source.close()
        if view is not None:
            view.close()
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)
    try:
        report = None
        if os.path.exists(device_report_path):
            with open(device_report_path) as fh:
                report = json.load(fh)
        if source is not None and source.started:
            if result is None:
                live.close()  # interrupted before streaming: run_live did not close it
            res = _summary(display, live, source.counters(), report, out)
            if code == 0 and res["estimated"] == 0:
                print("slipest demo: no cycle was estimated", file=sys.stderr)
                code = 1
    finally:
        tmp.cleanup()
    return code


#: JSON schema of ``/slipest/demo/truth``: what the demo's device drove in each leg cycle.
TRUTH_SCHEMA = {"title": "slipest.DemoTruth", "type": "object", "properties": {
    "cycle": {"type": "integer"}, "slip": {"type": "number", "description": "true slip [-]"},
    "dphi": {"type": "number", "description": "true phiS - phiD [rad]"},
    "kS": {"type": "number", "description": "[N/m]"}, "phiS": {"type": "number", "description": "[rad]"},
    "phiD": {"type": "number", "description": "[rad]"}}}


def _publish_truth(view, scenario, est) -> None:
    """The truth of the estimate's cycle on the live view (``/slipest/demo/truth``)."""
    k = int(est.cycle)
    if 0 <= k < len(scenario.cycles):
        c = scenario.cycles[k]
        view.publish("/slipest/demo/truth", {"cycle": k, "slip": float(c.slip), "dphi": float(c.phiS - c.phiD),
                                             "kS": float(c.kS), "phiS": float(c.phiS), "phiD": float(c.phiD)},
                     TRUTH_SCHEMA)


def _notices_to(view):
    """``run_live``'s ``on_notice`` for the demo: logged at INFO (as without a view) and, with a view, also
    on its ``/slipest/log``; None (``run_live``'s default) without a view."""
    if view is None:
        return None
    import logging

    def notice(text: str) -> None:
        logging.getLogger("slipest.demo").info("%s", text)
        view.notice(f"slipest demo: {text}")

    return notice


def _fault_args(bus: str, period: float, n_cycles: int) -> list[str]:
    """A few faults inside feature windows of the first cycles (window: 1.5 T .. 2 T of cycle 1, ...)."""
    def window(k: int, frac: float) -> float:
        return (k + 0.5 + 0.5 * frac) * period

    faults = [f"drop@{window(1, 0.3):.3f}:n=1", f"stuck@{window(3, 0.2):.3f}:n=200,wheel=0"]
    if n_cycles > 5:
        faults.append(f"disconnect@{window(5, 0.5):.3f}:down=0.3")
    if bus == "serial":
        faults.append(f"corrupt@{window(2, 0.4):.3f}:n=3")
    else:
        faults.append(f"unknown-ids@{window(2, 0.4):.3f}:n=25")
    out = []
    for f in faults:
        out += ["--fault", f]
    return out
