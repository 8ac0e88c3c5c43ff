#!/usr/bin/env python3
"""Research: would other per-cycle features identify slip better when the soil is unknown?

Per-cycle features scatter around any smooth law of (slip, soil) by a few
percent, and that scatter is deterministic (it is there at zero IMU noise):
crossing counts, energy quantiles and the break-away bin move in steps as
the parameters change (docs/estimator.md, "What limits the likelihood").
This study compares feature sets on the same simulated stances, at one leg
speed, IMU rate and noise, with a stripped-down version of the estimator's
inference, so that a candidate feature can be judged before it is put into
:mod:`slipest.features` and the model retrained:

1. ``--train`` stances drawn over the training envelope
   (:func:`slipest.inverse.simdata.draw_envelope`, the leg speed fixed) give
   each set's mean: one Legendre polynomial per feature of total degree
   ``--degree`` in (slip, kS, phiS, dphi); ``--test`` other stances give the
   covariance of its residuals (and each feature's R^2, printed);
2. ``--soils`` soils drawn over the estimator's soil domain (kS 500-1500 N/m,
   phiS 0.3-0.8 rad, dphi 0-0.35 rad, phiD >= 0.1 rad), each driven at
   ``--slips`` slips uniform over 0-0.5, are estimated as one run per soil:
   Gaussian likelihood on a soil grid (11 x 11 x 9 levels) x slip nodes
   (0-0.54 by 0.02), tempered by 0.4 as the estimator's; the soil posterior
   multiplies every cycle's slip-marginal likelihood raised to ``t``
   (0.15, the estimator's soil temper, 0.4 and 1); each cycle's slip is its
   posterior mean. Printed: slip RMSE per ``t`` and with the soil known.

It is a proxy, not the estimator: one speed, no noise variation, every
cycle of a soil seen at once (no filter, no soil change). Its figures
rank feature sets; only a retrained model scored by ``tools/bench_accuracy.py``
says what a change gives.

The sets: the 14 features the model had before the moments; those with the crossing counts (``zc_rate``,
``osc_freq``) replaced by the spectral moments (``spec_cent``, ``spec_bw``); with the energy quantiles
replaced by the energy moments (``e_cent``, ``e_spread``); the 14 and those four moments (the model shipped
before); and the shipped model's 20: those 18 with the spectrum's skew ``spec_skew`` and the second half's
centroid ``spec_cent2``. A new candidate is added to :mod:`slipest.features` first
(:func:`slipest.inverse.simdata.simulate_features` with ``grids=True`` gives the smoothed signal to prototype
it on), then to a set here.

    python tools/feature_study.py                      # 1 kHz, 0.01 g, 0.63 rad/s, seed 0: about 2 min
    python tools/feature_study.py --omega 0.4 --rate 250 --noise 0.025
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slipest.features import FEATURE_NAMES  # noqa: E402
from slipest.inverse.simdata import draw_envelope, simulate_features  # noqa: E402
from slipest.inverse.surrogate import MODEL_FEATURES, MOMENT_FEATURES, legendre_design, node_terms  # noqa: E402

#: Normalisation of (slip, kS, phiS, dphi): the training envelope's centre and half-width.
CENTER = np.array([0.275, 1050.0, 0.5, 0.2])
HALFWIDTH = np.array([0.275, 650.0, 0.4, 0.2])
#: The estimator's likelihood temper and the soil tempers compared.
SLIP_TEMPER = 0.4
SOIL_TEMPERS = (0.15, 0.4, 1.0)
STEPPED_FREQ = ("zc_rate", "osc_freq")
STEPPED_ENERGY = ("energy_q10", "energy_q50", "energy_q90")
SMOOTH_FREQ = ("spec_cent", "spec_bw")
SMOOTH_ENERGY = ("e_cent", "e_spread")
#: The spectrum's skew and the second half's centroid, the last two the shipped model took (docs/estimator.md,
#: "two more smooth features").
EXTRA_SPECTRAL = ("spec_skew", "spec_cent2")
#: The feature sets compared.
#: The 14 features the model had before the moments.
STEPPED_SET = [n for n in MODEL_FEATURES if n not in MOMENT_FEATURES]
FEATURE_SETS = {
    "the 14 before the moments": STEPPED_SET,
    "crossings -> spectral moments": [n for n in STEPPED_SET if n not in STEPPED_FREQ] + list(SMOOTH_FREQ),
    "quantiles -> energy moments": [n for n in STEPPED_SET if n not in STEPPED_ENERGY] + list(SMOOTH_ENERGY),
    "the 14 + four moments (18)": STEPPED_SET + list(SMOOTH_FREQ + SMOOTH_ENERGY),
    "shipped: the 18 + spec_skew, spec_cent2 (20)": list(MODEL_FEATURES),
}


def feature_table(features, names) -> np.ndarray:
    """Columns ``names`` of feature rows ``(n, len(FEATURE_NAMES))``: ``(n, len(names))``."""
    return features[:, [FEATURE_NAMES.index(k) for k in names]]


def fit_mean(x, y, degree):
    """Least-squares Legendre mean of total degree ``degree`` in (slip, kS, phiS, dphi): ``(terms, coef)``."""
    terms = node_terms({0: degree})[:, :4]
    u = (x[:, :4] - CENTER) / HALFWIDTH
    a = np.zeros((len(terms), len(terms)))
    b = np.zeros((len(terms), y.shape[1]))
    for k in range(0, len(x), 10000):
        d = legendre_design(u[k:k + 10000], terms)
        a += d.T @ d
        b += d.T @ y[k:k + 10000]
    ridge = 1e-10 * np.trace(a) / len(a)
    return terms, np.linalg.solve(a + ridge * np.eye(len(a)), b)


def predict(model, x):
    terms, coef = model
    return legendre_design((x[:, :4] - CENTER) / HALFWIDTH, terms) @ coef


def draw_runs(n_soils, n_slips, omega, rng):
    """``n_soils`` soils of the estimator's domain, each at ``n_slips`` slips: rows (slip, kS, phiS, dphi, omega)."""
    soils = []
    while len(soils) < n_soils:
        ks, phis, dphi = rng.uniform(500, 1500), rng.uniform(0.3, 0.8), rng.uniform(0.0, 0.35)
        if phis - dphi >= 0.1:
            soils.append((ks, phis, dphi))
    return np.array([(s, *soil, omega) for soil in soils for s in rng.uniform(0.0, 0.5, n_slips)])


def soil_grid():
    cells = [(k, p, d) for k in np.linspace(500, 1500, 11) for p in np.linspace(0.3, 0.8, 11)
             for d in np.linspace(0.0, 0.35, 9) if p - d >= 0.1]
    return np.array(cells), np.arange(0.0, 0.55, 0.02)


def score_set(names, data, degree, n_slips) -> dict:
    """Slip RMSE of one feature set over the runs (soil unknown per soil temper, soil known) and the R^2."""
    (xtr, ftr), (xte, fte), (xr, fr) = data
    ytr = feature_table(ftr, names)
    ok = np.all(np.isfinite(ytr), 1)
    model = fit_mean(xtr[ok], ytr[ok], degree)
    yte = feature_table(fte, names)
    ok = np.all(np.isfinite(yte), 1)
    resid = yte[ok] - predict(model, xte[ok])
    w = np.linalg.cholesky(np.linalg.inv(np.cov(resid.T)))
    r2 = 1.0 - resid.var(0) / yte[ok].var(0)
    cells, nodes = soil_grid()
    grid_x = np.array([(s, *c) for c in cells for s in nodes])
    mu = (predict(model, grid_x) @ w).reshape(len(cells), len(nodes), -1)
    yr = feature_table(fr, names)
    errs = {t: [] for t in SOIL_TEMPERS}
    errs["known"] = []
    for s0 in range(0, len(xr), n_slips):
        xs, ys = xr[s0:s0 + n_slips], yr[s0:s0 + n_slips]
        keep = np.all(np.isfinite(ys), 1)
        xs, z = xs[keep], ys[keep] @ w
        if not len(xs):
            continue
        loglik = -0.5 * SLIP_TEMPER * ((mu[None] - z[:, None, None, :]) ** 2).sum(-1)  # (cycles, cells, nodes)
        top = loglik.max((1, 2), keepdims=True)
        lik = np.exp(loglik - top)
        lc = np.log(lik.sum(2)) + top[:, :, 0]
        for t in SOIL_TEMPERS:
            lw = t * (lc - lc.max(1, keepdims=True)).sum(0)
            ws = np.exp(lw - lw.max())
            ps = (lik * ws[None, :, None]).sum(1)
            errs[t].append(ps @ nodes / ps.sum(1) - xs[:, 0])
        known = np.array([(s, *xs[0, 1:4]) for s in nodes])
        lk = -0.5 * SLIP_TEMPER * ((predict(model, known) @ w)[None] - z[:, None, :]) ** 2
        lk = lk.sum(-1)
        pk = np.exp(lk - lk.max(1, keepdims=True))
        errs["known"].append(pk @ nodes / pk.sum(1) - xs[:, 0])
    rmse = {str(k): float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in errs.items()}
    return {"features": names, "rmse": rmse, "r2": dict(zip(names, map(float, r2)))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--omega", type=float, default=0.63, help="leg speed [rad/s]")
    ap.add_argument("--rate", type=float, default=1000.0, help="IMU rate [Hz]")
    ap.add_argument("--noise", type=float, default=0.01, help="IMU noise [g]")
    ap.add_argument("--train", type=int, default=80000, help="stances fitting the means")
    ap.add_argument("--test", type=int, default=20000, help="stances giving the residual covariance")
    ap.add_argument("--soils", type=int, default=300, help="soils estimated")
    ap.add_argument("--slips", type=int, default=12, help="cycles (slips) per soil")
    ap.add_argument("--degree", type=int, default=10, help="total degree of the means")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args(argv)
    for name in ("train", "test", "soils", "slips", "degree"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1")
    if not (0.25 <= args.omega <= 1.3 and 200 <= args.rate <= 2000 and 0 <= args.noise <= 0.05):
        ap.error("--omega 0.25-1.3 rad/s, --rate 200-2000 Hz, --noise 0-0.05 g")
    t0 = time.time()
    rng = np.random.default_rng(args.seed)
    data = []
    bar = tqdm(total=args.train + args.test + args.soils * args.slips, desc="simulating stances", unit="stance",
               file=sys.stderr)
    for x in (draw_envelope(args.train, rng), draw_envelope(args.test, rng),
              draw_runs(args.soils, args.slips, args.omega, rng)):
        x[:, 4] = args.omega
        data.append((x, simulate_features(x, args.rate, args.noise, rng, progress=bar.update)))
    bar.close()
    out = {}
    for label, names in tqdm(FEATURE_SETS.items(), desc="feature sets", file=sys.stderr):
        out[label] = score_set(names, data, args.degree, args.slips)
    print(f"slip RMSE by feature set: {args.omega:g} rad/s, {args.rate:g} Hz, {args.noise:g} g; {args.soils} soils x "
          f"{args.slips} slips, degree {args.degree}, seed {args.seed}; {time.time() - t0:.0f} s")
    head = "".join(f"  soil t={t:<5g}" for t in SOIL_TEMPERS)
    print(f"  {'feature set':30s}{head}  soil known")
    for label, r in out.items():
        print(f"  {label:30s}" + "".join(f"  {r['rmse'][str(t)]:11.4f}" for t in SOIL_TEMPERS)
              + f"  {r['rmse']['known']:10.4f}")
    r2 = out["shipped: the 18 + spec_skew, spec_cent2 (20)"]["r2"]
    print("  R^2 of the means: " + ", ".join(f"{k} {r2[k]:.3f}" for k in STEPPED_FREQ + STEPPED_ENERGY + SMOOTH_FREQ
                                             + SMOOTH_ENERGY + EXTRA_SPECTRAL))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
