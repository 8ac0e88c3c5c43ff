"""A physics-based discrepancy: what a named catalog effect does to the features, from the simulator (pure computation).

When the diagnosis names an effect of the catalog (:mod:`slipest.model.effects`)
with fitted parameters, the simulator with that effect switched on gives
the rover's features on *any* soil, not only the testbed's.
:func:`effect_batch` simulates a small batch of leg cycles (slip and soil
drawn uniformly over the estimator's grid, one stream, the testbed's leg
speed, IMU rate and noise) and takes their features through the
estimator's own path (:func:`slipest.rover.testbed.cycle_rows`);
:func:`fit_effect_discrepancy` fits the discrepancy ``D`` (low total degree
in slip and soil) through their residuals from the shipped surrogate, and
returns the residuals left over (their scatter beyond the surrogate's
covariance becomes extra covariance).

Cost: about 100-200 simulated cycles per second on 2 cores (stream at the
model's step, effects included, then features).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from slipest.features import INDEX
from slipest.inverse.grid import SoilGrid
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.rover.discrepancy import Discrepancy, fit_discrepancy, soil_terms
from slipest.rover.testbed import cycle_rows

#: Slip range of the batch [-].
SLIP_RANGE = (0.0, 0.5)


def draw_cycles(n: int, rng: np.random.Generator, grid: SoilGrid | None = None) -> np.ndarray:
    """``n`` points ``(n, 4)``: slip [-], kS [N/m], phiS, dphi [rad], uniform over the grid's box with
    ``phiS - dphi >= phid_min``."""
    g = grid or SoilGrid.default()
    lo = np.array([SLIP_RANGE[0], g.kS.min(), g.phiS.min(), g.dphi.min()])
    hi = np.array([SLIP_RANGE[1], g.kS.max(), g.phiS.max(), g.dphi.max()])
    out = np.empty((0, 4))
    while len(out) < n:
        x = lo + (hi - lo) * rng.uniform(size=(2 * (n - len(out)) + 8, 4))
        out = np.vstack([out, x[x[:, 2] - x[:, 3] >= g.phid_min]])
    return out[:n]


def effect_batch(effects, n: int, rng: np.random.Generator, *, omega: float, rate: float, noise_g: float,
                 kappa: float = 0.3, n_legs: int = 4, grid: SoilGrid | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Simulated cycles with the catalog ``effects`` (specs ``{"name": ..., params}``; empty: the nominal
    model): ``(x4 (m, 4), features (m, F))``, the cycles the estimator's path estimated (m <= n).

    omega [rad/s], rate [Hz], noise_g [g]: the testbed's leg speed and IMU; kappa [-]: the rover's."""
    x = draw_cycles(n, rng, grid)
    base = StickSlipParams(kappa=kappa, nL=n_legs, omega=omega)
    sc = Scenario.per_cycle(base, {"rate": rate, "noise_g": noise_g, "seed": int(rng.integers(2**31))},
                            slip=x[:, 0], kS=x[:, 1], phiS=x[:, 2], phiD=x[:, 2] - x[:, 3])
    sc = replace(sc, effects=tuple(dict(e) for e in effects))
    from slipest.model.stream import simulate_stream

    s = simulate_stream(sc)
    r = cycle_rows(s.t, s.az, s.theta, None, n_legs)
    keep = (r["cycle"] >= 0) & (r["cycle"] < n)
    return x[r["cycle"][keep]], r["features"][keep]


def batch_residuals(model, x4, features) -> np.ndarray:
    """Features minus the model's mean at each cycle's slip, soil and measured leg speed and noise ``(n, d)``."""
    f = np.asarray(features, dtype=float)
    x6 = np.column_stack([x4, f[:, INDEX["omega"]], f[:, INDEX["noise_smooth"]]])
    return model.observe(f) - model.mean(x6)


def fit_effect_discrepancy(model, x4, features, degree: int = 3, ridge: float = 1e-4) -> tuple[Discrepancy, np.ndarray]:
    """``D`` of total degree ``degree`` in (slip, kS, phiS, dphi) through the batch's residuals from ``model``;
    returns it and the residuals it leaves ``(n, d)``."""
    resid = batch_residuals(model, x4, features)
    d = fit_discrepancy(x4, resid, soil_terms(degree), model.features, model.center[:4], model.halfwidth[:4], ridge)
    left = resid - d.evaluate(x4)
    return d, left


__all__ = ["SLIP_RANGE", "batch_residuals", "draw_cycles", "effect_batch", "fit_effect_discrepancy"]
