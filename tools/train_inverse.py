#!/usr/bin/env python3
"""Train the multi-feature inverse (feature surrogate) on the simulator and write it as package data.

Draws slip and soil uniformly over the spec's ranges (slip 0-0.5, kS
500-1500 N/m, phiD 0.1-0.4 rad, dphi 0-0.35 rad), simulates each stance,
samples it like a 1 kHz IMU with 0.01 g noise, computes the features
(:mod:`slipest.features`), fits :class:`slipest.inverse.surrogate.FeatureSurrogate`
and checks it on a held-out draw (slip RMSE and 95 % coverage, soil known
and unknown, one cycle). Writes ``slipest/data/inverse_model.json``
(``--out`` to write elsewhere). The benchmarks draw their soils with other
seeds; nothing here looks at them.

    python tools/train_inverse.py                             # ~5 min on 2 cores
    python tools/train_inverse.py --n-train 30000 --degree 8  # quick, for trying things
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
from slipest.inverse.simdata import RANGES, draw_soils, simulate_features
from slipest.inverse.surrogate import MODEL_FEATURES, FeatureSurrogate, SurrogateInverse, save_inverse_model
from slipest.model.params import StickSlipParams

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "slipest" / "data" / "inverse_model.json"


def draw(n, rng, noise_g, rate, bar, base):
    soils = draw_soils(n, rng)
    slip = rng.uniform(*RANGES["slip"], n)
    feats = simulate_features(slip, soils[:, 0], soils[:, 1], soils[:, 2], rate=rate, noise_g=noise_g, rng=rng,
                              progress=bar.update, base=base)
    return feats, slip, soils


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-train", type=int, default=400000, help="training stances (default 400000)")
    ap.add_argument("--n-val", type=int, default=3000, help="held-out stances (default 3000)")
    ap.add_argument("--degree", type=int, default=14, help="total degree of the surrogate polynomials (default 14)")
    ap.add_argument("--noise", type=float, default=0.01, help="IMU noise [g] (default 0.01)")
    ap.add_argument("--rate", type=float, default=1000.0, help="IMU rate [Hz] (default 1000)")
    ap.add_argument("--legs", type=int, default=4, help="legs of the wheel-leg the model is for (default 4)")
    ap.add_argument("--omega", type=float, default=StickSlipParams().omega,
                    help="leg angular speed [rad/s] of the training stances (default: the model's)")
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    base = StickSlipParams().with_(nL=args.legs, omega=args.omega)
    t0 = time.time()
    with tqdm(total=args.n_train + args.n_val, desc="simulate", unit="stance", file=sys.stderr) as bar:
        f_tr, s_tr, soil_tr = draw(args.n_train, rng, args.noise, args.rate, bar, base)
        f_va, s_va, soil_va = draw(args.n_val, rng, args.noise, args.rate, bar, base)
    ranges = [RANGES["slip"], RANGES["kS"], RANGES["phiD"], RANGES["dphi"]]
    model = FeatureSurrogate.fit(f_tr, s_tr, soil_tr[:, 0], soil_tr[:, 1], soil_tr[:, 2], MODEL_FEATURES,
                                 degree=args.degree, ranges=ranges)
    # held-out checks, one cycle at a time
    inv = SurrogateInverse(model)
    n_chk = min(args.n_val, 1500)
    known = np.array([inv.slip_known_soil(f_va[j], *soil_va[j]) for j in range(n_chk)])
    unknown = np.array([inv.slip(f_va[j]) for j in range(n_chk)])
    truth = s_va[:n_chk]

    def figs(est):
        e = est[:, 0] - truth
        return {"slip_rmse": float(np.sqrt(np.mean(e**2))), "coverage95": float(np.mean(np.abs(e) <= 1.96 * est[:, 1]))}

    mu_va = model.mean(s_va, soil_va[:, 0], soil_va[:, 1], soil_va[:, 2])
    obs = model.observe(f_va)
    resid = obs - mu_va
    rel = (resid.std(0) / obs.std(0)).tolist()
    meta = {
        "created_by": "tools/train_inverse.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "created_utc": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "slipest_version": __version__,
        "training": {"n_train": args.n_train, "n_val": args.n_val, "seed": args.seed, "noise_g": args.noise,
                     "rate_hz": args.rate, "ranges": {k: list(v) for k, v in RANGES.items()},
                     "model": f"StickSlipParams defaults but nL {args.legs}, omega {args.omega:g} rad/s",
                     "n_legs": args.legs, "omega": args.omega},
        "validation_one_cycle": {"soil_known": figs(known), "soil_unknown": figs(unknown),
                                 "residual_std_over_feature_std": dict(zip(model.features, rel))},
        "units": {"slip": "-", "kS": "N/m", "phiD": "rad", "dphi": "rad", "features": "see slipest.features.FEATURE_UNITS"},
    }
    model = FeatureSurrogate(model.features, model.center, model.halfwidth, model.ranges, model.degree, model.terms,
                             model.coef, model.R, meta, model.log_offset)
    path = save_inverse_model(model, args.out)
    v = meta["validation_one_cycle"]
    print(f"wrote {path} in {time.time() - t0:.0f} s", file=sys.stderr)
    print(f"one cycle, held out: soil known  slip RMSE {v['soil_known']['slip_rmse']:.4f}, "
          f"95% coverage {v['soil_known']['coverage95']:.3f}")
    print(f"one cycle, held out: soil unknown slip RMSE {v['soil_unknown']['slip_rmse']:.4f}, "
          f"95% coverage {v['soil_unknown']['coverage95']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
