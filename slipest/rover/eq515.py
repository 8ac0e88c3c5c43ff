"""Thesis Eq. 5.15 refitted on a rover's testbed logs: the thesis's calibrated method (pure computation).

Eq. 5.15 (:mod:`slipest.inverse.eq515`)::

    i = aIV + bIV * Da,   bIV = amu + bmu * dphi,   aIV = cI + cmu * dphi + cK * kS

needs, per cycle, ``Da`` [g] (the feature ``delta_a``), the slip [-] and
the soil's ``dphi`` [rad] and ``kS`` [N/m]. On a testbed the slip is known
and the soil is the one the calibration estimated for each log
(:func:`slipest.rover.fit.log_soil`). With at least four logs (soils) the
equation is fitted exactly as the thesis states it
(:func:`slipest.calibration.fit_eq515`). With fewer, the second-level
planes are not determined (two points for a three-coefficient plane): each
log's line ``i = aIV + bIV Da`` is fitted, the shipped calibration's
slopes in ``dphi`` and ``kS`` (``bmu``, ``cmu``, ``cK``) are kept and the
intercepts ``amu``, ``cI`` are refitted to the lines (least squares). The
result is a calibration dict that
:meth:`slipest.inverse.eq515.Eq515Tracker.from_calibration` reads: the
coefficients, ``rmse_end_to_end`` (the equation's slip RMSE over the
testbed cycles, the standard deviation it reports) and the leg speed and
legs it was fitted at (it knows one speed).
"""

from __future__ import annotations

import numpy as np

from slipest.calibration import fit_eq515, linear_fit, load_calibration, r2_score, rmse
from slipest.features import INDEX

#: Logs (soils) needed to fit every coefficient of Eq. 5.15.
FULL_FIT_SOILS = 4


def refit_eq515(logs, soils, omega: float, n_legs: int, shipped: dict | None = None) -> dict:
    """The Eq. 5.15 calibration of the testbed ``logs`` (:class:`~slipest.rover.testbed.TestbedLog`) on their
    estimated ``soils`` (:class:`~slipest.rover.fit.LogSoil`), at leg speed ``omega`` [rad/s] and ``n_legs``
    legs (see the module docstring). ``shipped``: the calibration whose slopes a partial fit keeps (default:
    the shipped one)."""
    da = np.concatenate([lg.features[:, INDEX["delta_a"]] for lg in logs])
    slip = np.concatenate([lg.slip for lg in logs])
    kS = np.concatenate([np.full(len(lg), s.kS) for lg, s in zip(logs, soils)])
    phiS = np.concatenate([np.full(len(lg), s.phiS) for lg, s in zip(logs, soils)])
    dphi = np.concatenate([np.full(len(lg), s.dphi) for lg, s in zip(logs, soils)])
    ok = np.isfinite(da) & np.isfinite(slip)
    distinct = {(round(s.kS, 6), round(s.phiS, 6), round(s.dphi, 6)) for s in soils}
    if len(distinct) >= FULL_FIT_SOILS:
        fit = fit_eq515(slip[ok], kS[ok], phiS[ok], phiS[ok] - dphi[ok], da[ok])
        coef = fit.coefficients()
        how = "Eq. 5.15 fitted as the thesis states it"
    else:
        c0 = (shipped or load_calibration())["eq515"]
        a_iv, b_iv, d_s, k_s = [], [], [], []
        for lg, s in zip(logs, soils):
            m = np.isfinite(lg.features[:, INDEX["delta_a"]])
            a, b, _ = linear_fit(lg.features[m, INDEX["delta_a"]], lg.slip[m])
            a_iv.append(a)
            b_iv.append(b)
            d_s.append(s.dphi)
            k_s.append(s.kS)
        a_iv, b_iv, d_s, k_s = (np.array(v) for v in (a_iv, b_iv, d_s, k_s))
        coef = {"bmu": float(c0["bmu"]), "cmu": float(c0["cmu"]), "cK": float(c0["cK"]),
                "amu": float(np.mean(b_iv - c0["bmu"] * d_s)),
                "cI": float(np.mean(a_iv - c0["cmu"] * d_s - c0["cK"] * k_s))}
        how = (f"{len(distinct)} soil(s): per-log lines fitted, the shipped slopes bmu, cmu, cK kept, amu and cI "
               "refitted (Eq. 5.15's planes need 4 soils)")
    pred = coef["cI"] + coef["cmu"] * dphi + coef["cK"] * kS + (coef["amu"] + coef["bmu"] * dphi) * da
    return {
        "eq515": {**{k: float(v) for k, v in coef.items()}, "rmse_end_to_end": rmse(slip[ok], pred[ok]),
                  "r2_end_to_end": r2_score(slip[ok], pred[ok]), "how": how, "n_cycles": int(ok.sum()),
                  "n_soils": len(distinct)},
        "model": {"params": {"nL": int(n_legs), "omega": float(omega)}},
    }


__all__ = ["FULL_FIT_SOILS", "refit_eq515"]
