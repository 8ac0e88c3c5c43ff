"""``speed_ripple``: leg angular speed not constant over a cycle (physics effect)."""

from __future__ import annotations

import math

import numpy as np

from slipest.model import kernel as K
from slipest.model.effects.base import FitParam, ParamSpec, PhysicsEffect


class SpeedRippleEffect(PhysicsEffect):
    """Drive/gear ripple ``h`` times per leg cycle: ``omega(theta) = omega0 (1 + A sin(h nL theta + phase))``.

    ``h`` is an integer (the ripple repeats every leg cycle, so every cycle
    at one slip looks the same). Fitted as ``(ripple_c, ripple_s) = (A cos
    phase, A sin phase)`` (no wrap-around in the phase, smooth through
    ``A = 0``) and the harmonic ``h`` 1-4 as a categorical parameter (one
    search instance per value). The log's mean leg speed ``omega`` (whole
    cycles) fixes the drive's ``omega0 = omega / sqrt(1 - A^2)`` (the cycle
    period of the law, for any integer ``h``). The encoder shows the ripple
    directly: its speed per phase bin seeds the fit, harmonic included.
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
        FitParam("harmonic", "-", 1, 4, integer=True, choices=(1, 2, 3, 4), off=1),
    )

    def catalog_values(self, fitted, soil, geometry):
        c, s = fitted["ripple_c"], fitted["ripple_s"]
        return {"amplitude": np.hypot(c, s), "phase": np.arctan2(s, c), "harmonic": fitted["harmonic"]}

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
        """The encoder's relative leg speed per phase bin fitted by ``1 + c sin(k phi) + s cos(k phi)``, ``k = h nL``.

        Each cycle's speed over its mean, averaged over the cycles; linear
        least squares with every fitted harmonic's pair at once; the
        harmonic with the largest amplitude ``hypot(c, s)`` gives the seed
        ``ripple_c = c``, ``ripple_s = s``, ``harmonic = h``.
        """
        grid = data.grid
        phi = grid.bin_centres
        omega = data.cycles.omega[data.idx]
        w = np.nanmean(data.speed / omega[:, None], axis=0)
        ok = np.isfinite(w)
        harmonics = self.fit_params[2].choices
        if ok.sum() < 4 * len(harmonics) + 2:
            return []
        cols = [np.ones(ok.sum())]
        for h in harmonics:
            cols += [np.sin(h * grid.n_legs * phi[ok]), np.cos(h * grid.n_legs * phi[ok])]
        coef, *_ = np.linalg.lstsq(np.stack(cols, axis=1), w[ok], rcond=None)
        if not coef[0] > 0:
            return []
        pairs = coef[1:].reshape(-1, 2) / coef[0]
        j = int(np.argmax(np.hypot(pairs[:, 0], pairs[:, 1])))
        return [{"ripple_c": float(pairs[j, 0]), "ripple_s": float(pairs[j, 1]), "harmonic": int(harmonics[j])}]
