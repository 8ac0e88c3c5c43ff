#!/usr/bin/env python
"""Check the sim-to-real diagnosis blind: can it name an effect it was not told about?

For each catalog effect (and for no effect), ``--cases`` logs are simulated
with a soil and effect parameters drawn at random (hidden from the
diagnosis), then :func:`slipest.diagnosis.run.diagnose` is run on the bare
samples ``t, az, theta, slip`` (plus the known hardware: masses, spoke
length, legs). Also with effects *not* in the catalog, made up here, for
which the right answer is ``unexplained`` (or at least not a catalog name).

Each log: 10 slip levels 0.05-0.5 in random order, 5 cycles each (50
cycles), IMU at 1 kHz with 0.01 g noise, kappa and soil drawn per case:
kS U(600, 1400) N/m, phiS U(0.40, 0.70) rad, phiS - phiD U(0.05, 0.30)
rad, kappa U(0.25, 0.40). Catalog effect parameters are drawn uniformly
from the catalog's *moderate* ranges (``slipest.model.effects``; the
touchdown amplitude with a random sign) and redrawn until the effect
changes the cycles' Da by >= 10% on average (``--min-change``); the change
is reported per case.

``time_skew`` logs change the leg speed from one slip level to the next
(U(0.4, 1.1) rad/s per level; at one speed a time skew is an angle offset);
the other logs run at the model's default leg speed.

Variants of catalog effects *outside their catalog draws* (withheld: the
right answer is the catalog effect they vary), to measure how the fit
generalises beyond the parametrisation it was built on:

* ``ripple_harmonic``: a ``speed_ripple`` 2, 3 or 4 times per leg cycle
  (the catalog draws ripple once per leg cycle), amplitude and phase from
  the catalog's moderate ranges;
* ``impact_shape``: a ``touchdown_impact`` of another shape: onset phase
  U(-pi, pi) (the catalog draws 0: the transient starts at zero), tau
  log-U(0.3, 4) s (catalog 0.8-1.2 s), f log-U(4, 30) Hz, |A| U(8, 20) m/s^2.

Both are redrawn like catalog effects (Da changed by >= 10%) and, unlike
them, also when they change Da by more than 60% (``VARIANT_MAX_CHANGE``: a
slowly decaying impact ringing near a multiple of the cycle frequency
builds up without bound).

Out-of-catalog effects (made up here, physically plausible):

* ``hub_rocking``: a hub pitch/roll rocking mode excited at every midstance
  (load transfer onto the planted leg): ``az += A exp(-s/tau) sin(2 pi f s)``,
  ``s`` the time since the midstance, f 2-4 Hz, tau 0.3-0.6 s, |A| 3-10 m/s^2;
* ``bracket_resonance``: the IMU on a bracket with its own lightly damped
  resonance (second structural mode), base excitation transmissibility
  ``H(s) = (1 + 2 z s/wn) / (1 + 2 z s/wn + s^2/wn^2)``, fn 10-15 Hz, z 0.03-0.08;
* ``encoder_quantisation``: a coarse encoder, theta rounded to
  ``2 pi / counts`` with counts 128-256 per revolution (no Da criterion;
  the diagnosis interpolates such an angle between its count changes,
  :func:`slipest.dequantize.dequantize_log`, so ``none`` is a right
  answer too).

The first two are drawn like catalog effects (Da changed by >= 10%).

``--fit-effects`` restricts the catalog effects the diagnosis fits (e.g. to
measure the catalog as it was before an effect was added).

Prints the confusion matrix (true effect x verdict), per effect the share of
cases with the right effect ranked first and named, the held-out shrink of
the right effect, the rate of ``none`` on clean data and of misnamed
out-of-catalog cases, and the time per diagnosis; writes a PNG of the
confusion matrix and (``--json``) every case. Progress on stderr: a bar with
the time left, and one line per case as it ends.

Time: one diagnosis per case and truth (14 truths by default: 8 catalog
effects, 2 variants, none, 3 out-of-catalog), 2-50 s each on 2 quiet cores
(2 s when the nominal model explains the data). ``--cases 3`` (42
diagnoses) took 85 min on 2 cores shared with other work (load average 7-9,
median 2 min per diagnosis); ``--quick`` halves the optimiser's budget.
Every case's hidden draws depend only on the seed, the truth and the case
number, so a subset of truths (``--effects``) reproduces their cases.

    python tools/check_withheld_effects.py --cases 4 --seed 1 -o out/check
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
import zlib

import numpy as np
from scipy import signal

from tqdm import tqdm  # noqa: E402

from slipest.diagnosis.cycles import cut_cycles  # noqa: E402
from slipest.diagnosis.fit import FitBudget, Geometry  # noqa: E402
from slipest.diagnosis.run import diagnose  # noqa: E402
from slipest.diagnosis.synth import da_change, simulate_run  # noqa: E402
from slipest.model.effects import EFFECTS, ORDER  # noqa: E402
from slipest.model.params import StickSlipParams  # noqa: E402
from slipest.model.scenario import Scenario  # noqa: E402
from slipest.plotting import pyplot  # noqa: E402  (matplotlib: pip install 'slipest[plot]')

plt = pyplot()

LEVELS = np.round(np.linspace(0.05, 0.5, 10), 3)
#: Leg speed range [rad/s] of logs whose speed changes per slip level (truths in VARYING_SPEED).
SPEED_RANGE = (0.4, 1.1)
VARYING_SPEED = ("time_skew",)
#: Largest mean |dDa/Da| of a drawn variant (see the module docstring).
VARIANT_MAX_CHANGE = 0.6
CYCLES_PER_LEVEL = 5
NOISE_G = 0.01
RATE = 1000.0


# --- out-of-catalog effects (sensor-chain stages, see slipest.model.sensor) ----------------------


class HubRocking:
    """Rocking transient after every midstance (continuous stage)."""

    domain = "continuous"

    def __init__(self, amplitude, tau, freq, n_legs=4):
        self.amplitude, self.tau, self.freq, self.n_legs = amplitude, tau, freq, n_legs

    def apply(self, t, az, theta, rng):
        step = 2 * math.pi / self.n_legs
        k = np.floor(theta / step).astype(np.int64)
        out = az.copy()
        for j in np.flatnonzero(np.diff(k) != 0):
            tm = t[j + 1]
            s = t - tm
            on = s >= 0
            out[on] += self.amplitude * np.exp(-s[on] / self.tau) * np.sin(2 * math.pi * self.freq * s[on])
        return out, theta


class BracketResonance:
    """Base-excitation transmissibility of a lightly damped IMU bracket (continuous stage)."""

    domain = "continuous"

    def __init__(self, fn, zeta):
        self.fn, self.zeta = fn, zeta
        self._state = None

    def apply(self, t, az, theta, rng):
        fs = 1.0 / (t[1] - t[0])
        wn = 2 * math.pi * self.fn
        b, a = signal.bilinear([2 * self.zeta / wn, 1.0], [1 / wn**2, 2 * self.zeta / wn, 1.0], fs=fs)
        if self._state is None:
            self._state = signal.lfilter_zi(b, a) * az[0]
        out, self._state = signal.lfilter(b, a, az, zi=self._state)
        return out, theta


class EncoderQuantisation:
    """Theta rounded to the encoder's resolution (sampled stage)."""

    domain = "sampled"

    def __init__(self, counts):
        self.step = 2 * math.pi / counts

    def apply(self, t, az, theta, rng):
        return az, np.round(theta / self.step) * self.step


OUT_OF_CATALOG = ("hub_rocking", "bracket_resonance", "encoder_quantisation")


def draw_ooc(name, rng):
    u = rng.uniform
    if name == "hub_rocking":
        p = {"amplitude": float(u(3, 10) * rng.choice([-1, 1])), "tau": float(u(0.3, 0.6)), "freq": float(u(2, 4))}
        return p, [HubRocking(**p)]
    if name == "bracket_resonance":
        p = {"fn": float(u(10, 15)), "zeta": float(u(0.03, 0.08))}
        return p, [BracketResonance(**p)]
    if name == "encoder_quantisation":
        p = {"counts": int(rng.integers(128, 257))}
        return p, [EncoderQuantisation(**p)]
    raise ValueError(name)


#: Variants of catalog effects outside their catalog draws -> the catalog effect (the right answer).
VARIANTS = {"ripple_harmonic": "speed_ripple", "impact_shape": "touchdown_impact"}


def right_answer(truth):
    """The verdict that is right for a truth (a variant's catalog effect; None for out-of-catalog ones)."""
    if truth in VARIANTS:
        return VARIANTS[truth]
    return truth if truth in ORDER or truth == "none" else None


def draw_variant(name, rng):
    """A catalog effect spec outside its catalog draws (see the module docstring)."""
    u = rng.uniform
    if name == "ripple_harmonic":
        spec = draw_catalog("speed_ripple", rng)
        spec["harmonic"] = int(rng.integers(2, 5))
        return spec
    if name == "impact_shape":
        return {"name": "touchdown_impact", "amplitude": float(u(8, 20) * rng.choice([-1, 1])),
                "tau": float(math.exp(u(math.log(0.3), math.log(4.0)))),
                "freq": float(math.exp(u(math.log(4.0), math.log(30.0)))), "onset": float(u(-math.pi, math.pi))}
    raise ValueError(name)


def draw_catalog(name, rng):
    """A catalog effect spec drawn from the moderate ranges (a parameter whose range is one value takes it)."""
    spec = EFFECTS[name]
    out = {"name": name}
    for p in spec.params:
        lo, hi = p.moderate
        if lo == hi:
            v = int(lo) if p.integer else float(lo)
        elif p.integer:
            v = int(rng.integers(int(lo), int(hi) + 1))
        elif p.log_scale and lo > 0:
            v = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        else:
            v = float(rng.uniform(lo, hi))
        out[p.name] = v
    if name == "touchdown_impact":
        out["amplitude"] *= float(rng.choice([-1.0, 1.0]))
    return out


def draw_soil(rng):
    phis = rng.uniform(0.40, 0.70)
    return {
        "kS": float(rng.uniform(600, 1400)),
        "phiS": float(phis),
        "phiD": float(phis - rng.uniform(0.05, 0.30)),
        "kappa": float(rng.uniform(0.25, 0.40)),
    }


def make_case(truth, rng, min_change):
    """(scenario, soil, catalog effects, extra stages, effect params, Da change).

    Effect parameters are redrawn up to 10 times until the effect changes Da
    by ``min_change``; if none does on that soil (a Stribeck curve barely
    matters on some soils), soil and slip order are redrawn too.
    """
    for _soil_attempt in range(10):
        soil = draw_soil(rng)
        order = rng.permutation(LEVELS)
        slips = np.repeat(order, CYCLES_PER_LEVEL)
        base = StickSlipParams(**soil)
        imu = {"rate": RATE, "noise_g": NOISE_G, "seed": int(rng.integers(2**31))}
        if truth in VARYING_SPEED:
            speeds = np.repeat(rng.uniform(*SPEED_RANGE, len(LEVELS)), CYCLES_PER_LEVEL)
            sc = Scenario.per_cycle(base, imu=imu, slip=slips, omega=speeds)
        else:
            sc = Scenario.per_cycle(base, imu=imu, slip=slips)
        if truth == "none":
            return sc, soil, (), (), {}, 0.0
        for _attempt in range(10):
            if truth in OUT_OF_CATALOG:
                params, stages = draw_ooc(truth, rng)
                effects = ()
                change = da_change(sc, (), stages) if truth != "encoder_quantisation" else float("nan")
                _, stages = draw_ooc_fixed(truth, params)
            else:
                spec = draw_variant(truth, rng) if truth in VARIANTS else draw_catalog(truth, rng)
                effects, stages, params = (spec,), (), {k: v for k, v in spec.items() if k != "name"}
                change = da_change(sc, effects)
            if truth in VARIANTS and not change <= VARIANT_MAX_CHANGE:
                continue
            if truth == "encoder_quantisation" or change >= min_change:
                scenario = Scenario(cycles=sc.cycles, rate=sc.rate, noise_g=sc.noise_g, seed=sc.seed, effects=effects)
                return scenario, soil, effects, stages, params, change
    raise RuntimeError(f"could not draw {truth} parameters changing Da by {min_change:.0%}")


def draw_ooc_fixed(name, params):
    """Fresh stage objects (stages keep state) for given parameters."""
    if name == "hub_rocking":
        return params, [HubRocking(**params)]
    if name == "bracket_resonance":
        return params, [BracketResonance(**params)]
    return params, [EncoderQuantisation(**params)]


def run_case(truth, rng, min_change, budget, seed, fit_effects=None):
    sc, soil, effects, stages, params, change = make_case(truth, rng, min_change)
    run = simulate_run(sc, stages)
    geometry = Geometry()  # the known hardware: the model's defaults (MH, mF, lS, nL)
    cycles = cut_cycles(run["t"], run["az"], run["theta"], run["slip"], geometry.nL)
    t0 = time.perf_counter()
    d = diagnose(cycles, geometry, fit_effects, seed=seed, budget=budget)
    elapsed = time.perf_counter() - t0
    ranking = [
        {"effect": c.effect, "gap_heldout": c.gap_heldout, "shrink": c.shrink, "params": c.params} for c in d.ranking
    ]
    right = next((c for c in d.ranking if c.effect == right_answer(truth)), None)
    return {
        "truth": truth,
        "right": right_answer(truth),
        "soil": soil,
        "params": params,
        "da_change": change,
        "verdict": d.verdict,
        "ranked_first": d.ranking[0].effect if d.ranking else None,
        "gap_nominal": d.gap_nominal,
        "gap_after": d.gap_after,
        "shrink_best": d.shrink,
        "shrink_right": right.shrink if right else None,
        "gap_right": right.gap_heldout if right else None,
        "noise_bin_g": d.noise.bin_g,
        "ranking": ranking,
        "elapsed_s": elapsed,
    }


def confusion_png(path, rows, cols, matrix, title):
    fig, ax = plt.subplots(figsize=(1.0 + 0.75 * len(cols), 1.0 + 0.5 * len(rows)))
    ax.imshow(matrix / np.maximum(matrix.sum(axis=1, keepdims=True), 1), cmap="Blues", vmin=0, vmax=1)
    for i in range(len(rows)):
        for j in range(len(cols)):
            if matrix[i, j]:
                ax.text(j, i, str(int(matrix[i, j])), ha="center", va="center", fontsize=9)
    ax.set_xticks(range(len(cols)), cols, rotation=40, ha="right", fontsize=8)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.set_xlabel("verdict")
    ax.set_ylabel("true effect (hidden)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def case_rng(seed, truth, k):
    """The hidden draws of case ``k`` of ``truth``: the same whichever other truths run."""
    return np.random.default_rng([seed, k, zlib.crc32(truth.encode())])


def _pct(x):
    return f"{x * 100:.0f}%" if x is not None and math.isfinite(x) else "-"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=4, help="logs per effect (default 4)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the hidden draws (default 1)")
    ap.add_argument("--effects", default=",".join(ORDER + tuple(VARIANTS) + ("none",) + OUT_OF_CATALOG),
                    help="comma-separated truths to test (catalog names, variants, none, out-of-catalog names)")
    ap.add_argument("--fit-effects", default=None,
                    help="comma-separated catalog effects the diagnosis fits (default: all)")
    ap.add_argument("--min-change", type=float, default=0.10, help="smallest mean |dDa/Da| of a drawn effect")
    ap.add_argument("--quick", action="store_true", help="half the diagnosis's optimiser budget")
    ap.add_argument("-o", "--out", default="out/check_withheld", help="output directory (PNG, JSON)")
    ap.add_argument("--json", action="store_true", help="also write every case to OUT/cases.json")
    args = ap.parse_args(argv)
    truths = [t.strip() for t in args.effects.split(",") if t.strip()]
    for t in truths:
        if t not in ORDER and t != "none" and t not in OUT_OF_CATALOG and t not in VARIANTS:
            ap.error(f"unknown truth {t!r}")
    fit_effects = None
    if args.fit_effects:
        fit_effects = [e.strip() for e in args.fit_effects.split(",") if e.strip()]
        bad = [e for e in fit_effects if e not in ORDER]
        if bad:
            ap.error(f"unknown catalog effect(s) {bad}; known: {', '.join(ORDER)}")
    os.makedirs(args.out, exist_ok=True)
    budget = FitBudget().scaled(0.5) if args.quick else FitBudget()
    jobs = [(t, k) for k in range(args.cases) for t in truths]
    results = []
    bar = tqdm(jobs, desc="cases", unit="log", file=sys.stderr)
    for truth, k in bar:
        bar.set_postfix_str(truth)
        r = run_case(truth, case_rng(args.seed, truth, k), args.min_change, budget, seed=k, fit_effects=fit_effects)
        results.append(r)
        tqdm.write(
            f"{truth:21s} case {k}: verdict {r['verdict']:17s} first {str(r['ranked_first']):17s} "
            f"gap {r['gap_nominal'] * 1000:6.1f} -> {r['gap_after'] * 1000:6.1f} mg  "
            f"right-effect shrink {_pct(r['shrink_right']):>5s}  "
            f"dDa {r['da_change'] * 100:5.1f}%  {r['elapsed_s']:.0f} s",
            file=sys.stderr,
        )
    bar.close()
    report(results, truths, args)
    return 0


def report(results, truths, args):
    """Print the confusion matrix and the figures; write the PNG (and the JSON)."""
    cols = list(ORDER) + ["none", "unexplained"]
    rows = list(truths)
    matrix = np.zeros((len(rows), len(cols)), dtype=int)
    for r in results:
        matrix[rows.index(r["truth"]), cols.index(r["verdict"])] += 1
    print("confusion matrix (rows: hidden truth, columns: verdict)")
    short = [c[:11] for c in cols]
    print(" " * 22 + " ".join(f"{c:>11s}" for c in short))
    for i, t in enumerate(rows):
        print(f"{t:22s}" + " ".join(f"{matrix[i, j]:11d}" for j in range(len(cols))))
    print()

    def block(label, names):
        n_all, n_first, n_named, good = 0, 0, 0, 0
        shr_all = []
        for t in names:
            rs = [r for r in results if r["truth"] == t]
            first = sum(r["ranked_first"] == r["right"] for r in rs)
            named = sum(r["verdict"] == r["right"] for r in rs)
            shr = [r["shrink_right"] for r in rs if r["shrink_right"] is not None]
            shr_all += shr
            n_all, n_first, n_named = n_all + len(rs), n_first + first, n_named + named
            good += int(first > len(rs) / 2)
            print(f"{t:17s} right ({rs[0]['right']}) ranked first {first}/{len(rs)}  named {named}/{len(rs)}  "
                  f"right-effect shrink median {_pct(np.median(shr) if shr else None)} "
                  f"(min {_pct(min(shr) if shr else None)})  dDa {np.mean([r['da_change'] for r in rs]) * 100:.0f}%"
                  f"  shrinks " + " ".join(_pct(r["shrink_right"]) for r in rs))
        if n_all:
            print(f"{label}: right effect ranked first in {n_first}/{n_all} = {n_first / n_all:.0%}, named in "
                  f"{n_named}/{n_all} = {n_named / n_all:.0%}; right first in most of their cases: "
                  f"{good}/{len(names)}; right-effect held-out shrink median {_pct(np.median(shr_all) if shr_all else None)}, "
                  f"share >= 70%: {_pct(np.mean(np.array(shr_all) >= 0.7) if shr_all else None)}")
        print()

    block("catalog effects", [t for t in rows if t in ORDER])
    block("variants outside the catalog draws", [t for t in rows if t in VARIANTS])
    clean = [r for r in results if r["truth"] == "none"]
    if clean:
        n_none = sum(r["verdict"] == "none" for r in clean)
        print(f"clean data answered 'none': {n_none}/{len(clean)} = {n_none / len(clean):.0%}")
    ooc = [r for r in results if r["truth"] in OUT_OF_CATALOG]
    if ooc:
        mis = sum(r["verdict"] in ORDER for r in ooc)
        unexp = sum(r["verdict"] == "unexplained" for r in ooc)
        print(f"out-of-catalog: misnamed {mis}/{len(ooc)}, 'unexplained' {unexp}/{len(ooc)}, "
              f"'none' {len(ooc) - mis - unexp}/{len(ooc)}")
        for t in OUT_OF_CATALOG:
            rs = [r for r in ooc if r["truth"] == t]
            if rs:
                print(f"  {t:21s} " + ", ".join(r["verdict"] for r in rs))
    times = [r["elapsed_s"] for r in results]
    print(f"diagnosis time per log: median {np.median(times):.0f} s, mean {np.mean(times):.0f} s, "
          f"max {max(times):.0f} s (50 cycles)")
    png = os.path.join(args.out, "confusion.png")
    confusion_png(png, rows, cols, matrix, f"blind diagnosis, {args.cases} logs per truth, seed {args.seed}")
    print(f"wrote {png}")
    if args.json:
        path = os.path.join(args.out, "cases.json")
        with open(path, "w") as fh:
            json.dump({"seed": args.seed, "fit_effects": args.fit_effects, "cases": results}, fh, indent=1,
                      default=float)
        print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
