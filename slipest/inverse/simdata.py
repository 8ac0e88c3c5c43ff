"""Simulated per-cycle features over the estimator's envelope, for training and checking inverses (pure computation).

The feature rows a real stream would give are produced without building a
stream: each stance is simulated by :func:`slipest.model.stance.simulate_batch`
on its ``dt`` grid, sampled like an IMU at its own rate with a random
sub-sample offset (as :mod:`slipest.model.stream` samples the continuous
signal), given Gaussian noise and passed to the feature routine of
:mod:`slipest.features` with that noise level. The stream's own path
(segmenter included) is what the benchmarks use.

The *envelope* (:data:`ENVELOPE`) is what the shipped inverse model covers,
with a margin beyond what the estimator promises (``phiS`` up to 0.8 rad,
``phiD`` from 0.10 rad up to ``phiS``, ``dphi`` 0-0.35 rad, ``kS`` 500-1500 N/m,
slip 0-0.5, leg speed 0.3-1.2 rad/s, IMU 200 Hz - 2 kHz), so that the model's
edges are not where the estimates are made.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from slipest.features import FEATURE_NAMES, N_GRID, _row_features, _smoothed_grid
from slipest.model import kernel as K
from slipest.model.params import StickSlipParams
from slipest.model.stance import DEFAULT_DT, simulate_batch
from slipest.units import G

#: Ranges [lo, hi] of the training draw (SI): slip [-], kS [N/m], phiS, dphi [rad], omega [rad/s].
ENVELOPE = {"slip": (0.0, 0.55), "kS": (400.0, 1700.0), "phiS": (0.1, 0.9), "dphi": (0.0, 0.4), "omega": (0.25, 1.3)}
#: Smallest dynamic friction angle ``phiD = phiS - dphi`` of the draw [rad].
PHID_MIN = 0.08
#: IMU rates [Hz] and noise standard deviations [g] the training draws from (log-uniform rate, uniform noise).
RATE_RANGE = (200.0, 2000.0)
NOISE_RANGE = (0.0, 0.03)
#: The variables of a draw, in column order.
VARIABLES = ("slip", "kS", "phiS", "dphi", "omega")


def draw_envelope(n: int, rng: np.random.Generator, envelope: dict | None = None, phid_min: float = PHID_MIN) -> np.ndarray:
    """``n`` points uniform over the envelope with ``phiS - dphi >= phid_min``: ``(n, 5)`` columns :data:`VARIABLES`."""
    env = envelope or ENVELOPE
    out = np.empty((0, 5))
    while len(out) < n:
        m = 2 * (n - len(out)) + 16
        x = np.column_stack([rng.uniform(*env[k], m) for k in VARIABLES])
        out = np.vstack([out, x[x[:, 2] - x[:, 3] >= phid_min]])
    return out[:n]


def draw_imu(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` IMU settings: rates [Hz] (log-uniform over :data:`RATE_RANGE`) and noise [g] (uniform over :data:`NOISE_RANGE`)."""
    rate = np.exp(rng.uniform(math.log(RATE_RANGE[0]), math.log(RATE_RANGE[1]), n))
    return rate, rng.uniform(*NOISE_RANGE, n)


@numba.njit(parallel=True, cache=True)
def _sample_and_featurise(theta, az, n_steps, ok, omega, rate, noise, offset, seeds, g, half, out, grids):
    """Per stance ``b``: sample the waveform at ``rate[b]`` from phase ``offset[b]``, add N(0, noise[b]) [g], features;
    when ``grids`` has rows, also the smoothed phase grid the features are taken on (NaN for a failed stance)."""
    for b in numba.prange(theta.shape[0]):
        if not ok[b]:
            for j in range(out.shape[1]):
                out[b, j] = np.nan
            for j in range(grids.shape[1] if grids.shape[0] > 0 else 0):
                grids[b, j] = np.nan
            continue
        m = n_steps[b]
        step = omega[b] / rate[b]
        k = int((theta[b, m - 1] - offset[b]) / step) + 1
        ph = np.empty(k)
        a = np.empty(k)
        np.random.seed(seeds[b])
        j = 0
        for i in range(k):
            p = offset[b] + i * step
            while j < m - 2 and theta[b, j + 1] < p:
                j += 1
            w = (p - theta[b, j]) / (theta[b, j + 1] - theta[b, j])
            ph[i] = p
            a[i] = (az[b, j] * (1.0 - w) + az[b, j + 1] * w) / g + 1.0 + np.random.normal() * noise[b]
        _row_features(ph, a, half, omega[b], noise[b], N_GRID, out[b])
        if grids.shape[0] > 0:
            y = np.empty(N_GRID)
            _smoothed_grid(ph, a, half, omega[b], N_GRID, y)
            for j in range(N_GRID):
                grids[b, j] = y[j]


def simulate_features(x, rate, noise, rng: np.random.Generator, base: StickSlipParams | None = None,
                      chunk: int = 2000, dt: float = DEFAULT_DT, progress=None, grids: bool = False):
    """Feature rows ``(n, len(FEATURE_NAMES))`` of ``n`` simulated stances.

    x: ``(n, 5)`` columns :data:`VARIABLES` (slip [-], kS [N/m], phiS, dphi
    [rad], omega [rad/s]); rate [Hz] and noise [g]: ``(n,)`` IMU settings
    (the features are computed knowing the noise, as the online layer does
    with its estimate); base: the other model parameters (default
    :class:`StickSlipParams`: the project's hardware and ``kappa``). Rows
    whose stance failed in the model are NaN. ``progress(k)``, when given,
    is called with the number of stances done after each chunk. ``grids``:
    also return the smoothed signal each row's features are taken on
    (:data:`slipest.features.N_GRID` points over the feature window, in g
    with gravity in; NaN rows for failed stances), for studying other
    features: then the result is ``(features, grids)``.
    """
    x = np.asarray(x, dtype=float)
    n = len(x)
    rate = np.broadcast_to(np.asarray(rate, dtype=float), (n,)).copy()
    noise = np.broadcast_to(np.asarray(noise, dtype=float), (n,)).copy()
    base = base or StickSlipParams()
    row = base.to_row()
    out = np.full((n, len(FEATURE_NAMES)), np.nan)
    grid_out = np.full((n if grids else 0, N_GRID), np.nan)
    for k0 in range(0, n, chunk):
        sl = slice(k0, min(n, k0 + chunk))
        xs = x[sl]
        mat = np.tile(row, (len(xs), 1))
        mat[:, K.P_SLIP] = xs[:, 0]
        mat[:, K.P_KS] = xs[:, 1]
        mat[:, K.P_MUS] = np.tan(xs[:, 2])
        mat[:, K.P_MUD] = np.tan(xs[:, 2] - xs[:, 3])
        mat[:, K.P_OMEGA] = xs[:, 4]
        res = simulate_batch(mat, dt=dt, waveforms=True, on_error="flag")
        offset = rng.uniform(0.0, 1.0, len(xs)) * xs[:, 4] / rate[sl]
        seeds = rng.integers(0, 2**31, len(xs))
        _sample_and_featurise(res.theta, res.az, res.n_steps, res.ok, np.ascontiguousarray(xs[:, 4]), rate[sl],
                              noise[sl], offset, seeds, float(base.g), math.pi / base.nL, out[sl],
                              grid_out[sl] if grids else grid_out)
        if progress:
            progress(len(xs))
    return (out, grid_out) if grids else out


def draw_soils(n: int, rng: np.random.Generator, envelope: dict | None = None) -> np.ndarray:
    """``n`` soils uniform over the envelope: ``(n, 3)`` columns kS [N/m], phiS, phiD [rad]."""
    x = draw_envelope(n, rng, envelope)
    return np.column_stack([x[:, 1], x[:, 2], x[:, 2] - x[:, 3]])


__all__ = ["ENVELOPE", "PHID_MIN", "RATE_RANGE", "NOISE_RANGE", "VARIABLES", "draw_envelope", "draw_imu", "draw_soils",
           "simulate_features"]
