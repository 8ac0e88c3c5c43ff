"""``speed_ripple``: leg angular speed not constant over a cycle (physics effect)."""

from __future__ import annotations

import math

import numpy as np

from slipest.model import kernel as K
from slipest.model.effects.base import FitParam, ParamSpec, PhysicsEffect


class SpeedRippleEffect(PhysicsEffect):
    """Drive/gear ripple ``h`` times per leg cycle: ``omega(theta) = omega0 (1 + A sin(h nL theta + phase))``.

    Fitted as ``(ripple_c, ripple_s) = (A cos phase, A sin phase)`` (no
    wrap-around in the phase, smooth through ``A = 0``). The log's mean leg
    speed ``omega`` (whole cycles) fixes the drive's ``omega0 = omega /
    sqrt(1 - A^2)`` (the cycle period of the law). The encoder shows the
    ripple directly: its speed per phase bin seeds the fit.
    """

    name = "speed_ripple"
    equation = "omega(theta) = omega0 (1 + A sin(h nL theta + phase))"
    description = "leg angular speed not constant over the cycle (drive/gear ripple h times per leg cycle)"
    params = (
        ParamSpec("amplitude", "-", 0.2, (0.0, 0.3), (0.15, 0.3), (0.0, 0.9), "relative ripple amplitude A",
                  neutral=0.0),
        ParamSpec("phase", "rad", 0.0, (-math.pi, math.pi), (-math.pi, math.pi), (-2 * math.pi, 2 * math.pi),
                  "ripple phase"),
        ParamSpec("harmonic", "-", 1, (1, 4), (1, 1), (1, 8),
                  "ripples per leg cycle h (an integer: the ripple repeats every leg cycle)", integer=True),
    )
    fields = (("amplitude", "ripple_amp", K.P_RIPPLE_A), ("phase", "ripple_phase", K.P_RIPPLE_PH),
              ("harmonic", "ripple_harmonic", K.P_RIPPLE_H))
    fit_params = (
        FitParam("ripple_c", "-", -0.35, 0.35, off=0.0),
        FitParam("ripple_s", "-", -0.35, 0.35, off=0.0),
    )

    def catalog_values(self, fitted, soil, geometry):
        c, s = fitted["ripple_c"], fitted["ripple_s"]
        return {"amplitude": np.hypot(c, s), "phase": np.arctan2(s, c), "harmonic": np.ones_like(np.asarray(c))}

    def drive_speed(self, omega, values):
        return omega / np.sqrt(1.0 - values["amplitude"] ** 2)  # same mean speed (cycle period) as the log

    def rigid(self, grid, leg, omega, values):
        """``-l (w^2 cos phi + w w' sin phi)`` under the drive law, ``l = leg (P,)``, mean speeds ``omega (G,)``."""
        a = values["amplitude"]
        w0 = self.drive_speed(np.asarray(omega, dtype=float)[None, :], {"amplitude": a[:, None]})[:, :, None]
        phi = grid.rigid_psi
        a = np.asarray(a, dtype=float)[:, None, None]
        k = grid.n_legs * np.asarray(values["harmonic"], dtype=float)[:, None, None]  # ripples per radian
        arg = k * phi[None, None, :] + np.asarray(values["phase"], dtype=float)[:, None, None]
        w = w0 * (1.0 + a * np.sin(arg))
        dw = w0 * a * k * np.cos(arg)
        leg = np.asarray(leg, dtype=float)[:, None, None]
        return -leg * (np.cos(phi)[None, None, :] * w * w + np.sin(phi)[None, None, :] * w * dw)

    def signature_seeds(self, data):
        """The encoder's leg speed per phase bin fitted by ``w0 (1 + c sin(nL phi) + s cos(nL phi))``.

        Linear least squares; ``ripple_c = A cos(phase) = c``, ``ripple_s = A sin(phase) = s``.
        """
        grid = data.grid
        phi = grid.bin_centres
        w = np.nanmean(data.speed, axis=0)
        ok = np.isfinite(w)
        if ok.sum() < 10:
            return []
        X = np.stack([np.ones(ok.sum()), np.sin(grid.n_legs * phi[ok]), np.cos(grid.n_legs * phi[ok])], axis=1)
        coef, *_ = np.linalg.lstsq(X, w[ok], rcond=None)
        if not coef[0] > 0:
            return []
        return [{"ripple_c": float(coef[1] / coef[0]), "ripple_s": float(coef[2] / coef[0])}]
