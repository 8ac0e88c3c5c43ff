#!/usr/bin/env python3
"""Accuracy benchmark: slip and dphi errors of the estimators on simulated runs where the soil changes.

Each run drives ``--soils`` soils one after the other, ``--cycles-per-soil``
leg cycles each; the soils are drawn uniformly over the spec's ranges
(kS 500-1500 N/m, phiD 0.1-0.4 rad, dphi 0-0.35 rad) and redrawn when
within 2 % of the range of a calibration-grid point in every coordinate
(so none is on the calibration grid); slip is piecewise constant, redrawn
uniformly in 0-0.5 every 2-5 cycles; the IMU stream (``Scenario`` +
``iter_stream``) has 0.01 g noise at 1 kHz. Compared, per cycle:

* ``default``: :class:`slipest.online.SlipEstimator` end to end (segmenter,
  features, recursive soil filter), **soil unknown**, never told of changes;
* ``default-known``: the same inverse with the true soil given (one cycle at a time);
* ``eq515-known``: thesis Eq. 5.15 with the true ``kS`` and ``dphi``.

Reported: slip RMSE, dphi RMSE and the share of truths inside the 95 %
intervals (``+-1.96 std``), over the cycles that come after the filter
has seen at least N cycles of the current soil (N = 1, 5, 10, 20; "N = 10"
is the target's "from the 10th cycle after the soil last changed"), and at
exactly N. Never tune anything on this benchmark's seed (default 2024):
development used other seeds.

    python tools/bench_accuracy.py                 # 12 runs x 4 soils x 25 cycles, ~15 s
    python tools/bench_accuracy.py --runs 2 --seed 7
    python tools/bench_accuracy.py --seed 11 --grid 15,13,11   # a development seed, another soil grid
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
from tqdm import tqdm

from slipest.features import INDEX, cycle_features
from slipest.inverse.eq515 import Eq515Inverse
from slipest.inverse.simdata import RANGES
from slipest.inverse.surrogate import SoilGrid, SurrogateInverse, load_inverse_model
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import iter_stream
from slipest.online import SlipEstimator
from slipest.segmentation import CycleSegmenter

CAL_GRID = {"kS": [500, 750, 1000, 1250, 1500], "phiD": [0.1, 0.2, 0.3, 0.4], "dphi": [0.0, 0.0875, 0.175, 0.2625, 0.35]}
NS = (1, 5, 10, 20)


def near_cal_grid(kS, phiD, dphi, tol=0.02) -> bool:
    """True when every coordinate is within ``tol`` of its range from a calibration-grid level."""
    out = True
    for name, v in (("kS", kS), ("phiD", phiD), ("dphi", dphi)):
        lo, hi = RANGES[name]
        out &= min(abs(v - g) for g in CAL_GRID[name]) <= tol * (hi - lo)
    return bool(out)


def draw_run(rng, n_soils, per_soil):
    soils = []
    while len(soils) < n_soils:
        kS = rng.uniform(*RANGES["kS"])
        phiD = rng.uniform(*RANGES["phiD"])
        dphi = rng.uniform(*RANGES["dphi"])
        if not near_cal_grid(kS, phiD, dphi):
            soils.append((kS, phiD + dphi, phiD))
    n = n_soils * per_soil
    slip = np.empty(n)
    j = 0
    while j < n:
        k = int(rng.integers(2, 6))
        slip[j : j + k] = rng.uniform(*RANGES["slip"])
        j += k
    soil = np.repeat(np.array(soils), per_soil, axis=0)
    since = np.tile(np.arange(1, per_soil + 1), n_soils)
    return slip, soil, since


def run_one(seed, n_soils, per_soil, noise, rate, eq, surro, est_opts=None, model=None):
    rng = np.random.default_rng(seed)
    slip, soil, since = draw_run(rng, n_soils, per_soil)
    sc = Scenario.per_cycle(StickSlipParams(), dict(noise_g=noise, rate=rate, seed=int(rng.integers(2**31))),
                            slip=slip, kS=soil[:, 0], phiS=soil[:, 1], phiD=soil[:, 2])
    n = slip.size
    rows = {k: np.full(n, np.nan) for k in ("slip_d", "sd_d", "dphi_d", "dsd_d", "slip_k", "sd_k", "slip_e", "sd_e")}
    est = SlipEstimator(n_legs=sc.n_legs, estimator=est_opts, model=model)
    seg = CycleSegmenter(sc.n_legs)
    for chunk in iter_stream(sc):
        for e in est.push_many(chunk.t, chunk.az, chunk.theta):
            if e.ok and e.cycle < n:
                rows["slip_d"][e.cycle], rows["sd_d"][e.cycle] = e.slip, e.slip_std
                rows["dphi_d"][e.cycle], rows["dsd_d"][e.cycle] = e.dphi, e.dphi_std
        for cyc in seg.push_many(chunk.t, chunk.az, chunk.theta):
            k = cyc.k
            if not cyc.ok or k >= n:
                continue
            f = cycle_features(cyc.theta_phase, cyc.az, cyc.t, n_legs=sc.n_legs)
            kS, phiS, phiD = soil[k]
            rows["slip_k"][k], rows["sd_k"][k] = surro.slip_known_soil(f, kS, phiS, phiD)
            rows["slip_e"][k] = float(eq.slip_from_da(f[INDEX["delta_a"]], phiS - phiD, kS))
            rows["sd_e"][k] = eq.slip_std
    rows.update(slip=slip, dphi=soil[:, 1] - soil[:, 2], since=since)
    return rows


def summarise(all_rows):
    cat = {k: np.concatenate([r[k] for r in all_rows]) for k in all_rows[0]}
    out = {}
    for label, key, sd, truth in (
        ("default (soil unknown) slip", "slip_d", "sd_d", "slip"),
        ("default (soil unknown) dphi", "dphi_d", "dsd_d", "dphi"),
        ("default-known (soil known) slip", "slip_k", "sd_k", "slip"),
        ("eq515-known (soil known) slip", "slip_e", "sd_e", "slip"),
    ):
        res = {}
        for mode in ("from", "at"):
            for n in NS:
                sel = (cat["since"] >= n) if mode == "from" else (cat["since"] == n)
                sel &= np.isfinite(cat[key])
                e = cat[key][sel] - cat[truth][sel]
                if e.size == 0:
                    continue
                res[f"{mode}_{n}"] = {
                    "n": int(e.size),
                    "rmse": float(np.sqrt(np.mean(e**2))),
                    "bias": float(np.mean(e)),
                    "coverage95": float(np.mean(np.abs(e) <= 1.96 * cat[sd][sel])),
                }
        res["not_estimated"] = int(np.sum(~np.isfinite(cat[key])))
        out[label] = res
    return out


def grid_levels(text: str) -> tuple[int, int, int]:
    """``--grid K,P,D``: three level counts, each at least 2."""
    try:
        levels = tuple(int(x) for x in text.split(","))
    except ValueError:
        levels = ()
    if len(levels) != 3 or min(levels) < 2:
        raise argparse.ArgumentTypeError(f"expected three level counts >= 2 like 11,10,31, got {text!r}")
    return levels


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=12)
    ap.add_argument("--soils", type=int, default=4, help="soils per run (the soil changes between them)")
    ap.add_argument("--cycles-per-soil", type=int, default=25)
    ap.add_argument("--noise", type=float, default=0.01, help="IMU noise [g]")
    ap.add_argument("--rate", type=float, default=1000.0, help="IMU rate [Hz]")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--json", help="also write the figures to this JSON file")
    ap.add_argument("--model", help="inverse model JSON (default: the shipped slipest/data/inverse_model.json)")
    ap.add_argument("--hazard", type=float, help="estimator option (default: the estimator's)")
    ap.add_argument("--soil-temper", type=float, help="estimator option (default: the estimator's)")
    ap.add_argument("--slip-temper", type=float, help="estimator option (default: the estimator's)")
    ap.add_argument("--forget", type=float, help="estimator option (default: the estimator's)")
    ap.add_argument("--n-dims", type=int, help="estimator option (default: the estimator's)")
    ap.add_argument("--grid", metavar="K,P,D", type=grid_levels,
                    help="soil grid: numbers of kS, phiD and dphi levels over the spec's ranges, each >= 2 "
                    "(default: SoilGrid.default(), 11,10,31)")
    args = ap.parse_args(argv)
    eq = Eq515Inverse.from_calibration()
    model = load_inverse_model(args.model) if args.model else None
    surro = SurrogateInverse(model)
    t0 = time.time()
    opts = {k: v for k, v in (("hazard", args.hazard), ("soil_temper", args.soil_temper),
                              ("slip_temper", args.slip_temper), ("forget", args.forget), ("n_dims", args.n_dims))
            if v is not None}
    if args.grid:
        k, p, d = args.grid
        opts["grid"] = SoilGrid(np.linspace(*RANGES["kS"], k), np.linspace(*RANGES["phiD"], p), np.linspace(*RANGES["dphi"], d))
    rows = [run_one(args.seed * 1000 + r, args.soils, args.cycles_per_soil, args.noise, args.rate, eq, surro, opts, model)
            for r in tqdm(range(args.runs), desc="runs", file=sys.stderr)]
    out = summarise(rows)
    print(f"{args.runs} runs x {args.soils} soils x {args.cycles_per_soil} cycles, noise {args.noise} g at "
          f"{args.rate:g} Hz, seed {args.seed}, {time.time() - t0:.0f} s")
    print(f"{'':34s} {'N':>3s} {'cycles':>6s} {'RMSE':>7s} {'bias':>7s} {'cov95':>6s}   (from the N-th cycle on a soil)")
    for label, res in out.items():
        for n in NS:
            r = res.get(f"from_{n}")
            if r:
                print(f"{label:34s} {n:3d} {r['n']:6d} {r['rmse']:7.4f} {r['bias']:+7.4f} {r['coverage95']:6.3f}")
    print("at exactly the N-th cycle on a soil:")
    for label, res in out.items():
        print(f"  {label:32s} " + "  ".join(
            f"N={n}: {res[f'at_{n}']['rmse']:.4f} ({res[f'at_{n}']['coverage95']:.2f})" for n in NS if f"at_{n}" in res))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"args": vars(args), "results": out}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
