"""Synthetic runs for checking the diagnosis and sizing effects (pure computation, no files).

* :func:`simulate_run`: a run's samples ``t, az, theta, slip`` from a
  :class:`~slipest.model.scenario.Scenario` (catalog effects included), with
  optional *extra* sensor stages that are not in the catalog (objects with
  ``domain`` and ``apply`` like :mod:`slipest.model.sensor`'s): the model
  is sampled at its own step, the extra continuous stages act there, the
  signal is decimated to the IMU rate, then the noise and the extra
  sampled stages act, as in :mod:`slipest.model.stream`.
* :func:`stance_da`: each whole cycle's ``Da`` [g] over the stance window of
  the *logged* phase, by :func:`slipest.features.cycle_features` (the
  project's ``Da``).
* :func:`da_change`: how much an effect changes ``Da``: mean over cycles of
  ``|Da_effect / Da_nominal - 1|`` on the same soil and slips, noise-free.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from slipest.features import cycle_features
from slipest.model.scenario import Scenario
from slipest.model.sensor import GaussianNoise, run_stages
from slipest.model.stream import simulate_stream


def simulate_run(scenario: Scenario, extra_stages=()) -> dict:
    """Samples of a run: ``t`` [s], ``az`` [m/s^2], ``theta`` [rad], ``slip`` [-] (arrays)."""
    extra_stages = list(extra_stages)
    if not extra_stages:
        s = simulate_stream(scenario)
        return {"t": s.t, "az": s.az, "theta": s.theta, "slip": s.slip}
    step = int(round(1.0 / (scenario.rate * scenario.dt)))
    if abs(step * scenario.rate * scenario.dt - 1.0) > 1e-9:
        raise ValueError("extra stages need an IMU period that is a whole number of model steps")
    fine = simulate_stream(replace(scenario, rate=1.0 / scenario.dt, noise_g=0.0))
    rng = np.random.default_rng(scenario.seed)
    az, _ = run_stages(extra_stages, "continuous", fine.t, fine.az.copy(), fine.theta, rng)
    t, az, theta, slip = fine.t[::step], az[::step], fine.theta[::step], fine.slip[::step]
    az, theta = GaussianNoise(scenario.noise_g).apply(t, az, theta, rng)
    az, theta = run_stages(extra_stages, "sampled", t, az, theta, rng)
    return {"t": t, "az": az, "theta": theta, "slip": slip}


def stance_da(run: dict, n_legs: int) -> np.ndarray:
    """``Da`` [g] of cycles 0, 1, ... (logged phase) whose stance window ``[0, pi/nL]`` is complete, else NaN."""
    half = math.pi / n_legs
    theta = np.asarray(run["theta"])
    k = np.floor((theta + half) / (2 * half)).astype(np.int64)
    out = []
    for kk in range(0, int(k.max()) + 1):
        sel = k == kk
        phase = theta[sel] - 2 * half * kk
        if sel.sum() < 32 or phase.min() > 1e-3 or phase.max() < half - 0.01:
            out.append(np.nan)
            continue
        out.append(cycle_features(phase, np.asarray(run["az"])[sel], np.asarray(run["t"])[sel], n_legs)[0])
    return np.array(out)


def da_change(scenario: Scenario, effects=(), extra_stages=()) -> float:
    """Mean relative change of ``Da`` an effect causes (catalog ``effects`` and/or ``extra_stages``).

    Both runs are noise-free, on the scenario's cycles; cycles whose ``Da``
    is not defined in either run are skipped.
    """
    base = replace(scenario, noise_g=0.0, effects=())
    with_effect = replace(base, effects=tuple(effects))
    n_legs = scenario.n_legs
    d0 = stance_da(simulate_run(base), n_legs)
    d1 = stance_da(simulate_run(with_effect, extra_stages), n_legs)
    n = min(len(d0), len(d1))
    d0, d1 = d0[:n], d1[:n]
    ok = np.isfinite(d0) & np.isfinite(d1) & (d0 > 0)
    if not ok.any():
        return float("nan")
    return float(np.mean(np.abs(d1[ok] / d0[ok] - 1.0)))
