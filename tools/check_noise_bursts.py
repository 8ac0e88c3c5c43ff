#!/usr/bin/env python3
"""The noise-burst rules of slipest.online.SlipEstimator: false alarms on clean drives, what a burst does to an
estimate, and what the stance measure costs.

1. False alarms: ``--drives`` clean drives over the envelope (IMU rate 200,
   250, 500, 1000 or 2000 Hz; noise 0.002-0.025 g; leg speed 0.35-1.15
   rad/s; soil over the domain; 14 cycles of random slip each) through
   ``SlipEstimator``: cycles it calls a burst (``cycles_noise_burst``; every
   one a false alarm, the data are clean).
   With ``--effect-seed S``, also one rover of each kind of
   ``tools/bench_calibration.py`` (every catalog effect, the variants and the
   out-of-catalog effects, drawn with seed ``S``), three 25-cycle drives
   each, 1 kHz, 0.01 g: bursts called on data carrying a sim-to-real effect.
2. Bursts: one 16-cycle drive at slip 0.3, 1 kHz, 0.01 g; cycle 8 gets white
   noise of 0.1 and 0.2 g on its stance only, then on the whole cycle, four
   draws each: the cycle's slip error in its own standard deviations (``z``),
   its reported noise, and whether it was counted as a burst.
3. Cost: the stance measure (``features.stance_noise``) against the rigid
   half's (``features.sample_noise``, the baseline), median of 200 calls on
   one 1 kHz cycle at 0.63 rad/s and one of 9000 samples.

    python tools/check_noise_bursts.py                # 40 drives, about 2 min
    python tools/check_noise_bursts.py --seed 3 --drives 150 --effect-seed 31
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
from tqdm import tqdm

from slipest.features import sample_noise, stance_noise
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.online import SlipEstimator
from slipest.units import G


def false_alarms(drives: int, seed: int) -> tuple[int, int]:
    """(cycles estimated, cycles called a burst) over ``drives`` clean drives."""
    rng = np.random.default_rng(seed)
    estimated = bursts = 0
    for run in tqdm(range(drives), desc="clean drives", file=sys.stderr):
        rate = float(rng.choice([200, 250, 500, 1000, 2000]))
        noise = float(rng.choice([0.002, 0.005, 0.01, 0.025]))
        om, ks, phis, dphi = rng.uniform(0.35, 1.15), rng.uniform(500, 1500), rng.uniform(0.4, 0.8), rng.uniform(0, 0.35)
        cycles = tuple(StickSlipParams(kS=ks, phiS=phis, phiD=max(phis - dphi, 0.1), omega=om, slip=rng.uniform(0, 0.7))
                       for _ in range(14))
        s = simulate_stream(Scenario(cycles=cycles, rate=rate, noise_g=noise, seed=seed * 10_000 + run))
        est = SlipEstimator(n_legs=4)
        est.push_many(s.t, s.az, s.theta)
        est.finish()
        c = est.counters
        estimated += c["cycles_ok"] + c["cycles_repaired"]
        bursts += c["cycles_noise_burst"]
    return estimated, bursts


def effect_alarms(seed: int) -> list[tuple]:
    """(rover kind, cycles, cycles called a burst) of three drives of each ``bench_calibration`` rover kind."""
    import os
    from dataclasses import replace

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import bench_calibration as bc

    from slipest.diagnosis.synth import simulate_run

    rng = np.random.default_rng(seed)
    out = []
    for truth in tqdm(bc.TRUTHS, desc="effect rovers", file=sys.stderr):
        effects, params, _, drives, _ = bc.draw_rover(truth, rng)
        n = called = 0
        for soil in drives:
            sc = bc.drive_scenario(rng, soil)
            run = simulate_run(replace(sc, effects=effects), () if truth in bc.ORDER else bc.stages_of(truth, params))
            est = SlipEstimator(n_legs=4)
            est.push_many(run["t"], run["az"], run["theta"])
            est.finish()
            n += est.counters["cycles"]
            called += est.counters["cycles_noise_burst"]
        out.append((truth, n, called))
    return out


def bursts() -> list[tuple]:
    """(where, level [g], draw, z, reported noise [g], counted) of a burst on cycle 8 of a steady drive."""
    p = StickSlipParams(kS=1200.0, phiS=0.6, phiD=0.35, slip=0.3)
    s = simulate_stream(Scenario.constant(16, p, rate=1000.0, noise_g=0.01, seed=4))
    k, half = 8, math.pi / 4
    phase = s.theta - 2 * half * k
    rows = []
    for where, sel in (("stance", (s.cycle == k) & (phase >= 0.0)), ("whole cycle", s.cycle == k)):
        for level in (0.1, 0.2):
            for draw in range(4):
                az = s.az.copy()
                az[sel] += level * G * np.random.default_rng(draw).standard_normal(int(sel.sum()))
                est = SlipEstimator(n_legs=4)
                out = {e.cycle: e for e in est.push_many(s.t, az, s.theta) + est.finish()}
                e = out[k]
                z = (e.slip - 0.3) / e.slip_std if e.ok else math.nan
                rows.append((where, level, draw, z, e.noise, est.counters["cycles_noise_burst"]))
    return rows


def cost() -> list[tuple]:
    """(samples, stance measure [us], rigid-half measure [us]): medians of 200 calls."""
    out = []
    for n in (int(round(2 * math.pi / 4 / 0.63 * 1000)), 9000):
        ph = np.linspace(-math.pi / 4, math.pi / 4, n)
        az = 9.81 + 0.1 * np.random.default_rng(0).standard_normal(n)
        times = {}
        for f in (stance_noise, sample_noise):
            f(ph, az)
            t = []
            for _ in range(200):
                t0 = time.perf_counter()
                f(ph, az)
                t.append(time.perf_counter() - t0)
            times[f] = 1e6 * float(np.median(t))
        out.append((n, times[stance_noise], times[sample_noise]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drives", type=int, default=40)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--effect-seed", type=int, default=None, help="also drives of every effect rover kind")
    args = ap.parse_args(argv)
    estimated, alarms = false_alarms(args.drives, args.seed)
    print(f"clean drives: {args.drives}, {estimated} cycles estimated, {alarms} called a burst (false alarms)")
    if args.effect_seed is not None:
        rows = effect_alarms(args.effect_seed)
        for truth, n, called in rows:
            print(f"  effect rover {truth:18s}: {n} cycles, {called} called a burst")
        print(f"effect drives: {sum(r[1] for r in rows)} cycles, {sum(r[2] for r in rows)} called a burst")
    print("burst on cycle 8 (slip 0.3, 1 kHz, 0.01 g): where, level, draw, z = error / std, reported noise, counted")
    for where, level, draw, z, noise, counted in bursts():
        print(f"  {where:12s} {level:.1f} g  draw {draw}: z {z:+5.2f}  noise {noise:.3f} g  bursts counted {counted}")
    for n, stance, rigid in cost():
        print(f"cost, {n} samples: stance measure {stance:.1f} us, rigid-half measure (baseline) {rigid:.1f} us, "
              f"ratio {stance / rigid:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
