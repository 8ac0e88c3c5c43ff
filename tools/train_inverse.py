#!/usr/bin/env python3
"""Train the multi-feature inverse (feature surrogate) on the simulator and write it as package data.

Draws slip, soil and leg speed uniformly over the envelope of
:mod:`slipest.inverse.simdata` (slip 0-0.55, kS 400-1700 N/m, phiS 0.1-0.9
rad, dphi 0-0.4 rad with phiD >= 0.08 rad, omega 0.25-1.3 rad/s: a margin
around what the estimator promises), an IMU rate log-uniform in 200-2000 Hz
and a noise uniform in 0-0.03 g per stance; simulates each stance, samples
and measures it (:mod:`slipest.features`), fits
:class:`slipest.inverse.surrogate.FeatureSurrogate` and checks it on a
held-out draw: one-cycle slip with the soil known and unknown (RMSE, 95 %
coverage), and the level of the best candidate's squared whitened distance
on clean cycles (``fit_level``, the estimator's misfit threshold). Writes
``slipest/data/inverse_model.json`` (``--out`` to write elsewhere). The
benchmarks draw with other seeds; nothing here looks at them.

    python tools/train_inverse.py                        # ~25 min on 2 cores (simulation ~10, fit ~8, checks ~5)
    python tools/train_inverse.py --n-train 60000 --schedule small   # quick, for trying things
    python tools/train_inverse.py --rows rows.npz        # keep (or reuse) the simulated rows
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from slipest import __version__
from slipest.inverse.feature_inverse import FeatureInverse
from slipest.inverse.simdata import ENVELOPE, NOISE_RANGE, PHID_MIN, RATE_RANGE, VARIABLES, draw_envelope, draw_imu, simulate_features
from slipest.inverse.surrogate import FeatureSurrogate, save_inverse_model
from slipest.model.params import StickSlipParams

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "slipest" / "data" / "inverse_model.json"

#: Term schedules: {(omega degree, noise degree): total degree in (slip, kS, phiS, dphi)}.
SCHEDULES = {
    "default": {(0, 0): 14, (1, 0): 10, (2, 0): 8, (3, 0): 6, (0, 1): 8, (1, 1): 6, (0, 2): 6, (2, 1): 4},
    "small": {(0, 0): 8, (1, 0): 6, (2, 0): 4, (0, 1): 4, (1, 1): 2},
}
#: What the estimator promises (the training envelope is wider).
COVERED = {"slip": [0.0, 0.5], "kS": [500.0, 1500.0], "phiS": [0.1, 0.8], "dphi": [0.0, 0.35], "omega": [0.3, 1.2],
           "phid_min": 0.1}


def simulate(n: int, rng: np.random.Generator, base: StickSlipParams, desc: str):
    """``n`` stances over the envelope: points ``x`` (n, 6) with the measured smoothed noise in column 5, rows."""
    x = draw_envelope(n, rng)
    rate, noise = draw_imu(n, rng)
    with tqdm(total=n, desc=desc, unit="stance", file=sys.stderr) as bar:
        rows = simulate_features(x, rate, noise, rng, base=base, progress=bar.update)
    from slipest.features import INDEX

    return np.column_stack([x, rows[:, INDEX["noise_smooth"]]]), rows, rate, noise


def one_cycle_figures(inverse: FeatureInverse, x, rows, n: int) -> dict:
    """Held-out one-cycle slip: soil known and unknown (RMSE, 95 % coverage)."""
    known, unknown = [], []
    for j in range(n):
        kS, phiS, dphi = x[j, 1:4]
        known.append(inverse.slip_known_soil(rows[j], kS, phiS, phiS - dphi))
        unknown.append(inverse.slip(rows[j]))

    def figs(est):
        est = np.asarray(est)
        e = est[:, 0] - x[:n, 0]
        ok = np.isfinite(e)
        return {"slip_rmse": float(np.sqrt(np.mean(e[ok] ** 2))),
                "coverage95": float(np.mean(np.abs(e[ok]) <= 1.96 * est[ok, 1])), "n": int(ok.sum())}

    return {"soil_known": figs(known), "soil_unknown": figs(unknown)}


def fit_level(model: FeatureSurrogate, x, rows, n: int) -> dict:
    """Quantiles of the best candidate's squared whitened distance over the grid, on clean held-out cycles."""
    from slipest.inverse.grid import SLIP_NODES, SoilGrid, grid_tables, slip_prior
    from slipest.inverse.grid_kernels import grid_loglik, whiten_into

    tables = grid_tables(model, SoilGrid.default(), SLIP_NODES[::2])
    cols = np.ascontiguousarray(model.columns, dtype=np.int64)
    lp = slip_prior(SLIP_NODES[::2]).astype(np.float32)
    best = []
    for j in range(n):
        table = tables.get(x[j, 4], x[j, 5])
        d, k, s = table.columnar.shape
        fw = np.zeros(d, dtype=np.float32)
        if not whiten_into(rows[j], cols, table.whitener, fw):
            continue
        b, _ = grid_loglik(table.columnar, fw, lp, 0.02, 1.0, np.inf, np.empty((k, s), np.float32), np.empty(s),
                           np.empty((2, s), np.float32))
        best.append(b)
    q = np.percentile(best, [50, 90, 95, 99, 99.5])
    return {"q50": float(q[0]), "q90": float(q[1]), "q95": float(q[2]), "q99": float(q[3]), "q995": float(q[4]),
            "n": len(best)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-train", type=int, default=400000, help="training stances (default 400000)")
    ap.add_argument("--n-val", type=int, default=6000, help="held-out stances (default 6000)")
    ap.add_argument("--schedule", choices=sorted(SCHEDULES), default="default", help="term schedule (default: default)")
    ap.add_argument("--n-check", type=int, default=800,
                    help="held-out stances the one-cycle figures and the misfit level use (default 800; each needs "
                    "a grid table at its speed and noise, about 0.2 s)")
    ap.add_argument("--legs", type=int, default=4, help="legs of the wheel-leg the model is for (default 4)")
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--rows", type=Path, help="an .npz of simulated rows: read if it exists, else written")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    base = StickSlipParams().with_(nL=args.legs)
    t0 = time.time()
    if args.rows is not None and args.rows.exists():
        data = np.load(args.rows)
        x_tr, f_tr, x_va, f_va = data["x_tr"], data["f_tr"], data["x_va"], data["f_va"]
        print(f"read {len(x_tr)} + {len(x_va)} simulated rows from {args.rows}", file=sys.stderr)
    else:
        rng = np.random.default_rng(args.seed)
        x_tr, f_tr, _, _ = simulate(args.n_train, rng, base, "simulate (training)")
        x_va, f_va, _, _ = simulate(args.n_val, rng, base, "simulate (held out)")
        if args.rows is not None:
            np.savez(args.rows, x_tr=x_tr, f_tr=f_tr, x_va=x_va, f_va=f_va)
    t_sim = time.time() - t0
    ranges = [list(ENVELOPE[v]) for v in VARIABLES[:5]] + [[0.0, float(np.nanmax(x_tr[:, 5]))]]
    with tqdm(total=len(x_tr), desc="fit", unit="row", file=sys.stderr) as bar:
        model = FeatureSurrogate.fit(x_tr, f_tr, SCHEDULES[args.schedule], ranges=ranges, phid_min=PHID_MIN,
                                     covered=COVERED, progress=bar.update)
    t_fit = time.time() - t0 - t_sim
    save_inverse_model(model, args.out)  # (again below with the held-out figures) not lost if checking fails
    ok = np.all(np.isfinite(f_va[:, model.columns]), axis=1)
    x_va, f_va = x_va[ok], f_va[ok]
    levels = fit_level(model, x_va, f_va, min(len(x_va), args.n_check))
    meta = {
        "created_by": "tools/train_inverse.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "slipest_version": __version__,
        "training": {"n_train": int(len(x_tr)), "n_val": int(len(x_va)), "seed": args.seed,
                     "schedule": {f"{k[0]},{k[1]}": v for k, v in SCHEDULES[args.schedule].items()},
                     "n_terms": int(model.terms.shape[0]), "envelope": ENVELOPE, "phid_min": PHID_MIN,
                     "rate_hz": list(RATE_RANGE), "noise_g": list(NOISE_RANGE),
                     "model": f"StickSlipParams defaults but nL {args.legs}", "n_legs": args.legs,
                     "simulate_s": round(t_sim), "fit_s": round(t_fit)},
        "fit_level": levels["q99"],
        "fit_level_quantiles": levels,
        "units": {"slip": "-", "kS": "N/m", "phiS": "rad", "dphi": "rad", "omega": "rad/s", "noise_smooth": "g",
                  "features": "see slipest.features.FEATURE_UNITS"},
    }
    model = FeatureSurrogate(model.features, model.center, model.halfwidth, model.ranges, model.phid_min, model.terms,
                             model.coef, model.cov_coef, model.covered, meta)
    meta["validation_one_cycle"] = one_cycle_figures(FeatureInverse(model), x_va, f_va, min(len(x_va), args.n_check))
    path = save_inverse_model(model, args.out)
    v = meta["validation_one_cycle"]
    print(f"wrote {path}: {model.terms.shape[0]} terms; simulation {t_sim:.0f} s, fit {t_fit:.0f} s", file=sys.stderr)
    print(f"one cycle, held out: soil known   slip RMSE {v['soil_known']['slip_rmse']:.4f}, "
          f"95% coverage {v['soil_known']['coverage95']:.3f}")
    print(f"one cycle, held out: soil unknown slip RMSE {v['soil_unknown']['slip_rmse']:.4f}, "
          f"95% coverage {v['soil_unknown']['coverage95']:.3f}")
    print(f"best candidate's squared whitened distance on clean cycles: median {levels['q50']:.1f}, "
          f"99th percentile {levels['q99']:.1f} (the misfit level)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
