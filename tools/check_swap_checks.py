#!/usr/bin/env python3
"""The estimator's checks at the leg swaps (``slipest/swap_timing.py``): what they catch, and what they leave alone.

Three parts, each on simulated logs (one soil, slip redrawn every 3 cycles,
1 kHz, 0.01 g; scored from the 12th cycle):

* ``variants``: effects at parametrisations outside the catalog's (time
  skews of either sign, angle offsets, IMU low-passes at 6-40 Hz), with the
  checks on and off: slip RMSE, 95 % coverage, re-timings, the correction in
  force, cycles widened for a sluggish IMU, the settling ratio;
* ``skew``: clean logs with ``theta`` re-timed by a skew, the checks off:
  how much timing error the estimator tolerates (``swap_timing.TOLERANCE``),
  on the one log and on ``bench_accuracy``'s draws (4 soils x 25 cycles,
  default 8 runs);
* ``clean``: ``bench_accuracy``'s draws (4 soils x 25 cycles, leg speed
  steady or changing) rotated over 1 kHz, 250 Hz, 200 Hz, 2 kHz, 0.025 g
  and no noise, plus runs at a constant slip of 0.4-0.5 (the foot re-plants
  there): runs re-timed or widened, which should be none.

Development seeds only (default 9 for the variants and the one skewed log, 3
for the envelope skews and the clean runs); progress on stderr. About 5
minutes for the default sizes.

    python tools/check_swap_checks.py
    python tools/check_swap_checks.py --parts clean --seed 5 --clean-runs 24
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_accuracy as acc  # noqa: E402  (tools/bench_accuracy.py: its draws)

from slipest.model.params import StickSlipParams  # noqa: E402
from slipest.model.scenario import Scenario  # noqa: E402
from slipest.model.stream import simulate_stream  # noqa: E402
from slipest.online import SlipEstimator  # noqa: E402

SPEEDS = np.repeat([0.5, 0.9, 0.7, 1.0, 0.6, 0.8], 5)
VARIANTS = (
    ("time_skew", {"skew": -0.15}, None), ("time_skew", {"skew": -0.06}, SPEEDS),
    ("time_skew", {"skew": 0.06}, SPEEDS), ("time_skew", {"skew": 0.3}, SPEEDS),
    ("angle_offset", {"offset": -0.18}, SPEEDS), ("angle_offset", {"offset": 0.05}, None),
    ("imu_lowpass", {"cutoff": 6.0, "order": 2}, None), ("imu_lowpass", {"cutoff": 10.0, "order": 1}, None),
    ("imu_lowpass", {"cutoff": 10.0, "order": 2}, None), ("imu_lowpass", {"cutoff": 20.0, "order": 4}, None),
    ("imu_lowpass", {"cutoff": 40.0, "order": 2}, None), ("none", {}, None),
)
SKEWS = (-0.08, -0.04, -0.02, -0.01, 0.0, 0.01, 0.02, 0.04, 0.06, 0.08)
CONDITIONS = ((1000.0, 0.01), (250.0, 0.01), (1000.0, 0.025), (200.0, 0.01), (2000.0, 0.01), (1000.0, 0.0))
FROM_CYCLE = 12


def log(effects=(), n: int = 30, omega=None, seed: int = 9):
    """A simulated log: one soil (kS 900 N/m, phiS 0.55, phiD 0.4 rad), slip redrawn every 3 cycles."""
    rng = np.random.default_rng(seed)
    slips = np.repeat(rng.uniform(0.05, 0.45, n // 3), 3)[:n]
    per_cycle = {"slip": slips} if omega is None else {"slip": slips, "omega": omega}
    sc = Scenario.per_cycle(StickSlipParams(kS=900.0, phiS=0.55, phiD=0.4), **per_cycle)
    run = simulate_stream(Scenario(cycles=sc.cycles, rate=1000.0, noise_g=0.01, seed=seed, effects=tuple(effects)))
    return run, slips


def score(t, az, theta, slips, **opts) -> dict:
    """Slip RMSE and 95 % coverage from :data:`FROM_CYCLE`, and the swap checks' counters."""
    est = SlipEstimator(n_legs=4, **opts)
    rows = est.push_many(t, az, theta) + est.finish()
    late = [r for r in rows if r.ok and FROM_CYCLE <= r.cycle < len(slips)]
    err = np.array([r.slip - slips[r.cycle] for r in late])
    std = np.array([r.slip_std for r in late])
    c = est.counters
    settling = est._timing.settling if est._timing is not None else math.nan
    return {"rmse": float(np.sqrt(np.mean(err**2))), "bias": float(err.mean()),
            "coverage": float(np.mean(np.abs(err) <= 1.96 * std)), "n": len(err),
            "retimed": c["timing_corrections"], "shift": c["timing_shift_rad"], "sluggish": c["cycles_sluggish_imu"],
            "settling": settling}


def variants(seed: int) -> None:
    print(f"effects outside the catalog's parametrisations (seed {seed}, 30 cycles, scored from cycle {FROM_CYCLE})")
    print(f"  {'effect':48s} {'checks on: RMSE cover':>22s} {'re-timed':>8s} {'shift':>7s} {'widened':>7s} "
          f"{'settling':>8s} | {'checks off: RMSE cover':>22s}")
    for name, params, omega in tqdm(VARIANTS, desc="variants", file=sys.stderr):
        effects = () if name == "none" else ({"name": name, **params},)
        run, slips = log(effects, omega=omega, seed=seed)
        on = score(run.t, run.az, run.theta, slips)
        off = score(run.t, run.az, run.theta, slips, swap_checks=False)
        what = f"{name} {params}" + (", speed changing" if omega is not None else "")
        print(f"  {what:48s} {on['rmse']:13.3f} {on['coverage']:7.0%} {on['retimed']:8d} {on['shift']:+7.3f} "
              f"{on['sluggish']:7d} {on['settling']:+8.3f} | {off['rmse']:13.3f} {off['coverage']:7.0%}")


def skews(seed: int, envelope_seed: int, runs: int) -> None:
    print(f"\nclean log re-timed by a skew, checks off (seed {seed}): the timing error the estimator tolerates")
    run, slips = log(seed=seed)
    for tau in tqdm(SKEWS, desc="skews", file=sys.stderr):
        theta = np.interp(run.t - tau, run.t, run.theta)  # the encoder's reading tau late (tau < 0: early)
        r = score(run.t, run.az, theta, slips, swap_checks=False)
        print(f"  skew {1e3 * tau:+5.0f} ms: slip RMSE {r['rmse']:.3f}, bias {r['bias']:+.3f}, coverage {r['coverage']:.0%}")
    print(f"\n{runs} envelope runs (bench_accuracy's draws, 1 kHz, 0.01 g, seed {envelope_seed}) re-timed by a skew, "
          "checks off; scored from the 10th cycle on a soil")
    rng = np.random.default_rng(envelope_seed)
    sims = []
    for r in range(runs):
        d = acc.draw_run(rng, 4, 25, changing=bool(r % 2))
        sims.append((simulate_stream(acc.scenario(d, 1000.0, 0.01)), np.asarray(d["slip"]), d["since"]))
    for tau in tqdm(SKEWS, desc="envelope skews", file=sys.stderr):
        err, std = [], []
        for s, slips_, since in sims:
            est = SlipEstimator(n_legs=4, swap_checks=False)
            rows = est.push_many(s.t, s.az, np.interp(s.t - tau, s.t, s.theta)) + est.finish()
            for e in rows:
                if e.ok and e.cycle < slips_.size and since[e.cycle] >= 10:  # as bench_accuracy scores
                    err.append(e.slip - slips_[e.cycle])
                    std.append(e.slip_std)
        err, std = np.asarray(err), np.asarray(std)
        print(f"  skew {1e3 * tau:+5.0f} ms: slip RMSE {np.sqrt(np.mean(err**2)):.4f}, bias {err.mean():+.4f}, "
              f"coverage {np.mean(np.abs(err) <= 1.96 * std):.1%} ({err.size} cycles)")


def clean(seed: int, runs: int, high_slip: int) -> None:
    rng = np.random.default_rng(seed)
    draws = [acc.draw_run(rng, 4, 25, changing=bool(r % 2)) for r in range(runs)]
    flagged, settling = [], []
    for i, run in enumerate(tqdm(draws, desc="clean runs", file=sys.stderr)):
        rate, noise = CONDITIONS[i % len(CONDITIONS)]
        s = simulate_stream(acc.scenario(run, rate, noise))
        est = SlipEstimator(n_legs=4)
        est.push_many(s.t, s.az, s.theta)
        est.finish()
        c = est.counters
        settling.append(est._timing.settling)
        if c["timing_corrections"] or c["cycles_sluggish_imu"]:
            flagged.append(f"run {i} ({rate:g} Hz, {noise:g} g)")
    for i in tqdm(range(high_slip), desc="constant high slip", file=sys.stderr):
        kS, phiS, phiD = acc.draw_soil(rng)
        n = 25
        sc = Scenario.per_cycle(StickSlipParams(), dict(noise_g=0.01, rate=1000.0, seed=int(rng.integers(2**31))),
                                slip=np.full(n, rng.uniform(0.4, 0.5)), kS=np.full(n, kS), phiS=np.full(n, phiS),
                                phiD=np.full(n, phiD), omega=np.full(n, rng.uniform(0.35, 1.1)))
        s = simulate_stream(sc)
        est = SlipEstimator(n_legs=4)
        est.push_many(s.t, s.az, s.theta)
        est.finish()
        c = est.counters
        settling.append(est._timing.settling)
        if c["timing_corrections"] or c["cycles_sluggish_imu"]:
            flagged.append(f"constant-slip run {i}")
    s = np.asarray(settling, dtype=float)
    print(f"\nclean runs (seed {seed}): {runs} envelope runs and {high_slip} at constant slip 0.4-0.5; re-timed or "
          f"widened: {len(flagged)}{' (' + ', '.join(flagged) + ')' if flagged else ''}; final settling ratios "
          f"{np.nanmin(s):+.3f} to {np.nanmax(s):+.3f} (sluggish from 0.12)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="variants,skew,clean", help="comma-separated: variants, skew, clean")
    ap.add_argument("--seed", type=int, default=None, help="seed (default 9 for variants and skew, 3 for clean)")
    ap.add_argument("--clean-runs", type=int, default=12, help="envelope runs of the clean part")
    ap.add_argument("--high-slip-runs", type=int, default=12, help="constant high-slip runs of the clean part")
    ap.add_argument("--envelope-runs", type=int, default=8, help="envelope runs of the skew part")
    args = ap.parse_args(argv)
    parts = {p.strip() for p in args.parts.split(",")}
    unknown = parts - {"variants", "skew", "clean"}
    if unknown:
        ap.error(f"unknown part(s): {', '.join(sorted(unknown))}")
    if "variants" in parts:
        variants(9 if args.seed is None else args.seed)
    if "skew" in parts:
        skews(9 if args.seed is None else args.seed, 3 if args.seed is None else args.seed, args.envelope_runs)
    if "clean" in parts:
        clean(3 if args.seed is None else args.seed, args.clean_runs, args.high_slip_runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
