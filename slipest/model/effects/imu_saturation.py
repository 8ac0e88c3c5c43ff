"""``imu_saturation``: accelerometer full-scale clipping (sampled sensor effect)."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from slipest.model.effects.base import Effect, FitParam, ParamSpec


class Saturation:
    """Full-scale clipping at ``+-full_scale`` [m/s^2] ("sampled" stage)."""

    domain = "sampled"

    def __init__(self, full_scale: float):
        self.full_scale = float(full_scale)

    def apply(self, t, az, theta, rng):
        return np.clip(az, -self.full_scale, self.full_scale), theta


def expected_clip(u: np.ndarray, full_scale, sigma: float) -> np.ndarray:
    """Mean of ``clip(u + n, -FS, FS)`` for Gaussian noise ``n`` of standard deviation ``sigma``.

    The logged samples are clipped after the noise is added, so a bin average
    near the full scale sits below it; with ``d = FS - u``:
    ``E[min(u + n, FS)] = u + d (1 - Phi(d/s)) - s phi(d/s)`` (same at ``-FS``).
    """
    if sigma <= 0:
        return np.clip(u, -full_scale, full_scale)
    d_hi = (full_scale - u) / sigma
    d_lo = (u + full_scale) / sigma
    hi = sigma * (d_hi * ndtr(-d_hi) - np.exp(-0.5 * d_hi**2) / math.sqrt(2 * math.pi))
    lo = sigma * (d_lo * ndtr(-d_lo) - np.exp(-0.5 * d_lo**2) / math.sqrt(2 * math.pi))
    return u + hi - lo


class ImuSaturationEffect(Effect):
    """Accelerometer full-scale clipping of the specific force (gravity included): ``az = clip(az, -FS, FS)``.

    Commercial parts have 2-16 g (19.6-157 m/s^2); the hub's specific force
    peaks at 1.4-1.8 g, so only a low range clips it (the moderate range
    stands for an analog front end or a +-2 g part mounted with an offset).
    The clipping acts after the noise and the bias, so the prediction takes
    the noise's expected effect on a bin average and the bias (fitted by the
    nominal model) into account. Clipped tops are flat: the largest bin
    average seeds the fit.
    """

    name = "imu_saturation"
    kind = "sampled"
    equation = "az = clip(az, -FS, +FS)"
    description = "accelerometer full-scale clipping of the specific force (gravity included)"
    params = (
        ParamSpec("full_scale", "m/s^2", 12.5, (19.6, 160.0), (11.5, 13.5), (0.1, 1e4),
                  "full-scale range FS (commercial parts: 2-16 g = 19.6-157 m/s^2; the moderate range "
                  "stands for an analog front end or a +-2 g part mounted with an offset)"),
    )
    fit_params = (FitParam("full_scale", "m/s^2", 10.0, 25.0, off=25.0),)
    bias_inside = True

    def stage(self, values):
        return Saturation(values["full_scale"])

    def sense(self, x, values, ctx):
        fs = values["full_scale"][:, None, None]
        return ctx.bin_average(expected_clip(x + ctx.bias0, fs, ctx.noise_sigma) - ctx.bias0)

    def signature_seeds(self, data):
        """The largest bin average (clipped tops are flat)."""
        return [{"full_scale": float(np.max(data.y))}]
