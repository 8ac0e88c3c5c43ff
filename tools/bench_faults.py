#!/usr/bin/env python3
"""Robustness benchmark: estimates from streams with the faults real ones have, against the same streams clean.

Part 1, logs with injected faults (issue 13's targets): the runs of
``tools/bench_accuracy.py`` (soils over the whole domain, slip and leg
speed changing; soil unknown) at 1 kHz and 0.01 g, once clean and once
with, drawn per leg cycle: one isolated spike of 3-15 g (either sign) in
30 % of the cycles, 1-3 consecutive rows missing in 30 %, 1-2 ``az = NaN``
samples in 10 %, anywhere in the cycle. Reported: the share of cycles
estimated, slip RMSE and 95 % coverage from the 10th cycle of a soil, for
both, and how many faulted cycles were repaired. Targets: >= 90 %
estimated, slip RMSE within 0.005 of the clean logs, coverage 0.90-0.99.

Part 2, a corrupted serial link (``--serial``): firmware-sim on a
pseudo-terminal with 1e-4 of its bytes corrupted, ``slipest serial`` on the
other end (real processes), 40 leg cycles at 8x speed. Reported: cycles
estimated of those closed, frames lost, and that no estimate came from a
corrupted frame (the CRC rejects them: every frame the device corrupted is
counted lost by the receiver). Target: >= 80 % of cycles estimated.

    python tools/bench_faults.py                      # part 1: 8 runs x 4 soils x 25 cycles, ~2 min
    python tools/bench_faults.py --serial             # and part 2, ~1 min more
    python tools/bench_faults.py --runs 4 --seed 11   # development seed (the official one, 2024, is never tuned on)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_accuracy as acc  # noqa: E402  (tools/bench_accuracy.py: the runs and the figures)

from slipest.inverse.feature_inverse import FeatureInverse  # noqa: E402
from slipest.inverse.surrogate import load_inverse_model  # noqa: E402
from slipest.units import G  # noqa: E402

#: Per-cycle probabilities of the injected faults.
P_SPIKE, P_MISSING, P_NAN = 0.3, 0.3, 0.1


def injector(seed: int, tally: dict):
    """``inject(t, az, theta, cycle)`` putting the faults of the module docstring in a stream, counting them."""
    rng = np.random.default_rng(seed)

    def inject(t, az, theta, cycle):
        az = az.copy()
        keep = np.ones(t.size, bool)
        starts = np.flatnonzero(np.diff(np.concatenate([[-1], cycle])))
        ends = np.append(starts[1:], t.size)
        for a, b in zip(starts, ends):
            if b - a < 20:
                continue
            faulted = False
            if rng.random() < P_SPIKE:
                j = int(rng.integers(a + 2, b - 2))
                az[j] += rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 15.0) * G
                tally["spikes"] += 1
                faulted = True
            if rng.random() < P_MISSING:
                j = int(rng.integers(a + 2, b - 5))
                n = int(rng.integers(1, 4))
                keep[j : j + n] = False
                tally["rows_missing"] += n
                faulted = True
            if rng.random() < P_NAN:
                n = int(rng.integers(1, 3))
                for j in rng.choice(np.arange(a + 2, b - 2), n, replace=False):
                    az[j] = math.nan
                tally["nan_samples"] += n
                faulted = True
            tally["cycles_faulted"] += faulted
        return t[keep], az[keep], theta[keep]

    return inject


def logs(args) -> dict:
    model = load_inverse_model(args.model)
    inverse = FeatureInverse(model)
    rng = np.random.default_rng(args.seed)
    runs = [acc.draw_run(rng, args.soils, args.cycles_per_soil, changing=bool(r % 2)) for r in range(args.runs)]
    tally = dict.fromkeys(("cycles_faulted", "spikes", "rows_missing", "nan_samples"), 0)
    clean, faulted = [], []
    with tqdm(total=2 * len(runs), desc="runs (clean, faulted)", file=sys.stderr) as bar:
        for i, run in enumerate(runs):
            clean.append(acc.run_one(run, 1000.0, 0.01, inverse, model))
            bar.update(1)
            faulted.append(acc.run_one(run, 1000.0, 0.01, inverse, model, inject=injector(args.seed + 1000 + i, tally)))
            bar.update(1)
    every = lambda c: np.ones(c["since"].size, bool)  # noqa: E731
    out = {"clean": acc.figures(clean, every, args.from_cycle), "faulted": acc.figures(faulted, every, args.from_cycle),
           "injected": tally,
           "cycles_repaired": int(sum(int((r["quality"] == "repaired").sum()) for r in faulted)),
           "samples_repaired": int(sum(int(r["repaired"].sum()) for r in faulted))}
    c, f = out["clean"], out["faulted"]
    print(f"\nlogs with injected faults: {args.runs} runs x {args.soils} soils x {args.cycles_per_soil} cycles, 1 kHz, "
          f"0.01 g, soil unknown, seed {args.seed}; scored from the {args.from_cycle}th cycle on a soil")
    print(f"  injected: {tally['cycles_faulted']} cycles faulted of {c['cycles']}: {tally['spikes']} spikes, "
          f"{tally['rows_missing']} rows missing, {tally['nan_samples']} NaN samples; "
          f"{out['cycles_repaired']} cycles estimated as 'repaired' ({out['samples_repaired']} samples)")
    print(f"  {'':8s} {'estimated':>9s} {'slip RMSE':>9s} {'cov95':>6s} {'dphi RMSE':>9s}   not estimated")
    for name, fig in (("clean", c), ("faulted", f)):
        why = ", ".join(f"{q} {n}" for q, n in fig["not_estimated"].items())
        print(f"  {name:8s} {fig['estimated']:9.3f} {fig['slip']['rmse']:9.4f} {fig['slip']['coverage95']:6.3f} "
              f"{fig['dphi']['rmse']:9.4f}   {why}")
    d = f["slip"]["rmse"] - c["slip"]["rmse"]
    print(f"  targets: estimated >= 0.90: {f['estimated']:.3f}; slip RMSE within 0.005 of clean: {d:+.4f}; "
          f"coverage 0.90-0.99: {f['slip']['coverage95']:.3f}")
    return out


def serial(args) -> dict:
    from tests.hil_support import Stopping, firmware_sim, serial_device, slipest_cmd

    with tempfile.TemporaryDirectory() as tmp:
        live, dev_report = Path(tmp) / "live.json", Path(tmp) / "device.json"
        with Stopping() as procs:
            dev = procs.add(firmware_sim("serial", "--cycles", "40", "--speed", "8", "--noise", "0.01", "--seed", "5",
                                         "--corrupt-rate", str(args.corrupt_rate), "--fault-seed", "9",
                                         "--report", str(dev_report), "--settle", "0.2"))
            est = procs.add(slipest_cmd("serial", serial_device(dev), "--format", "none", "--idle-timeout", "4",
                                        "--report", str(live), "--sim-speed", "8"))
            rc = est.wait(300)
            dev.wait(60)
        device = json.loads(dev_report.read_text())
        report = json.loads(live.read_text())
    wheel = report["estimation"]["wheel0"]
    cycles = wheel.get("cycles_seen", 0)
    estimates = wheel.get("estimates", 0)
    injected = device["faults"]
    out = {"rc": rc, "cycles": cycles, "estimated": estimates, "fraction": estimates / cycles if cycles else math.nan,
           "frames_corrupted": injected["frames_corrupted"], "bytes_corrupted": injected["bytes_corrupted"],
           "frames_lost": wheel.get("frames_lost"), "qualities": wheel.get("qualities", {})}
    print(f"\nserial link, {args.corrupt_rate:g} of bytes corrupted: {injected['bytes_corrupted']} bytes in "
          f"{injected['frames_corrupted']} frames; the receiver counted {out['frames_lost']} frames lost; "
          f"{estimates} of {cycles} cycles estimated ({out['fraction']:.3f}; target >= 0.80); qualities "
          f"{out['qualities']}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--soils", type=int, default=4)
    ap.add_argument("--cycles-per-soil", type=int, default=25)
    ap.add_argument("--from-cycle", type=int, default=10)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--model", help="inverse model file (default: the shipped one)")
    ap.add_argument("--serial", action="store_true", help="also part 2: a corrupted serial link, live")
    ap.add_argument("--corrupt-rate", type=float, default=1e-4, help="share of bytes corrupted in part 2")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    t0 = time.time()
    out = {"logs": logs(args)}
    if args.serial:
        out["serial"] = serial(args)
    print(f"\n{time.time() - t0:.0f} s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
