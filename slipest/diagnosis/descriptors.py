"""Phase-insensitive descriptors of binned cycles: the smooth first-stage objective of the fit.

The waveform residual is rugged in the soil parameters (a small change of
``kS`` or ``phiS`` shifts the stick-slip oscillation's phase); these
summaries change smoothly when an oscillation's phase drifts
(:func:`descriptors`). Pure numpy.
"""

from __future__ import annotations

import numpy as np

from slipest.diagnosis.predict import Grid

#: Scales [g, g, g/rad, rad, g, rad] of the descriptor groups (window means, window RMS, window RMS of
#: the slope, stance energy quantiles, stance extremes, onset) in the search's first stage.
DESCRIPTOR_SCALES = (0.01, 0.02, 1.0, 0.02, 0.03, 0.01)
#: Threshold of the onset descriptor: deviation from the stick level [g].
ONSET_G = 0.03
#: Windows of the cycle over which the descriptors are taken.
DESCRIPTOR_WINDOWS = 10


def descriptors(y: np.ndarray, grid: Grid, g: float = 9.81) -> np.ndarray:
    """Phase-insensitive summary of cycles ``y (..., nb)`` [m/s^2] -> ``(..., K)``, each term scaled to ~1.

    Per window of the cycle (:data:`DESCRIPTOR_WINDOWS`): the mean, the RMS
    about it and the RMS of the slope d az/d phi (amplitude times
    frequency); over the stance half: the phases by which 10/25/50/75/90 %
    of the energy about the stick level has accumulated, and the extremes
    above/below the stick level, and the onset (first phase where the
    signal leaves the stick level by :data:`ONSET_G`, interpolated between
    bins). Signals are smoothed over 5 bins first.
    Unlike the waveform itself these change smoothly when an oscillation's
    phase drifts, which makes them a good first-stage objective.
    """
    nb = grid.nb
    dphi = 2 * grid.half / nb
    k = 5
    a = y / g
    pad = np.concatenate([np.repeat(a[..., :1], k // 2, -1), a, np.repeat(a[..., -1:], k // 2, -1)], axis=-1)
    c = np.cumsum(pad, axis=-1)
    c = np.concatenate([np.zeros(c.shape[:-1] + (1,)), c], axis=-1)
    a = (c[..., k:] - c[..., :-k]) / k
    nw = DESCRIPTOR_WINDOWS
    w = a.reshape(a.shape[:-1] + (nw, nb // nw))
    mean = w.mean(-1)
    rms = np.sqrt(np.mean((w - mean[..., None]) ** 2, -1))
    d = np.diff(a, axis=-1, append=a[..., -1:]) / dphi
    rmsd = np.sqrt(np.mean(d.reshape(d.shape[:-1] + (nw, nb // nw)) ** 2, -1))
    st = a[..., nb // 2 :]
    stick = st[..., :5].mean(-1)
    e = np.cumsum((st - stick[..., None]) ** 2, axis=-1)
    e = e / np.maximum(e[..., -1:], 1e-12)
    qs = np.stack([np.sum(e < q, axis=-1) * dphi for q in (0.1, 0.25, 0.5, 0.75, 0.9)], -1)
    ext = np.stack([st.max(-1) - stick, stick - st.min(-1)], -1)
    # onset: first phase where |a - stick| exceeds ONSET_G, interpolated between bins (pi/nL: never)
    dev = np.abs(st - stick[..., None])
    above = dev > ONSET_G
    first = np.where(above.any(-1), np.argmax(above, axis=-1), st.shape[-1])
    j = np.clip(first, 1, st.shape[-1] - 1)
    d1 = np.take_along_axis(dev, j[..., None], -1)[..., 0]
    d0 = np.take_along_axis(dev, (j - 1)[..., None], -1)[..., 0]
    frac = np.clip((ONSET_G - d0) / np.maximum(d1 - d0, 1e-12), 0.0, 1.0)
    onset = np.where(first >= st.shape[-1], grid.half, (j - 1 + frac + 0.5) * dphi)
    s = DESCRIPTOR_SCALES
    return np.concatenate([mean / s[0], rms / s[1], rmsd / s[2], qs / s[3], ext / s[4], onset[..., None] / s[5]], -1)
