"""Benchmark the leg-cycle segmenter and the CSV log format.

Run from the repository root:

    python tools/bench_segmentation.py [--seconds 3600] [--push-seconds 300] [--repeat 3] [--baseline FILE]

Prints, for a synthetic 1 kHz stream (default: one hour, 3.6 M samples):
  * CycleSegmenter.push (one sample at a time): samples/s and us per sample,
  * CycleSegmenter.push_many (chunks of 65536): samples/s,
  * LogWriter write rows/s (chunks of 65536, flushed after each, as the live
    recorder does) and LogReader read rows/s (whole file, and iter_chunks),
  * a replay (iter_chunks -> push_many) in samples/s.
Each figure is the best of --repeat runs; wall-clock and CPU (process) time
are both shown, since a shared machine can slow the wall clock down.
``--baseline FILE``: another version of ``slipest/segmentation.py`` (e.g.
``git show b8ba846:slipest/segmentation.py > /tmp/seg_base.py``) whose push
and push_many are timed too, in this process on the same stream, alternating
runs with the current one, with the ratio current / baseline of CPU times and
whether both give the same cycles and counters.
The log is written to a temporary directory that is removed afterwards.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from slipest.io.log_csv import LogReader, LogWriter, read_log  # noqa: E402
from slipest.segmentation import CycleSegmenter  # noqa: E402

CHUNK = 65536


def make_stream(seconds: float, fs: float = 1000.0, omega: float = 0.63, n_legs: int = 4, seed: int = 0):
    """t [s], az [m/s^2], theta [rad] wrapped to [-pi, pi), slip [-]."""
    rng = np.random.default_rng(seed)
    n = int(seconds * fs)
    t = np.arange(n) / fs + rng.uniform(-2e-5, 2e-5, n)
    th = -0.3 + omega * t
    p = 2 * math.pi / n_legs
    ph = (th + p / 2) % p - p / 2
    az = 9.81 + 2.0 * np.exp(-8.0 * np.maximum(ph, 0.0)) * np.sin(40.0 * ph) + rng.normal(0, 0.05, n)
    th = (th + math.pi) % (2 * math.pi) - math.pi
    slip = np.full(n, 0.25)
    return t, az, th, slip


def best_of(repeat, fn):
    """(result, best wall s, best cpu s) over `repeat` runs."""
    walls, cpus = [], []
    res = None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        res = fn()
        cpus.append(time.process_time() - c0)
        walls.append(time.perf_counter() - w0)
    return res, min(walls), min(cpus)


def load_baseline(path):
    """The module in file ``path``, imported as part of the slipest package (its relative imports work)."""
    spec = importlib.util.spec_from_file_location("slipest._segmentation_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def cycle_fields(cycles):
    """Comparable content of LegCycles (of any version of the class)."""
    return [(c.k, c.t_start, c.t_end, c.n_samples, c.quality, c.flags, c.t.tobytes(), c.az.tobytes(),
             c.theta_phase.tobytes()) for c in cycles]


def report(name, n, wall, cpu, unit="samples"):
    print(f"{name:38s} {n / wall / 1e6:8.2f} M {unit}/s wall   {n / cpu / 1e6:8.2f} M {unit}/s cpu")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3600.0, help="length of the stream/log at 1 kHz [s]")
    ap.add_argument("--push-seconds", type=float, default=300.0, help="part of it fed to push() one by one [s]")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure (best is shown)")
    ap.add_argument("--baseline", metavar="FILE", help="another segmentation.py to time alongside (ratios)")
    args = ap.parse_args(argv)

    t, az, th, slip = make_stream(args.seconds)
    n = t.size
    print(f"stream: {n} samples ({args.seconds:.0f} s at 1 kHz), theta wrapped, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")

    # --- push, one sample at a time; push_many, chunks --------------------
    m = min(n, int(args.push_seconds * 1000))
    tl, al, hl = t[:m].tolist(), az[:m].tolist(), th[:m].tolist()

    def run_push(cls):
        seg = cls()
        push = seg.push
        out = []
        for a, b, c in zip(tl, al, hl):
            r = push(a, b, c)
            if r:
                out += r
        return out, seg.counters

    def run_many(cls, nn=n):
        seg = cls()
        out = []
        for i in range(0, nn, CHUNK):
            j = min(i + CHUNK, nn)
            out += seg.push_many(t[i:j], az[i:j], th[i:j])
        return out, seg.counters

    versions = {"": CycleSegmenter}
    if args.baseline:
        versions["baseline "] = load_baseline(args.baseline).CycleSegmenter
    push_cpu, many_cpu, results = {}, {}, {}
    for _ in range(args.repeat):  # alternate the versions, so that both see the same load
        for label, cls in versions.items():
            res, wall, cpu = best_of(1, lambda: run_push(cls))
            push_cpu[label] = min(push_cpu.get(label, (math.inf,) * 2), (cpu, wall))
            res_many, wall, cpu = best_of(1, lambda: run_many(cls))
            many_cpu[label] = min(many_cpu.get(label, (math.inf,) * 2), (cpu, wall))
            results[label] = (res, res_many, run_many(cls, m))
    for label in versions:
        (cpu, wall), (mcpu, mwall) = push_cpu[label], many_cpu[label]
        report(f"{label}push() x {m}", m, wall, cpu)
        print(f"{'':38s} {wall / m * 1e6:8.3f} us/sample wall {cpu / m * 1e6:8.3f} us/sample cpu")
        report(f"{label}push_many() chunks of {CHUNK}", n, mwall, mcpu)
        (push_cycles, push_counts), (cycles, _), (first, first_counts) = results[label]
        same = cycle_fields(first) == cycle_fields(push_cycles) and first_counts == push_counts
        print(f"{'':38s} {len(cycles)} cycles, {sum(c.ok for c in cycles)} ok; "
              f"push == push_many on the first {m} samples: {same}")
    if args.baseline:
        b = "baseline "
        same = all(cycle_fields(x[0]) == cycle_fields(y[0]) and x[1] == y[1]
                   for x, y in zip(results[""], results[b]))
        print(f"current / baseline CPU time: push {push_cpu[''][0] / push_cpu[b][0]:.2f}, "
              f"push_many {many_cpu[''][0] / many_cpu[b][0]:.2f}; same cycles and counters: {same}")

    # --- log write / read ------------------------------------------------
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.csv")

        def write():
            with LogWriter(path, ("t", "az", "theta", "slip"), metadata={"nL": 4, "slip": 0.25}, overwrite=True) as w:
                for i in range(0, n, CHUNK):
                    j = min(i + CHUNK, n)
                    w.write(t[i:j], az[i:j], th[i:j], slip=slip[i:j])
                    w.flush()

        _, wall, cpu = best_of(args.repeat, write)
        size = os.path.getsize(path)
        report(f"LogWriter write ({size / 1e6:.0f} MB)", n, wall, cpu, "rows")
        print(f"{'':38s} {wall:8.2f} s wall for the whole log")

        log, wall, cpu = best_of(args.repeat, lambda: read_log(path))
        report("read_log (whole file)", n, wall, cpu, "rows")
        assert len(log) == n
        err = max(float(np.max(np.abs(log.t - t))), float(np.max(np.abs(log.theta - th))))
        print(f"{'':38s} max round-trip error t/theta: {err:.2e}")
        del log

        def read_chunks():
            rows = 0
            with LogReader(path) as r:
                for c in r.iter_chunks(CHUNK):
                    rows += len(c)
            return rows

        rows, wall, cpu = best_of(args.repeat, read_chunks)
        report(f"LogReader.iter_chunks({CHUNK})", rows, wall, cpu, "rows")

        def replay():
            seg = CycleSegmenter()
            k = 0
            with LogReader(path) as r:
                for c in r.iter_chunks(CHUNK):
                    k += len(seg.push_many(c.t, c.az, c.theta))
            return k

        k, wall, cpu = best_of(args.repeat, replay)
        report("replay: read + segment", n, wall, cpu)
        print(f"{'':38s} {k} cycles")


if __name__ == "__main__":
    main()
