#!/usr/bin/env python3
"""Where the time of a cycle's closing sample goes: a per-stage breakdown of ``SlipEstimator.push``.

Pushes a simulated log (``tools/bench_replay.py``'s 10-minute log, or
``--log``) one sample at a time, twice in this process:

1. bare, as ``tools/bench_replay.py`` item 3 does: the duration of every
   ``push`` that closes a cycle (the headline figure), and of the other
   pushes (microseconds per sample);
2. instrumented: the stages of each closing push timed separately, by
   wrapping them (each wrapper adds about 0.1-0.3 us):

   * ``segmenter``: ``CycleSegmenter.push`` on the closing sample (cycle
     close, window checks, ``LegCycle``);
   * ``features``: ``cycle_features`` of the closed window;
   * ``estimator``: ``SoilSlipEstimator.update``, split into its compiled
     ``kernel`` (the cycle step) and the ``python`` rest (whitening, moments,
     soil summary, result object);
   * ``online``: the rest of ``push`` (speed check, ``Estimate``).

3. paced (``--paced-cycles``, default 20, about 50 s): the same log's first cycles pushed at the log's
   own time, one sample per millisecond as a live IMU sends them, the process idle in between (as
   ``slipest demo`` and a rover are). The closing pushes take longer than back to back: on this
   kind of machine the same compiled cycle step takes 0.68 ms when run back to back and 1.2-1.5 ms
   after 10 ms of sleep or of busy waiting, even with its data read just before: after a pause its
   memory reads are slower, not its arithmetic (docs/estimator.md, "Paced at real time");
4. then a drive whose leg speed changes every 3-6 cycles (0.35-1.1 rad/s, ``tools/bench_accuracy.py``'s
   changing-speed draw, 1 kHz, 0.01 g; ``--speed-cycles``), pushed one sample at a time: the closing
   pushes, and how many built a (speed, noise) table on the closing sample (about 0.05 s each; the
   estimator builds them before the close, the stream's first cycle's included).

Figures are milliseconds (median, p90, p99, max) with the load average of
the machine at the time (other processes' load shows in the tail); the
closing pushes' CPU time (``time.thread_time``) leaves out the time the
process waited for the CPU, an estimate of the figures on a quiet machine
(the caches are still shared).

    python tools/bench_latency.py               # ~90 s (50 s of it the real-time round)
    python tools/bench_latency.py --quick       # the first 2.5 min of the log only
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import slipest.estimator as estimator_mod
import slipest.online as online_mod
from slipest.io.log_csv import LogReader
from slipest.online import SlipEstimator

clock = time.perf_counter

#: Compiled functions called by ``SoilSlipEstimator.update`` that make up its kernel time.
KERNELS = ("_cycle_step",)


def _stats(x) -> str:
    x = np.asarray(x) * 1e3
    if x.size == 0:
        return "-"
    return (f"median {np.median(x):.3f}  p90 {np.percentile(x, 90):.3f}  p99 {np.percentile(x, 99):.3f}  "
            f"max {x.max():.3f}")


def closing_pushes(t, az, th, n_legs, *, paced: bool = False, max_closes: int | None = None):
    """Wall and CPU (this thread's) durations [s] of the closing pushes of the log pushed one sample at a time,
    and the mean wall duration of a push [s]. ``paced``: each sample waits (sleeping) until its time (``t``
    [s]) has come on this host's clock, as a live stream arrives; ``max_closes``: stop after that many."""
    SlipEstimator(n_legs=n_legs).push_many(t[:20000], az[:20000], th[:20000])  # warm up
    est = SlipEstimator(n_legs=n_legs)
    push = est.push
    cpu = time.thread_time
    closing, closing_cpu = [], []
    n = 0
    t0 = clock()
    for a, b, c in zip(t, az, th):
        if paced:
            wait = (a - t[0]) - (clock() - t0)
            if wait > 0.0:
                time.sleep(wait)
        n += 1
        s = clock()
        sc = cpu()
        if push(a, b, c):
            closing_cpu.append(cpu() - sc)
            closing.append(clock() - s)
            if max_closes is not None and len(closing) >= max_closes:
                break
    return np.array(closing), np.array(closing_cpu), (clock() - t0) / n


class _Timer:
    """Accumulates the time spent in wrapped callables, per stage, for the current push."""

    def __init__(self):
        self.acc = {}

    def wrap(self, stage, fn):
        acc = self.acc

        def timed(*a, **k):
            s = clock()
            try:
                return fn(*a, **k)
            finally:
                acc[stage] = acc.get(stage, 0.0) + clock() - s

        return timed


def instrumented(t, az, th, n_legs):
    """Per-stage durations [s] of every closing push."""
    tm = _Timer()
    saved = {}
    try:
        saved[(online_mod, "cycle_features")] = online_mod.cycle_features
        online_mod.cycle_features = tm.wrap("features", online_mod.cycle_features)
        for name in KERNELS:
            saved[(estimator_mod, name)] = getattr(estimator_mod, name)
            setattr(estimator_mod, name, tm.wrap("kernel", getattr(estimator_mod, name)))
        est = SlipEstimator(n_legs=n_legs)
        est.segmenter.push = tm.wrap("segmenter", est.segmenter.push)
        est.filter.update = tm.wrap("estimator", est.filter.update)
        push = est.push
        rows = []
        for a, b, c in zip(t, az, th):
            tm.acc.clear()
            s = clock()
            r = push(a, b, c)
            total = clock() - s
            if r and r[0].ok:
                g = tm.acc.get
                rows.append((total, g("segmenter", 0.0), g("features", 0.0), g("estimator", 0.0), g("kernel", 0.0)))
    finally:
        for (mod, name), fn in saved.items():
            setattr(mod, name, fn)
    r = np.array(rows)
    total, seg, feat, upd, ker = r.T
    return {
        "total (instrumented)": total,
        "segmenter": seg,
        "features": feat,
        "estimator": upd,
        "  kernel": ker,
        "  python": upd - ker,
        "online": total - seg - feat - upd,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", help="log to push (default: write the 10-minute benchmark log of bench_replay.py)")
    ap.add_argument("--quick", action="store_true", help="push the first 150 s of the log only")
    ap.add_argument("--repeat", type=int, default=1, help="bare/instrumented rounds (default 1)")
    ap.add_argument("--paced-cycles", type=int, default=20,
                    help="closing pushes of the real-time round (default 20, about 50 s; 0: none)")
    ap.add_argument("--speed-cycles", type=int, default=100,
                    help="cycles of the changing-speed drive (default 100; 0: none)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="slipest-lat-") as tmp:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_replay import log_or_default

        log = log_or_default(args.log, tmp)
        with LogReader(log) as r:
            d = r.read_all()
    n = 150_000 if args.quick else d.t.size
    t, az, th = d.t[:n].tolist(), d.az[:n].tolist(), d.theta[:n].tolist()
    n_legs = d.metadata.n_legs or 4
    for rnd in range(args.repeat):
        load0 = os.getloadavg()[0]
        closing, closing_cpu, per = closing_pushes(t, az, th, n_legs)
        stages = instrumented(t, az, th, n_legs)
        load1 = os.getloadavg()[0]
        print(f"round {rnd + 1}: {n} samples, load average {load0:.2f} -> {load1:.2f} on {os.cpu_count()} CPUs")
        print(f"  {'closing push (bare)':22s} {_stats(closing)} ms   ({closing.size} cycles; {per * 1e6:.2f} us/push)")
        print(f"  {'  its CPU time':22s} {_stats(closing_cpu)} ms   (without the time other processes had the CPU)")
        for name, x in stages.items():
            print(f"  {name:22s} {_stats(x)} ms")
    if args.paced_cycles > 0:
        load0 = os.getloadavg()[0]
        closing, closing_cpu, _ = closing_pushes(t, az, th, n_legs, paced=True, max_closes=args.paced_cycles)
        print(f"paced at the log's time (one sample per {1e3 * (t[1] - t[0]):.1f} ms, idle between), load "
              f"{load0:.2f} -> {os.getloadavg()[0]:.2f}:")
        print(f"  {'closing push (bare)':22s} {_stats(closing)} ms   ({closing.size} cycles)")
        print(f"  {'  its CPU time':22s} {_stats(closing_cpu)} ms")
    if args.speed_cycles > 0:
        closing, built = changing_speed(args.speed_cycles, n_legs)
        print(f"changing speed: {closing.size} closes, {int(built.sum())} built a table on the closing sample "
              f"(cycles {np.flatnonzero(built).tolist()})")
        print(f"  {'closing push (bare)':22s} {_stats(closing)} ms")
        print(f"  {'  without the first':22s} {_stats(closing[1:])} ms")
    return 0


def changing_speed(n_cycles: int, n_legs: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Durations [s] of the closing pushes of a simulated drive whose leg speed changes every 3-6 cycles, and
    whether each built a table."""
    from bench_replay import changing_speed_scenario

    from slipest.model.stream import simulate_stream

    s = simulate_stream(changing_speed_scenario(n_cycles, seed))
    est = SlipEstimator(n_legs=n_legs)
    tables = est.filter.tables
    push = est.push
    closing, built = [], []
    for a, b, c in zip(s.t.tolist(), s.az.tolist(), s.theta.tolist()):
        before = tables.builds
        t0 = clock()
        if push(a, b, c):
            closing.append(clock() - t0)
            built.append(tables.builds > before)
    return np.array(closing), np.array(built)


if __name__ == "__main__":
    sys.exit(main())
