"""Simulated per-cycle features for training and checking the inverses (pure computation).

The feature vectors a real stream would give are produced here without
building a stream: each stance is simulated by
:func:`slipest.model.stance.simulate_batch` on its ``dt`` grid, sampled at
the IMU rate with a random sub-sample offset (as
:mod:`slipest.model.stream` samples the continuous signal), given Gaussian
noise of ``noise_g`` [g] and passed to :func:`slipest.features.features_batch`.
The stream's own path (segmenter included) is what the benchmarks use.

Soil and slip ranges are those of the spec and of the shipped calibration
grid: ``kS`` 500-1500 N/m, ``phiD`` 0.1-0.4 rad, ``dphi`` 0-0.35 rad, slip
0-0.5 (:data:`RANGES`).
"""

from __future__ import annotations

import math

import numpy as np

from slipest.features import FEATURE_NAMES, features_batch
from slipest.model.params import StickSlipParams
from slipest.model.stance import DEFAULT_DT, simulate_batch
from slipest.units import G

#: Parameter ranges [lo, hi] of the training and benchmark draws (SI).
RANGES = {"slip": (0.0, 0.5), "kS": (500.0, 1500.0), "phiD": (0.1, 0.4), "dphi": (0.0, 0.35)}


def draw_soils(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` soils uniform in :data:`RANGES`: ``(n, 3)`` columns kS [N/m], phiS, phiD [rad]."""
    kS = rng.uniform(*RANGES["kS"], n)
    phiD = rng.uniform(*RANGES["phiD"], n)
    dphi = rng.uniform(*RANGES["dphi"], n)
    return np.column_stack([kS, phiD + dphi, phiD])


def simulate_features(
    slip,
    kS,
    phiS,
    phiD,
    rate: float = 1000.0,
    noise_g: float = 0.01,
    rng: np.random.Generator | None = None,
    base: StickSlipParams | None = None,
    chunk: int = 512,
    dt: float = DEFAULT_DT,
    progress=None,
) -> np.ndarray:
    """Feature rows ``(n, len(FEATURE_NAMES))`` of ``n`` simulated stances.

    slip [-], kS [N/m], phiS, phiD [rad]: 1-D arrays of one length.
    rate: IMU sample rate [Hz]; noise_g: noise standard deviation [g].
    base: the other model parameters (default :class:`StickSlipParams`).
    Rows whose stance failed in the model are NaN. ``progress(k)``, when
    given, is called with the number of stances done after each chunk.
    """
    rng = rng or np.random.default_rng()
    base = base or StickSlipParams()
    slip, kS, phiS, phiD = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (slip, kS, phiS, phiD))
    n = slip.size
    out = np.full((n, len(FEATURE_NAMES)), np.nan)
    half = math.pi / base.nL
    step = base.omega / rate  # phase between samples [rad]
    for k0 in range(0, n, chunk):
        sl = slice(k0, min(n, k0 + chunk))
        params = [
            base.with_(slip=float(a), kS=float(b), phiS=float(c), phiD=float(d))
            for a, b, c, d in zip(slip[sl], kS[sl], phiS[sl], phiD[sl])
        ]
        res = simulate_batch(params, dt=dt, waveforms=True, on_error="flag")
        m = int(res.n_steps[res.ok].min()) if res.ok.any() else 0
        if m < 2:
            if progress:
                progress(len(params))
            continue
        theta = res.theta[int(np.argmax(res.ok)), :m]
        offset = rng.uniform(0.0, step)
        ph = np.arange(offset, half, step)
        ph = ph[ph <= theta[-1]]
        # linear interpolation on the common theta grid of the batch (one phase grid for all rows)
        j = np.clip(np.searchsorted(theta, ph, side="right") - 1, 0, m - 2)
        w = (ph - theta[j]) / (theta[j + 1] - theta[j])
        az = res.az[:, j] * (1.0 - w) + res.az[:, j + 1] * w + base.g
        az[~res.ok] = np.nan
        az += rng.normal(0.0, noise_g * G, az.shape)
        out[sl] = features_batch(ph, az, n_legs=base.nL, omega=base.omega)
        if progress:
            progress(len(params))
    return out
