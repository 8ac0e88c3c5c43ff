"""``stribeck``: speed-dependent dynamic friction of the sliding foot (physics effect)."""

from __future__ import annotations

from slipest.model import kernel as K
from slipest.model.effects.base import FitParam, ParamSpec, PhysicsEffect


class StribeckEffect(PhysicsEffect):
    """Stribeck curve with a viscous term: ``mu(v) = muD + (muS - muD) exp(-(|v|/vs)^delta)``.

    The foot's friction force is ``mu(v) FN sgn(v) + viscous v``. No value
    of ``vs`` is neutral: ``mu(0) = muS`` changes the break-away even for a
    tiny ``vs`` (``vs = 0`` is the nominal constant ``muD``).

    The fit searches at finer integration steps (:attr:`search_steps`): the
    curve's velocity scale (~0.01 m/s) is crossed in one step of the foot's
    acceleration at 4e-4 s (waveform error 0.01-0.04 g at the true
    parameters, against 0.002-0.005 g at 2e-4 s).
    """

    name = "stribeck"
    equation = "mu(v) = muD + (muS - muD) exp(-(|v|/vs)^delta);  F = mu(v) FN sgn(v) + sigma_v v"
    description = ("speed-dependent dynamic friction of the sliding foot (Stribeck curve) with an optional "
                   "viscous term")
    params = (
        ParamSpec("vs", "m/s", 0.03, (0.001, 0.1), (0.01, 0.05), (0.0, 10.0),
                  "Stribeck velocity (0: constant muD)", neutral=0.0, log_scale=True),
        ParamSpec("delta", "-", 2.0, (0.5, 2.0), (1.0, 2.0), (0.1, 5.0), "Stribeck exponent"),
        ParamSpec("viscous", "N s/m", 0.0, (0.0, 5.0), (0.0, 1.0), (0.0, 1e4),
                  "viscous friction coefficient sigma_v", neutral=0.0),
    )
    fields = (("vs", "stribeck_vs", K.P_VS), ("delta", "stribeck_exp", K.P_SEXP), ("viscous", "viscous", K.P_VISC))
    fit_params = (
        FitParam("vs", "m/s", 0.001, 0.2, log=True, off=0.02),  # nothing is neutral; a mid-range start
        FitParam("delta", "-", 0.5, 3.0, off=2.0),
        FitParam("viscous", "N s/m", 0.0, 6.0, off=0.0),
    )
    search_steps = (2e-4, 2e-4)
