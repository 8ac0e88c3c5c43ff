#!/usr/bin/env python3
"""Accuracy benchmark: slip and dphi errors of the estimator across the rover's operating envelope.

Each run drives ``--soils`` soils one after the other, ``--cycles-per-soil``
leg cycles each, through the whole chain a rover uses (``Scenario`` ->
``iter_stream`` -> :class:`slipest.online.SlipEstimator`: segmenter, noise
estimate, features, recursive soil filter), **soil unknown**, never told of
changes. Draws (all uniform):

* soils over the whole promised domain: kS 500-1500 N/m, phiD 0.10-0.80 rad
  and dphi 0-0.35 rad with phiS = phiD + dphi <= 0.80 rad;
* slip redrawn in 0-0.5 every 2-5 cycles;
* leg speed 0.35-1.1 rad/s: one per run (``steady`` runs) or redrawn every
  3-6 cycles (``changing`` runs, every other run);
* the IMU of each run: one of the ``--conditions`` (rate [Hz] : noise [g]),
  every condition getting the same runs.

Reported per condition, and per leg-speed band, soil stiffness band and soil
range (``old range``: phiD <= 0.4 rad, what the single-speed model
covered): slip RMSE,
bias and the share of truths inside the 95 % intervals (``+-1.96 std``),
dphi RMSE and coverage, over the cycles from the ``--from-cycle``-th (10th)
after the soil last changed; and the share of all cycles that were
estimated (with why the others were not). Also, per condition, the same
inverse with the true soil given (one cycle at a time). Never tune anything
on this benchmark's official seed (2024): development used seeds 11 and 7.

    python tools/bench_accuracy.py                    # 12 runs x 3 conditions x 4 soils x 25 cycles, ~4 min
    python tools/bench_accuracy.py --runs 4 --seed 11 --conditions 1000:0.01
    python tools/bench_accuracy.py --conditions 200:0.01,2000:0.01,500:0.02 --json out.json
    python tools/bench_accuracy.py --runs 4 --seed 7 --conditions 1000:0.01 --grid-refine 2   # 8x the cells
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
from tqdm import tqdm

from slipest.inverse.feature_inverse import FeatureInverse
from slipest.inverse.grid import SoilGrid
from slipest.inverse.surrogate import InverseModelError, load_inverse_model
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import iter_stream, simulate_stream
from slipest.online import ESTIMATED, SlipEstimator

DOMAIN = {"kS": (500.0, 1500.0), "phiD": (0.10, 0.80), "dphi": (0.0, 0.35), "phiS_max": 0.80, "slip": (0.0, 0.5),
          "omega": (0.35, 1.1)}
SPEED_BANDS = ((0.35, 0.55), (0.55, 0.8), (0.8, 1.1))
#: Soil stiffness bands [N/m] (soft soils are where soil and slip are hardest to tell apart: docs/estimator.md).
KS_BANDS = ((500.0, 800.0), (800.0, 1100.0), (1100.0, 1500.0))
OLD_PHID_MAX = 0.4


def draw_soil(rng) -> tuple[float, float, float]:
    """kS [N/m], phiS, phiD [rad] uniform over the domain."""
    while True:
        phiD = rng.uniform(*DOMAIN["phiD"])
        dphi = rng.uniform(*DOMAIN["dphi"])
        if phiD + dphi <= DOMAIN["phiS_max"]:
            return rng.uniform(*DOMAIN["kS"]), phiD + dphi, phiD


def piecewise(rng, n: int, lo_len: int, hi_len: int, draw) -> np.ndarray:
    out = np.empty(n)
    j = 0
    while j < n:
        k = int(rng.integers(lo_len, hi_len + 1))
        out[j : j + k] = draw()
        j += k
    return out


def draw_run(rng, n_soils: int, per_soil: int, changing: bool) -> dict:
    soils = np.repeat(np.array([draw_soil(rng) for _ in range(n_soils)]), per_soil, axis=0)
    n = n_soils * per_soil
    slip = piecewise(rng, n, 2, 5, lambda: rng.uniform(*DOMAIN["slip"]))
    if changing:
        omega = piecewise(rng, n, 3, 6, lambda: rng.uniform(*DOMAIN["omega"]))
    else:
        omega = np.full(n, rng.uniform(*DOMAIN["omega"]))
    since = np.tile(np.arange(1, per_soil + 1), n_soils)
    return {"slip": slip, "kS": soils[:, 0], "phiS": soils[:, 1], "phiD": soils[:, 2], "omega": omega, "since": since,
            "seed": int(rng.integers(2**31))}


def scenario(run: dict, rate: float, noise: float) -> Scenario:
    """The simulator scenario of a drawn run (:func:`draw_run`) with an IMU at ``rate`` [Hz] and ``noise`` [g]."""
    return Scenario.per_cycle(StickSlipParams(), dict(noise_g=noise, rate=rate, seed=run["seed"]),
                              **{k: run[k] for k in ("slip", "kS", "phiS", "phiD", "omega")})


def run_one(run: dict, rate: float, noise: float, inverse: FeatureInverse, model, inject=None,
            estimator: dict | None = None) -> dict:
    """Estimates of one run (soil unknown) and the same cycles' soil-known inversions; ``inject(t, az, theta,
    cycle)``, when given, returns the stream with faults in it (``tools/bench_faults.py``); ``estimator``:
    options of the soil and slip estimator (``SlipEstimator(estimator=...)``), default its own."""
    n = run["slip"].size
    sc = scenario(run, rate, noise)
    rows = {k: np.full(n, np.nan) for k in ("slip", "slip_std", "dphi", "dphi_std", "slip_known", "slip_known_std")}
    quality = np.full(n, "missing", dtype=object)
    repaired = np.zeros(n, int)

    def on_estimate(e):
        k = e.cycle
        if not 0 <= k < n:
            return
        quality[k] = e.quality
        repaired[k] = e.n_repaired
        if e.ok:
            rows["slip"][k], rows["slip_std"][k] = e.slip, e.slip_std
            rows["dphi"][k], rows["dphi_std"][k] = e.dphi, e.dphi_std
            # the same cycle's features (the callback runs as each estimate is made)
            rows["slip_known"][k], rows["slip_known_std"][k] = inverse.slip_known_soil(
                est.last_features, run["kS"][k], run["phiS"][k], run["phiD"][k])

    est = SlipEstimator(n_legs=sc.n_legs, model=model, on_estimate=on_estimate, estimator=estimator)
    if inject is None:
        chunks = ((c.t, c.az, c.theta) for c in iter_stream(sc))
    else:
        s = simulate_stream(sc)
        chunks = [inject(s.t, s.az, s.theta, s.cycle)]
    for _ in est.iter_estimates(chunks):
        pass
    rows.update(quality=quality, true_slip=run["slip"], true_dphi=run["phiS"] - run["phiD"], omega=run["omega"],
                kS=run["kS"], phiD=run["phiD"], since=run["since"], noise=est.noise_estimate, repaired=repaired)
    return rows


def figures(rows: list[dict], sel_fn, from_cycle: int) -> dict:
    if not rows:  # (a group with no run: --runs 1 has no changing-speed run)
        return {"cycles": 0}
    cat = {k: np.concatenate([np.atleast_1d(r[k]) for r in rows]) for k in rows[0] if k != "noise"}
    sel_all = sel_fn(cat)
    out = {"cycles": int(sel_all.sum())}
    if not out["cycles"]:
        return out
    q = cat["quality"][sel_all]
    est = np.isin(q, ESTIMATED)
    out["estimated"] = float(np.mean(est))
    out["not_estimated"] = {str(k): int(v) for k, v in zip(*np.unique(q[~est], return_counts=True))}
    sel = sel_all & (cat["since"] >= from_cycle) & np.isin(cat["quality"], ESTIMATED)
    out["scored"] = int(sel.sum())
    for name, est, std, truth in (("slip", "slip", "slip_std", "true_slip"), ("dphi", "dphi", "dphi_std", "true_dphi"),
                                  ("slip_soil_known", "slip_known", "slip_known_std", "true_slip")):
        e = cat[est][sel] - cat[truth][sel]
        ok = np.isfinite(e)
        if ok.sum():
            out[name] = {"rmse": float(np.sqrt(np.mean(e[ok] ** 2))), "bias": float(np.mean(e[ok])),
                         "coverage95": float(np.mean(np.abs(e[ok]) <= 1.96 * cat[std][sel][ok]))}
    return out


def print_table(title: str, groups: dict) -> None:
    print(title)
    print(f"  {'group':26s} {'cycles':>6s} {'estim.':>6s} | {'slip RMSE':>9s} {'bias':>7s} {'cov95':>5s} | "
          f"{'dphi RMSE':>9s} {'cov95':>5s} | {'soil known':>10s}")
    for name, f in groups.items():
        if not f.get("cycles"):
            continue
        s, d, k = f.get("slip", {}), f.get("dphi", {}), f.get("slip_soil_known", {})
        why = ", ".join(f"{q} {c}" for q, c in f["not_estimated"].items())
        print(f"  {name:26s} {f['cycles']:6d} {f['estimated']:6.3f} | {s.get('rmse', math.nan):9.4f} "
              f"{s.get('bias', math.nan):+7.4f} {s.get('coverage95', math.nan):5.3f} | {d.get('rmse', math.nan):9.4f} "
              f"{d.get('coverage95', math.nan):5.3f} | {k.get('rmse', math.nan):10.4f}" + (f"   ({why})" if why else ""))


def conditions(text: str) -> list[tuple[float, float]]:
    """``RATE:NOISE,...``: IMU rates [Hz] and noise standard deviations [g]."""
    out = []
    for item in text.split(","):
        try:
            rate, noise = (float(v) for v in item.split(":"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected RATE:NOISE like 1000:0.01, got {item!r}") from None
        if not (rate > 0 and noise >= 0):
            raise argparse.ArgumentTypeError(f"rate must be > 0 Hz and noise >= 0 g, got {item!r}")
        out.append((rate, noise))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=12, help="runs per condition (half steady, half changing speed)")
    ap.add_argument("--soils", type=int, default=4, help="soils per run (the soil changes between them)")
    ap.add_argument("--cycles-per-soil", type=int, default=25)
    ap.add_argument("--conditions", type=conditions, default=conditions("1000:0.01,250:0.01,1000:0.025"),
                    help="IMU rate [Hz] : noise [g] of the runs, comma-separated (default 1000:0.01,250:0.01,1000:0.025)")
    ap.add_argument("--from-cycle", type=int, default=10, help="score from this cycle after a soil change (default 10)")
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--model", help="inverse model file (default: the shipped one)")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    ap.add_argument("--estimator", type=json.loads, default={},
                    help="research: options of the soil and slip estimator as JSON (e.g. '{\"soil_temper\": 0.1}')")
    ap.add_argument("--grid-refine", type=int, default=1, metavar="N",
                    help="research: the estimator's soil grid with every spacing divided by N (N**3 times the cells "
                         "and the work per cycle; default 1, the shipped grid)")
    args = ap.parse_args(argv)
    if args.grid_refine < 1:
        ap.error(f"--grid-refine must be >= 1, got {args.grid_refine}")
    estimator = dict(args.estimator)
    if args.grid_refine > 1:
        estimator["grid"] = SoilGrid.default().refined(args.grid_refine)
    try:
        model = load_inverse_model(args.model)
    except InverseModelError as exc:
        ap.error(str(exc))
    try:
        SlipEstimator(model=model, estimator=estimator or None)  # options checked before the runs
    except ValueError as exc:
        ap.error(f"--estimator: {exc}")
    inverse = FeatureInverse(model)
    t0 = time.time()
    rng = np.random.default_rng(args.seed)
    runs = [draw_run(rng, args.soils, args.cycles_per_soil, changing=bool(r % 2)) for r in range(args.runs)]
    results = {}
    with tqdm(total=len(runs) * len(args.conditions), desc="runs", file=sys.stderr) as bar:
        for rate, noise in args.conditions:
            rows = []
            for run in runs:
                rows.append(run_one(run, rate, noise, inverse, model, estimator=estimator or None))
                bar.update(1)
            name = f"{rate:g} Hz, {noise:g} g"
            groups = {"all": figures(rows, lambda c: np.ones(c["since"].size, bool), args.from_cycle)}
            for lo, hi in SPEED_BANDS:
                groups[f"speed {lo:g}-{hi:g} rad/s"] = figures(
                    rows, lambda c, lo=lo, hi=hi: (c["omega"] >= lo) & (c["omega"] < hi), args.from_cycle)
            for lo, hi in KS_BANDS:
                groups[f"kS {lo:g}-{hi:g} N/m"] = figures(
                    rows, lambda c, lo=lo, hi=hi: (c["kS"] >= lo) & (c["kS"] < hi), args.from_cycle)
            groups["steady-speed runs"] = figures(rows[0::2], lambda c: np.ones(c["since"].size, bool), args.from_cycle)
            groups["changing-speed runs"] = figures(rows[1::2], lambda c: np.ones(c["since"].size, bool), args.from_cycle)
            groups[f"soils phiD <= {OLD_PHID_MAX} (old range)"] = figures(
                rows, lambda c: c["phiD"] <= OLD_PHID_MAX, args.from_cycle)
            groups[f"soils phiD > {OLD_PHID_MAX}"] = figures(rows, lambda c: c["phiD"] > OLD_PHID_MAX, args.from_cycle)
            noise_est = [r["noise"] for r in rows]
            results[name] = {"groups": groups, "noise_estimated_g": [float(np.nanmin(noise_est)),
                                                                     float(np.nanmax(noise_est))]}
    grid = "" if args.grid_refine == 1 else f", soil grid refined {args.grid_refine}x ({estimator['grid'].size} cells)"
    grid += f", estimator options {args.estimator}" if args.estimator else ""
    print(f"{args.runs} runs x {args.soils} soils x {args.cycles_per_soil} cycles per condition, seed {args.seed}, "
          f"scored from the {args.from_cycle}th cycle on a soil{grid}; {time.time() - t0:.0f} s")
    for name, res in results.items():
        lo, hi = res["noise_estimated_g"]
        print_table(f"\n{name} (noise estimated from the data: {lo:.4f}-{hi:.4f} g)", res["groups"])
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"args": {k: v for k, v in vars(args).items()}, "results": results}, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
