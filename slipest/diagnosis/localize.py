"""Where the model misses: the gap split by leg-angle window, by feature and by slip level (pure).

All three work on residuals ``r = y - prediction`` of cycles (``(C, nb)``
[m/s^2], analysis bins of :mod:`slipest.diagnosis.cycles`) and the bin
noise variance ``var`` of :func:`slipest.diagnosis.rank.noise_floor`.

* **Leg-angle windows**: the cycle ``[-pi/nL, pi/nL)`` cut into equal
  windows; each window's gap is ``sqrt(max(0, mean(r^2 - var)))`` over its
  bins (the definition of :mod:`slipest.diagnosis.rank` restricted to the
  window) and its *share* is its part of the total excess squared error
  ``sum(r^2 - var)`` (negative parts counted as 0). Shares sum to 1.
* **Slip levels**: the same per slip level (cycles of equal slip).
* **Features**: the project's per-cycle features (:mod:`slipest.features`:
  ``Da``, onset angle, oscillation frequency, RMS per quarter, ...) of the
  logged cycle and of the model's prediction, both from the bin averages of
  the stance half; per feature the mean difference (data - model), its
  RMS, and ``z = RMS / scale`` with ``scale`` the feature's cycle-to-cycle
  scatter at equal slip (floored, see :data:`FEATURE_FLOORS`); the share
  is ``z^2 / sum z^2``.
"""

from __future__ import annotations

import math

import numpy as np

from slipest import features as F
from slipest.diagnosis.predict import Grid
from slipest.units import G

#: Windows the cycle is cut into for the leg-angle localisation.
N_WINDOWS = 8
#: Features compared (names of :data:`slipest.features.FEATURE_NAMES`).
FEATURES = ("delta_a", "onset", "rice_freq", "rms", "rms_q1", "rms_q2", "rms_q3", "rms_q4", "peak_pos",
            "peak_neg", "energy_q50")
#: Smallest scale of a feature difference, by unit (so that a noise-free feature does not dominate).
FEATURE_FLOORS = {"g": 0.01, "rad": 0.01, "Hz": 0.1, "-": 1.0}


def _shares(excess: np.ndarray) -> np.ndarray:
    pos = np.maximum(np.asarray(excess, dtype=float), 0.0)
    total = pos.sum()
    return pos / total if total > 0 else np.zeros_like(pos)


def by_window(resid: np.ndarray, var: np.ndarray, grid: Grid, n_windows: int = N_WINDOWS) -> list[dict]:
    """Gap [g] and share per leg-angle window (``from``/``to`` [rad] of logged phase)."""
    resid = np.asarray(resid, dtype=float)
    var = np.broadcast_to(var, resid.shape)
    edges = np.linspace(-grid.half, grid.half, n_windows + 1)
    centres = grid.bin_centres
    which = np.clip(np.searchsorted(edges, centres, side="right") - 1, 0, n_windows - 1)
    sums = np.array([np.sum(resid[:, which == w] ** 2 - var[:, which == w]) for w in range(n_windows)])
    counts = np.array([resid[:, which == w].size for w in range(n_windows)])
    share = _shares(sums)
    return [
        {
            "from": float(edges[w]),
            "to": float(edges[w + 1]),
            "gap": math.sqrt(max(sums[w] / counts[w], 0.0)) / G if counts[w] else 0.0,
            "share": float(share[w]),
        }
        for w in range(n_windows)
    ]


def by_slip(resid: np.ndarray, var: np.ndarray, slip: np.ndarray, heldout_levels=()) -> list[dict]:
    """Gap [g] and share per slip level; ``heldout_level``: the level was not fitted at all."""
    resid = np.asarray(resid, dtype=float)
    var = np.broadcast_to(var, resid.shape)
    key = np.round(np.asarray(slip, dtype=float), 6)
    levels = np.unique(key)
    sums = np.array([np.sum(resid[key == s] ** 2 - var[key == s]) for s in levels])
    counts = np.array([resid[key == s].size for s in levels])
    share = _shares(sums)
    held = {round(float(h), 6) for h in heldout_levels}
    return [
        {
            "slip": float(s),
            "cycles": int(np.sum(key == s)),
            "gap": math.sqrt(max(sums[i] / counts[i], 0.0)) / G,
            "share": float(share[i]),
            "heldout_level": round(float(s), 6) in held,
        }
        for i, s in enumerate(levels)
    ]


def stance_features(y: np.ndarray, grid: Grid, omega: float) -> np.ndarray:
    """Features (:data:`FEATURES`, units of :mod:`slipest.features`) of cycles' stance-half bins ``(C, nb)``."""
    half_bins = grid.nb_half
    phase = grid.bin_centres[half_bins:]
    rows = F.features_batch(phase, np.asarray(y, dtype=float)[:, half_bins:], n_legs=grid.n_legs, omega=omega)
    cols = [F.INDEX[n] for n in FEATURES]
    return rows[:, cols]


def by_feature(y: np.ndarray, pred: np.ndarray, slip: np.ndarray, grid: Grid, omega: float) -> list[dict]:
    """Per feature: data and model means, mean difference, RMS difference, z and share (see the module docstring)."""
    fd = stance_features(y, grid, omega)
    fm = stance_features(pred, grid, omega)
    diff = fd - fm
    key = np.round(np.asarray(slip, dtype=float), 6)
    units = [F.FEATURE_UNITS[F.INDEX[n]] for n in FEATURES]
    out = []
    z = np.zeros(len(FEATURES))
    for j, name in enumerate(FEATURES):
        col = fd[:, j]
        ss, dof = 0.0, 0
        for s in np.unique(key):
            v = col[key == s]
            v = v[np.isfinite(v)]
            if len(v) >= 2:
                ss += float(np.sum((v - v.mean()) ** 2))
                dof += len(v) - 1
        scatter = math.sqrt(ss / dof) if dof else 0.0
        scale = max(scatter, FEATURE_FLOORS.get(units[j], 0.01))
        d = diff[:, j][np.isfinite(diff[:, j])]
        rms = float(np.sqrt(np.mean(d**2))) if d.size else float("nan")
        z[j] = rms / scale if d.size else 0.0
        out.append(
            {
                "feature": name,
                "unit": units[j],
                "data": float(np.nanmean(fd[:, j])),
                "model": float(np.nanmean(fm[:, j])),
                "mean_diff": float(np.mean(d)) if d.size else float("nan"),
                "rms_diff": rms,
                "scale": scale,
                "z": float(z[j]),
            }
        )
    share = _shares(z**2)
    for item, s in zip(out, share):
        item["share"] = float(s)
    return out
