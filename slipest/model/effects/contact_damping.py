"""``contact_damping``: Hunt-Crossley damping of the leg/soil contact (physics effect)."""

from __future__ import annotations

from slipest.model import kernel as K
from slipest.model.effects.base import FitParam, ParamSpec, PhysicsEffect


class ContactDampingEffect(PhysicsEffect):
    """Hunt-Crossley damping that thesis Eq. 5.10 drops: ``FS = kS d + b_hc d^n_hc d'``.

    ``d`` is the compression [m], ``FS`` is clamped at ``>= 0`` (no
    adhesion). The damping it adds near the static sinkage
    ``d0 = MH g / kS`` is ``c = b_hc d0^n_hc`` [N s/m] (about 3 N s/m at
    ``b_hc = 300``, a damping ratio of ~5% on the hub). The moderate range of
    ``b_hc`` is for ``n_hc = 1``.

    Fitted as ``(c_hc, n_hc)``: ``c_hc = b_hc d0^n_hc`` [N s/m] at the
    fitted soil's static sinkage is better conditioned than ``b_hc``, whose
    scale depends on ``n_hc``.
    """

    name = "contact_damping"
    equation = "FS = kS d + b_hc d^n_hc d'  (clamped FS >= 0)"
    description = ("Hunt-Crossley damping of the leg/soil contact that thesis Eq. 5.10 drops "
                   "(bHC > 0; nHC = 1 is damping proportional to the compression, 1.5 the Hertzian value)")
    params = (
        ParamSpec("b_hc", "N s/m^(1+n_hc)", 300.0, (0.0, 2000.0), (150.0, 600.0), (0.0, 1e7),
                  "Hunt-Crossley damping coefficient; c = b_hc d0^n_hc [N s/m] at the static sinkage d0 = MH g/kS",
                  neutral=0.0),
        ParamSpec("n_hc", "-", 1.0, (1.0, 1.5), (1.0, 1.0), (0.0, 3.0),
                  "Hunt-Crossley exponent (the moderate range of b_hc is for n_hc = 1)"),
    )
    fields = (("b_hc", "b_hc", K.P_BHC), ("n_hc", "n_hc", K.P_NHC))
    fit_params = (
        FitParam("c_hc", "N s/m", 0.0, 12.0, off=0.0),
        FitParam("n_hc", "-", 0.8, 2.0, off=1.0),
    )

    def catalog_values(self, fitted, soil, geometry):
        d0 = geometry.MH * geometry.g / soil["kS"]
        return {"b_hc": fitted["c_hc"] / d0 ** fitted["n_hc"], "n_hc": fitted["n_hc"]}
