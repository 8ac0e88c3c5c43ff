"""What ``slipest serial`` and ``slipest can`` share: estimating on a live stream.

:class:`LiveEstimation` takes the frames a source delivers (serial or CAN,
any wheel), turns each wheel's frames into samples
(:class:`~slipest.io.device_stream.WheelStream`: lost frames become NaN
samples so their cycles are flagged, stuck sensors are caught), runs one
estimator per wheel, records the input to log CSVs, and reports every
estimate to a callback (print, publish on the bus...).  :func:`run_live`
is the loop around a source: signals (SIGTERM and SIGINT stop cleanly with
the recording flushed and closed; SIGUSR1 prints the counters), stop
conditions (``--duration``, ``--cycles``, ``--idle-timeout``), counters at
exit and in a JSON report.

Recording: ``--record FILE`` writes wheel 0 to FILE and wheel k to
``STEM.wheelK.EXT`` (or to FILE with ``{wheel}`` replaced, when FILE
contains it), in the log format ``slipest replay`` reads: ``t`` (device
time [s]), ``az``, ``theta`` (unwrapped), ``slip`` (reference, NaN when
none).  A lost frame is a row with ``az = nan`` (a dropout, as the
estimator saw it); every received sample is written as received.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from slipest.cli.estimator_args import add_estimator_arguments, model_from_args, soil_from_args
from slipest.io.device_stream import WheelSamples, WheelStream
from slipest.startup_gc import freeze_startup_objects


def add_live_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by the live commands."""
    e = p.add_argument_group("estimation")
    e.add_argument("--legs", type=int, default=4, help="legs of each wheel-leg (default 4)")
    add_estimator_arguments(e)
    e.add_argument("--use-reference", action="store_true",
                   help="learn the soil from the reference slip frames the device sends (testbeds)")
    e.add_argument("--wheel", type=int, action="append", default=None, metavar="W",
                   help="estimate only this wheel (repeatable; default: every wheel seen)")
    e.add_argument("--stuck-samples", type=int, default=50, metavar="N",
                   help="az bit-identical over N consecutive samples is a stuck sensor: not estimated from "
                   "(default 50; 0: off; noise-free simulated data over CAN needs 0)")
    o = p.add_argument_group("output")
    o.add_argument("--record", metavar="FILE",
                   help="record the input to a log CSV (wheel 0: FILE; wheel k: STEM.wheelK.EXT, or FILE with "
                   "{wheel} replaced); flushed continuously, complete after Ctrl-C or SIGTERM")
    o.add_argument("--overwrite", action="store_true", help="overwrite existing --record files")
    o.add_argument("--report", metavar="FILE", help="write the counters and latency figures as JSON at exit")
    o.add_argument("-q", "--quiet", action="store_true", help="do not print estimates (counters still at exit)")
    s = p.add_argument_group("stopping")
    s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    s.add_argument("--cycles", type=int, default=None, metavar="N",
                   help="stop once every wheel seen has N leg cycles estimated or flagged")
    s.add_argument("--idle-timeout", type=float, default=None, metavar="S",
                   help="stop when no frame arrived for S seconds (after the first one)")
    t = p.add_argument_group("timing")
    t.add_argument("--sim-speed", type=float, default=None, metavar="S",
                   help="the device is firmware-sim on this host with --speed S: its timestamps are this host's "
                   "monotonic clock x S, so the latency from each sample's instant to its intake is measured, and "
                   "wrapped CAN timestamps are unwrapped across outages knowing that device time runs S times "
                   "faster than this host's")


def live_from_args(args, **kwargs) -> "LiveEstimation":
    """The :class:`LiveEstimation` the live options describe (SystemExit on a bad combination)."""
    try:
        live = LiveEstimation(n_legs=args.legs, method=args.method, soil=soil_from_args(args),
                              use_reference=args.use_reference, model=model_from_args(args), wheels=args.wheel, stuck_samples=args.stuck_samples, sim_speed=args.sim_speed,
                              record=args.record, overwrite=args.overwrite, **kwargs)
        live.warmup()  # also checks the estimator options (e.g. eq515 without a soil)
    except FileExistsError as exc:
        raise SystemExit(f"slipest: {exc}; use --overwrite") from None
    except (ValueError, TypeError) as exc:
        raise SystemExit(f"slipest: {exc}") from None
    return live


def record_path(template: str, wheel: int) -> str:
    """Where wheel ``wheel`` is recorded for ``--record template``."""
    if "{wheel}" in template:
        return template.replace("{wheel}", str(wheel))
    if wheel == 0:
        return template
    stem, ext = os.path.splitext(template)
    return f"{stem}.wheel{wheel}{ext}"


def _percentiles(values: list[np.ndarray]) -> dict:
    if not values:
        return {"n": 0}
    v = np.concatenate(values)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"n": 0}
    return {"n": int(v.size), "median_ms": float(np.median(v) * 1e3), "p99_ms": float(np.percentile(v, 99) * 1e3),
            "max_ms": float(v.max() * 1e3)}


@dataclass
class WheelState:
    stream: WheelStream
    estimator: object
    writer: object = None
    pending: list = field(default_factory=list)  # samples not yet written to the recording
    estimates: int = 0
    cycles_seen: int = 0
    qualities: dict = field(default_factory=dict)


class LiveEstimation:
    """Frames of any wheel in, estimates out (see the module docstring).

    ``on_estimate(wheel, estimate, info)`` is called for every estimate, in
    order; ``info`` holds ``intake`` (arrival time of the cycle's closing
    sample, host monotonic [s]) and ``latency`` (from that arrival to the
    estimate being ready [s]).  ``seq_modulus``/``time_modulus``: the
    source's counter and timestamp ranges (serial: 2**16 and None; CAN: 256
    and 0.65536 s).  ``sim_speed``: see ``--sim-speed``.
    """

    def __init__(self, *, n_legs: int = 4, method: str | None = None, soil: dict | None = None,
                 use_reference: bool = False, model=None,
                 wheels: list[int] | None = None, stuck_samples: int = 50, seq_modulus: int = 1 << 16,
                 time_modulus: float | None = None, sim_speed: float | None = None,
                 record: str | None = None, overwrite: bool = False, source: str = "",
                 on_estimate: Callable | None = None, estimator_factory: Callable | None = None):
        self.n_legs = n_legs
        self.method = method
        self.soil = soil or None
        self.use_reference = use_reference
        self.model = model  # the inverse model (FeatureSurrogate) of the default method; None: the shipped one
        self.only_wheels = set(wheels) if wheels else None
        self.stuck_samples = stuck_samples
        self.seq_modulus = seq_modulus
        self.time_modulus = time_modulus
        self.sim_speed = sim_speed
        self.record = record
        self.overwrite = overwrite
        self.source = source
        self.on_estimate = on_estimate or (lambda wheel, est, info: None)
        self._factory = estimator_factory or self._default_factory
        self.wheels: dict[int, WheelState] = {}
        self.c = {"frames_ignored_wheel": 0, "estimates": 0, "cycles_flagged": 0, "estimator_errors": 0}
        self._intake_latency: list[np.ndarray] = []
        self._estimate_latency: list[float] = []
        self._last_flush = 0.0
        self._spare = None
        self.last_error: str | None = None
        if record and not overwrite and os.path.exists(record_path(record, 0)):
            raise FileExistsError(f"{record_path(record, 0)} exists (a recording is never overwritten by mistake)")

    def warmup(self) -> float:
        """Get the estimator's one-time costs (loading the model, compiled
        code) out of the way before data comes: a throwaway estimator gets two
        synthetic leg cycles, and a fresh one is kept for the first wheel.
        Returns the seconds it took."""
        t0 = time.monotonic()
        est = self._factory(-1)
        n_legs = self.n_legs
        omega = 0.63
        period = 2 * math.pi / (n_legs * omega)
        t = np.arange(0.0, 3 * period, 1e-3)
        theta = -math.pi / n_legs + omega * t
        phase = np.mod(theta + math.pi / n_legs, 2 * math.pi / n_legs) - math.pi / n_legs
        rng = np.random.default_rng(0)
        az = 9.81 + np.where(phase > 0.2, 3.0 * np.sin(2 * math.pi * 12 * t), 0.0) + rng.normal(0, 0.1, t.size)
        try:
            est.push_many(t, az, theta)
        except ValueError:
            pass
        self._spare = self._factory(0)
        return time.monotonic() - t0

    # -- set-up -----------------------------------------------------------------
    def _default_factory(self, wheel: int):
        from slipest.online import SlipEstimator

        kwargs = {"n_legs": self.n_legs, "use_reference": self.use_reference, "soil": self.soil, "model": self.model}
        if self.method is not None:
            kwargs["method"] = self.method
        return SlipEstimator(**kwargs)

    def _wheel(self, wheel: int) -> WheelState | None:
        st = self.wheels.get(wheel)
        if st is not None:
            return st
        if self.only_wheels is not None and wheel not in self.only_wheels:
            return None
        stream = WheelStream(wheel, seq_modulus=self.seq_modulus, time_modulus=self.time_modulus,
                             time_scale=self.sim_speed or 1.0, stuck_samples=self.stuck_samples)
        estimator, self._spare = (self._spare, None) if self._spare is not None else (self._factory(wheel), None)
        st = WheelState(stream, estimator)
        if self.record:
            from slipest.io.log_csv import LogWriter

            meta = {"nL": self.n_legs, "wheel": wheel, "source": self.source or "live",
                    "recorded": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
            st.writer = LogWriter(record_path(self.record, wheel), ("t", "az", "theta", "slip"), metadata=meta,
                                  comments=["recorded live by slipest; az=nan rows stand for lost frames"],
                                  overwrite=self.overwrite)
        self.wheels[wheel] = st
        return st

    # -- input ------------------------------------------------------------------
    def reference(self, wheel: int, slip: float) -> None:
        st = self._wheel(wheel)
        if st is None:
            self.c["frames_ignored_wheel"] += 1
            return
        st.stream.set_reference(slip)

    def samples(self, wheel: int, seq, t, az, theta, intake) -> None:
        """Frames of one wheel, in arrival order (arrays); ``t`` [s] device time
        (wrapped when the source's time is); ``intake`` [s] arrival times."""
        st = self._wheel(wheel)
        if st is None:
            self.c["frames_ignored_wheel"] += len(t)
            return
        if self.sim_speed:
            self._measure_intake(np.asarray(t, np.float64), np.asarray(intake, np.float64))
        self._push(wheel, st, st.stream.add(seq, t, az, theta, intake))

    def _measure_intake(self, t, intake) -> None:
        s = self.sim_speed
        lag = np.asarray(s * intake - t, np.float64).reshape(-1)
        if self.time_modulus:
            lag = np.mod(lag, self.time_modulus)
        self._intake_latency.append(lag / s)

    def _push(self, wheel: int, st: WheelState, s: WheelSamples) -> None:
        if not len(s):
            return
        if st.writer is not None:
            st.pending.append(s)
        try:
            est = st.estimator
            if len(s) <= 8:  # a few samples: one by one is cheaper than the array path
                estimates = []
                use_ref = self.use_reference
                for i in range(len(s)):
                    estimates += est.push(float(s.t[i]), float(s.az[i]), float(s.theta[i]),
                                          float(s.slip[i]) if use_ref else None)
            else:
                estimates = est.push_many(s.t, s.az, s.theta, s.slip if self.use_reference else None)
        except (ValueError, FloatingPointError) as exc:  # never let one bad cycle stop the stream
            self.c["estimator_errors"] += 1
            self.last_error = f"wheel {wheel}: {type(exc).__name__}: {exc}"
            return
        now = time.monotonic()
        for est in estimates:
            st.cycles_seen += 1
            q = str(getattr(est, "quality", "ok"))
            st.qualities[q] = st.qualities.get(q, 0) + 1
            slip = getattr(est, "slip", math.nan)
            if q != "ok" or slip != slip:
                self.c["cycles_flagged"] += 1
            else:
                st.estimates += 1
                self.c["estimates"] += 1
            t_end = float(getattr(est, "t_end", math.nan))
            k = int(np.searchsorted(s.t, t_end)) if t_end == t_end else -1
            intake = float(s.intake[k]) if 0 <= k < len(s) and s.t[k] == t_end else math.nan
            latency = now - intake if intake == intake else math.nan
            if latency == latency:
                self._estimate_latency.append(latency)
            self.on_estimate(wheel, est, {"intake": intake, "latency": latency, "ready": now})

    def flush(self, force: bool = False) -> None:
        """Write the pending samples to the recordings and flush them to the OS
        (every 0.1 s at most unless ``force``: formatting a few rows at a time
        would cost more than estimating them)."""
        now = time.monotonic()
        if not force and now - self._last_flush < 0.1:
            return
        self._last_flush = now
        for st in self.wheels.values():
            if st.writer is not None and st.pending:
                s = WheelSamples.concatenate(st.pending)
                st.writer.write(s.t, s.az, s.theta, s.slip)
                st.pending = []
                st.writer.flush()

    def close(self) -> None:
        """Release held samples, then write, flush and close every recording."""
        try:
            for wheel, st in self.wheels.items():
                self._push(wheel, st, st.stream.flush())
        finally:
            self.flush(force=True)
            for st in self.wheels.values():
                if st.writer is not None:
                    st.writer.close()

    # -- reporting ---------------------------------------------------------------
    def min_cycles(self) -> int:
        return min((st.cycles_seen for st in self.wheels.values()), default=0)

    def counters(self) -> dict:
        c = dict(self.c)
        for wheel, st in sorted(self.wheels.items()):
            wc = st.stream.counters()
            wc["estimates"] = st.estimates
            wc["cycles"] = st.cycles_seen
            wc["qualities"] = dict(st.qualities)
            seg = getattr(st.estimator, "counters", None)
            if seg is not None:
                wc["estimator"] = seg() if callable(seg) else dict(seg)
            if st.writer is not None:
                wc["rows_recorded"] = st.writer.rows_written
            c[f"wheel{wheel}"] = wc
        return c

    def latency(self) -> dict:
        out = {"intake_to_estimate": _percentiles([np.array(self._estimate_latency)])}
        if self.sim_speed:
            out["device_to_intake"] = _percentiles(self._intake_latency)
        return out


def format_counters(source_counters: dict, live: LiveEstimation) -> str:
    """Counters of what was dropped and why, for humans."""
    lines = ["counters:"]
    lines.append("  source: " + ", ".join(f"{k}={v}" for k, v in source_counters.items() if not isinstance(v, dict)))
    c = live.counters()
    lines.append("  estimation: " + ", ".join(f"{k}={v}" for k, v in c.items() if not isinstance(v, dict)))
    for key, wc in c.items():
        if isinstance(wc, dict):
            flat = {k: v for k, v in wc.items() if not isinstance(v, dict)}
            lines.append(f"  {key}: " + ", ".join(f"{k}={v}" for k, v in flat.items())
                         + (f", qualities={wc['qualities']}" if wc.get("qualities") else ""))
    lat = live.latency()
    for name, figures in lat.items():
        if figures.get("n"):
            lines.append(f"  latency {name.replace('_', ' ')}: median {figures['median_ms']:.3f} ms, "
                         f"p99 {figures['p99_ms']:.3f} ms (n={figures['n']})")
    return "\n".join(lines)


def feed_batches(live: "LiveEstimation", batches, t_scale: float) -> None:
    """Feed source batches (:class:`~slipest.io.serial_source.SourceBatch`) to
    ``live``: the IMU samples of each wheel are merged into one push per run
    between reference frames (fewer, larger pushes when the consumer is
    behind); ``t`` [s] = the sample's time field x ``t_scale``."""
    per_wheel: dict[int, tuple[list, list, list, list, list]] = {}

    def push():
        for w, (seq, t, az, th, intake) in per_wheel.items():
            live.samples(w, seq, t, az, th, intake)
        per_wheel.clear()

    for b in batches:
        if b.refs:
            push()
            for wheel, _seq, _t, slip in b.refs:
                live.reference(wheel, slip)
        for wheel, seq, t, az, th in b.imu:
            cols = per_wheel.get(wheel)
            if cols is None:
                cols = per_wheel[wheel] = ([], [], [], [], [])
            cols[0].append(seq)
            cols[1].append(t * t_scale)
            cols[2].append(az)
            cols[3].append(th)
            cols[4].append(b.intake)
    push()


def run_live(source, live: LiveEstimation, args, *, handle_batches: Callable, notices: Callable[[], list[str]],
             source_counters: Callable[[], dict], err=None) -> int:
    """The loop of a live command.  ``handle_batches(batches)`` feeds ``live``.

    Returns the exit code: 0 on a normal stop (duration, cycles, idle,
    Ctrl-C, SIGTERM)."""
    err = err or sys.stderr
    flags = {"usr1": False, "stop": None}

    def _stop(signum, frame):
        # A flag, checked every 50 ms: an exception raised at an arbitrary point
        # could fall between taking samples off the queue and writing them.
        if flags["stop"] is not None:
            raise KeyboardInterrupt  # a second signal: stop at once (recording still closed below)
        flags["stop"] = signal.Signals(signum).name

    def _usr1(signum, frame):
        flags["usr1"] = True

    old = {}
    for sig, handler in ((signal.SIGTERM, _stop), (signal.SIGINT, _stop), (signal.SIGUSR1, _usr1)):
        try:
            old[sig] = signal.signal(sig, handler)
        except ValueError:  # not the main thread: no signal handling
            pass
    # start-up is over: a full garbage collection walking its ~120k objects would stall the stream 30-60 ms
    freeze_startup_objects()
    start = time.monotonic()
    last_data = None
    reason = "stopped"
    try:
        while True:
            batches = source.get(0.05)
            now = time.monotonic()
            if batches:
                handle_batches(batches)
                last_data = now
            live.flush()
            for text in notices():
                print(f"slipest: {text}", file=err, flush=True)
            if flags["usr1"]:
                flags["usr1"] = False
                print(format_counters(source_counters(), live), file=err, flush=True)
            if flags["stop"] is not None:
                reason = f"interrupted ({flags['stop']})"
                break
            if args.duration is not None and now - start >= args.duration:
                reason = f"duration {args.duration:g} s reached"
                break
            if args.cycles is not None and live.wheels and live.min_cycles() >= args.cycles:
                reason = f"{args.cycles} cycles reached"
                break
            if args.idle_timeout is not None and last_data is not None and now - last_data >= args.idle_timeout:
                reason = f"no data for {args.idle_timeout:g} s"
                break
    except KeyboardInterrupt:
        reason = "interrupted"
    finally:
        try:
            source.close()
        finally:
            live.close()
            for sig, handler in old.items():
                signal.signal(sig, handler)
    print(f"slipest: {reason}", file=err)
    print(format_counters(source_counters(), live), file=err, flush=True)
    if getattr(args, "report", None):
        report = {"reason": reason, "source": source_counters(), "estimation": live.counters(),
                  "latency": live.latency(), "elapsed_s": time.monotonic() - start}
        with open(args.report, "w") as fh:
            json.dump(report, fh, indent=1, default=str)
    return 0
