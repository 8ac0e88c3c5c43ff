#!/usr/bin/env python
"""Measure the known weak points of the stick-slip model that docs/model.md states.

On ``--n`` stances drawn uniformly over the project's ranges (slip 0-0.5,
kS 500-1500 N/m, phiD 0.1-0.4 rad, dphi 0-0.35 rad: ``RANGES``, the ranges
the model was first explored over), prints:

* how many stances lose contact at least once (the re-planting rule is
  used), on the draws and on the shipped calibration's grid;
* the sensitivity to ``kappa`` (0.1, 0.3, 1.0): failed stances by cause and
  the median ``Da`` [g];
* the shape of the waveform: where in the stance the largest ``|zH''|``
  lies, and how often the amplitude "grows then decays" as in the thesis's
  Fig. 5.5 (largest ``|zH''|`` before 75% of the stance and the last
  quarter's largest below 0.7 of it), for the draws and the Fig. 5.5 cases;
* the step convergence (``Da`` at dt and dt/2) on the draws.

    python tools/model_weak_points.py [--n 2000] [--seed 1]
"""

from __future__ import annotations

import argparse
import itertools
import math

import numpy as np

from slipest.calibration import load_calibration
from slipest.model.params import StickSlipParams
from slipest.model.stance import DEFAULT_DT, simulate_batch, status_text

#: The ranges drawn [SI]: slip, kS [N/m], phiD and dphi [rad].
RANGES = {"slip": (0.0, 0.5), "kS": (500.0, 1500.0), "phiD": (0.1, 0.4), "dphi": (0.0, 0.35)}

#: Fig. 5.5 cases (docs/model.md section 4): label, changes from the defaults.
FIG55 = [("i=0.50", dict(slip=0.5)), ("i=0.25", dict(slip=0.25)), ("i=0.125", dict(slip=0.125)),
         ("kS=1.5k", dict(kS=1500.0)), ("kS=0.5k", dict(kS=500.0)), ("phiS=.70,phiD=.30", dict(phiS=0.70, phiD=0.30)),
         ("phiS=.52,phiD=.30", dict(phiS=0.52, phiD=0.30)), ("phiS=.35,phiD=.30", dict(phiS=0.35, phiD=0.30))]


def draws(n: int, seed: int) -> list[StickSlipParams]:
    rng = np.random.default_rng(seed)
    slip, ks, phid, dphi = (rng.uniform(*RANGES[k], n) for k in ("slip", "kS", "phiD", "dphi"))
    return [StickSlipParams(slip=a, kS=b, phiS=c + d, phiD=c) for a, b, c, d in zip(slip, ks, phid, dphi)]


def calibration_grid() -> list[StickSlipParams]:
    g = load_calibration()["grid"]
    out = []
    for slip, ks, phid, dphi in itertools.product(g["slip"], g["kS"], g["phiD"], g["dphi"]):
        if phid + dphi < math.pi / 2 - 0.1:  # the calibration's margin below pi/2
            out.append(StickSlipParams(slip=slip, kS=ks, phiS=phid + dphi, phiD=phid))
    return out


def shape(batch) -> np.ndarray:
    """Per stance: (position of the largest |zH''| as a share of the stance, last quarter's largest / it)."""
    out = []
    for j in np.flatnonzero(batch.ok):
        n = batch.n_steps[j]
        share = batch.theta[j, :n] / batch.theta[j, n - 1]
        a = np.abs(batch.az[j, :n])
        out.append((share[np.argmax(a)], a[share > 0.75].max() / a.max()))
    return np.array(out)


def grows_then_decays(s: np.ndarray) -> np.ndarray:
    return (s[:, 0] < 0.75) & (s[:, 1] < 0.7)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="random stances (default 2000)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the draws (default 1)")
    args = ap.parse_args(argv)
    ps = draws(args.n, args.seed)
    ranges = ", ".join(f"{k} {lo:g}-{hi:g}" for k, (lo, hi) in RANGES.items())
    print(f"{args.n} stances uniform over {ranges} (seed {args.seed}), dt = {DEFAULT_DT:g} s")

    b = simulate_batch(ps, waveforms=True, on_error="flag")
    grid = calibration_grid()
    bg = simulate_batch(grid, on_error="flag")
    print("\n== contact loss (the re-planting rule)")
    print(f"   draws: {np.mean(b.n_contact_losses > 0):.1%} of the stances lose contact at least once")
    print(f"   calibration grid ({len(grid)} stances): {np.mean(bg.n_contact_losses > 0):.1%}")
    fig = simulate_batch([StickSlipParams(**c) for _, c in FIG55], waveforms=True)
    print(f"   Fig. 5.5 cases: {int(np.sum(fig.n_contact_losses > 0))} of {len(FIG55)}")

    print("\n== kappa sensitivity (the same draws)")
    for kappa in (0.1, 0.3, 1.0):
        bk = b if kappa == 0.3 else simulate_batch([p.with_(kappa=kappa) for p in ps], on_error="flag")
        causes = {status_text(s).split(":")[0]: int(np.sum(bk.status == s)) for s in np.unique(bk.status) if s}
        failed = ", ".join(f"{n} {c}" for c, n in causes.items()) or "none"
        print(f"   kappa {kappa:3.1f}: median Da {np.nanmedian(bk.delta_a_g):.3f} g; failed: {failed}")

    print("\n== waveform shape (largest |zH''|, gravity-free)")
    s = shape(b)
    print(f"   draws: position median {np.median(s[:, 0]):.0%} of the stance; in the last quarter "
          f"{np.mean(s[:, 0] > 0.75):.0%}; grows then decays {np.mean(grows_then_decays(s)):.0%}")
    sf = shape(fig)
    for (label, _), (pos, last), gd in zip(FIG55, sf, grows_then_decays(sf)):
        print(f"   {label:18s} largest at {pos:.0%} of the stance, last quarter {last:.2f} of it"
              + ("  (grows then decays)" if gd else ""))

    print("\n== step convergence on the draws: Da at dt and dt/2")
    half = simulate_batch(ps, dt=DEFAULT_DT / 2, on_error="flag")
    change = np.abs(half.delta_a / b.delta_a - 1)
    change = change[np.isfinite(change)]
    print(f"   relative change: median {np.median(change):.3%}, 95th percentile {np.percentile(change, 95):.3%}, "
          f"max {change.max():.2%}; share above 0.1%: {np.mean(change > 0.001):.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
