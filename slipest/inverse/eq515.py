"""Thesis Eq. 5.15 exactly as stated, as a slip inverse (baseline, kept for comparison).

    i = aIV + bIV * Da,   bIV = amu + bmu * dphi,   aIV = cI + cmu * dphi + cK * kS

``Da`` [g] (max minus min of the hub's vertical acceleration over the
feature window), ``dphi = phiS - phiD`` [rad], ``kS`` [N/m], slip ``i`` [-].
The coefficients come from the shipped calibration
(``slipest/data/calibration.json``, section ``eq515``, written by
``tools/calibrate.py``; see :mod:`slipest.calibration`).

Two directions, both closed form:

* :meth:`Eq515Inverse.slip_from_da`: slip from ``Da`` with ``dphi`` and
  ``kS`` known (the thesis's slip estimate);
* :meth:`Eq515Inverse.dphi_from_da`: ``dphi`` from ``Da`` with a reference
  slip and ``kS`` known (the thesis's use of the equation to learn the soil):
  ``dphi = (i - cI - cK kS - amu Da) / (cmu + bmu Da)``.

Uncertainty: the equation carries none of its own; the standard deviation
reported is the calibration's end-to-end slip RMSE of Eq. 5.15 over its
sweep (``rmse_end_to_end``), an honest, soil-independent figure. In this
model that RMSE is large (docs/model.md section 5: the second-level laws do not
hold); the number is reported, not tuned.

:class:`Eq515Tracker` is the recursive use: a 1-state Kalman filter on
``dphi`` fed by :meth:`dphi_from_da` whenever a reference slip comes, used
for the slip of the other cycles.
"""

from __future__ import annotations

import math

import numpy as np

from slipest.cycle_estimator import CycleEstimate, CycleEstimator
from slipest.features import INDEX
from slipest.inverse.base import SlipInverse, Soil


class Eq515Inverse(SlipInverse):
    """Eq. 5.15 with coefficients ``amu, bmu, cI, cmu, cK`` (``cmu``, ``bmu`` [1/rad]-scaled, ``cK`` [m/N]).

    ``slip_std``: standard deviation [-] attached to every slip estimate.
    """

    name = "eq515"
    needs_soil = ("kS", "dphi")
    features = ("delta_a",)

    def __init__(self, amu: float, bmu: float, cI: float, cmu: float, cK: float, slip_std: float):
        vals = dict(amu=amu, bmu=bmu, cI=cI, cmu=cmu, cK=cK, slip_std=slip_std)
        bad = [k for k, v in vals.items()
               if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)]
        if bad:
            raise ValueError(f"Eq. 5.15 coefficient(s) not finite numbers: {', '.join(bad)} (a calibration whose "
                             "Eq. 5.15 could not be fitted: use the default method)")
        if not slip_std > 0:
            raise ValueError(f"slip_std={slip_std} must be > 0")
        self.amu, self.bmu, self.cI, self.cmu, self.cK = (float(v) for v in (amu, bmu, cI, cmu, cK))
        self.slip_std = float(slip_std)

    @classmethod
    def from_calibration(cls, cal: dict | None = None) -> "Eq515Inverse":
        """From a calibration dict (default: the shipped one, :func:`slipest.calibration.load_calibration`)."""
        if cal is None:
            from slipest.calibration import load_calibration

            cal = load_calibration()
        c = cal["eq515"] if "eq515" in cal else cal
        return cls(c["amu"], c["bmu"], c["cI"], c["cmu"], c["cK"], c["rmse_end_to_end"])

    def coefficients(self) -> dict:
        return dict(amu=self.amu, bmu=self.bmu, cI=self.cI, cmu=self.cmu, cK=self.cK)

    def slip_from_da(self, da_g, dphi, kS):
        """Slip [-] from ``Da`` [g], ``dphi`` [rad], ``kS`` [N/m] (Eq. 5.15; not clipped). Broadcasts."""
        da_g, dphi, kS = (np.asarray(v, dtype=float) for v in (da_g, dphi, kS))
        a_iv = self.cI + self.cmu * dphi + self.cK * kS
        b_iv = self.amu + self.bmu * dphi
        return a_iv + b_iv * da_g

    def dphi_from_da(self, da_g, slip, kS):
        """``dphi`` [rad] from ``Da`` [g], a reference slip [-] and ``kS`` [N/m] (Eq. 5.15 solved for dphi).

        NaN where ``cmu + bmu Da`` is 0 (``Da`` carries no information on ``dphi`` there). Broadcasts.
        """
        da_g, slip, kS = (np.asarray(v, dtype=float) for v in (da_g, slip, kS))
        den = self.cmu + self.bmu * da_g
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(den != 0.0, (slip - self.cI - self.cK * kS - self.amu * da_g) / den, np.nan)

    def dphi_std(self, da_g) -> np.ndarray:
        """Standard deviation [rad] of :meth:`dphi_from_da`: ``slip_std / |cmu + bmu Da|`` (inf where 0)."""
        den = np.abs(self.cmu + self.bmu * np.asarray(da_g, dtype=float))
        with np.errstate(divide="ignore"):
            return np.where(den > 0, self.slip_std / den, np.inf)

    def slip(self, features, soil: Soil | None = None) -> tuple[float, float]:
        self.check_soil(soil)
        da = float(np.asarray(features, dtype=float)[INDEX["delta_a"]])
        if not math.isfinite(da):
            return math.nan, math.nan
        return float(self.slip_from_da(da, soil.dphi, soil.kS)), self.slip_std

    def slip_batch(self, features_2d, soil: Soil | None = None):
        self.check_soil(soil)
        da = np.atleast_2d(np.asarray(features_2d, dtype=float))[:, INDEX["delta_a"]]
        s = self.slip_from_da(da, soil.dphi, soil.kS)
        return s, np.where(np.isfinite(s), self.slip_std, np.nan)


class Eq515Tracker(CycleEstimator):
    """The thesis's recursive use of Eq. 5.15: learn ``dphi`` from reference slips, estimate slip from ``Da``.

    ``soil``: ``kS`` [N/m] must be known (Eq. 5.15 cannot learn it alongside
    ``dphi``); with ``dphi`` known it is used as is, else ``dphi`` [rad] is a
    random walk (process noise ``q`` [rad^2] per cycle) in a 1-state
    filter started at ``dphi0`` with standard
    deviation ``dphi0_std`` and updated by :meth:`Eq515Inverse.dphi_from_da`
    whenever a reference slip comes (only with ``use_reference``): a 1-state
    Kalman filter, written out (predict ``P += q``; update ``K = P / (P + r)``,
    ``x += K (z - x)``, ``P = (1 - K)^2 P + K^2 r``, the Joseph form filterpy
    uses; docs/estimator.md says why not filterpy). The slip
    of every cycle is Eq. 5.15 at the current ``dphi``; its std combines the
    equation's RMSE and the ``dphi`` uncertainty through ``bmu Da + cmu``.
    ``model_legs``, ``model_omega`` [rad/s]: the geometry and the one leg
    speed the coefficients were calibrated at; cycles within ``speed_tol``
    (relative) of it are estimated (:class:`~slipest.cycle_estimator.CycleEstimator`'s
    ``omega_range``): Eq. 5.15 knows one speed.
    """

    def __init__(self, inverse: Eq515Inverse, soil: Soil, use_reference: bool = False, dphi0: float = 0.175,
                 dphi0_std: float = 0.1, q: float = 1e-4, model_legs: int = 4, model_omega: float = 0.63,
                 speed_tol: float = 0.1):
        if soil is None or soil.kS is None:
            raise ValueError("method 'eq515' needs the soil's kS (Eq. 5.15 cannot learn it)")
        if soil.dphi is None and not use_reference:
            raise ValueError("method 'eq515' needs the soil's dphi, or use_reference=True to learn it from reference "
                             "slips")
        self.inv = inverse
        self.soil = soil
        self.kS = float(soil.kS)
        self.use_reference = bool(use_reference)
        self.dphi_known = soil.dphi is not None
        self.model_legs = int(model_legs)
        self.model_omega = float(model_omega)
        if not 0.0 < speed_tol < 1.0:
            raise ValueError(f"speed_tol={speed_tol} must be in (0, 1)")
        self.omega_range = (self.model_omega * (1.0 - speed_tol), self.model_omega * (1.0 + speed_tol))
        self._dphi0 = float(soil.dphi if self.dphi_known else dphi0)
        self._dphi0_std = float(dphi0_std)
        self._q = float(q)
        self.reset()

    @classmethod
    def from_calibration(cls, soil: Soil, use_reference: bool = False, calibration: dict | None = None,
                         **options) -> "Eq515Tracker":
        """A tracker with the coefficients and geometry of a calibration dict (default: the shipped one)."""
        if calibration is None:
            from slipest.calibration import load_calibration

            calibration = load_calibration()
        params = calibration.get("model", {}).get("params", {})
        return cls(Eq515Inverse.from_calibration(calibration), soil, use_reference,
                   model_legs=int(params.get("nL", 4)), model_omega=float(params.get("omega", 0.63)), **options)

    def reset(self) -> None:
        #: the filter's state: ``dphi`` [rad] and its variance [rad^2]
        self._x = self._dphi0
        self._p = 0.0 if self.dphi_known else self._dphi0_std**2

    @property
    def dphi(self) -> float:
        return float(self._x)

    @property
    def dphi_std(self) -> float:
        return math.sqrt(max(self._p, 0.0))

    def step(self, da_g: float, slip_ref: float | None = None) -> tuple[float, float, float, float, bool]:
        """One cycle's ``Da`` [g] and optional reference slip [-]: ``(slip, slip_std, dphi, dphi_std, used_reference)``."""
        if not self.dphi_known:
            self._p += self._q  # predict: dphi is a random walk
        dphi, dstd = self.dphi, self.dphi_std
        slip = float(self.inv.slip_from_da(da_g, dphi, self.kS))
        sens = self.inv.cmu + self.inv.bmu * da_g
        slip_std = math.sqrt(self.inv.slip_std**2 + (sens * dstd) ** 2)
        used = False
        if self.use_reference and slip_ref is not None and math.isfinite(slip_ref) and not self.dphi_known:
            z = float(self.inv.dphi_from_da(da_g, slip_ref, self.kS))
            r = float(self.inv.dphi_std(da_g))
            if math.isfinite(z) and math.isfinite(r):
                gain = self._p / (self._p + r * r)
                self._x += gain * (z - self._x)
                self._p = (1.0 - gain) ** 2 * self._p + gain**2 * r * r
                used = True
        return slip, slip_std, self.dphi, self.dphi_std, used

    def update(self, features, slip_ref: float | None = None, widen: float = 1.0) -> CycleEstimate:
        da = float(np.asarray(features, dtype=float)[INDEX["delta_a"]])
        if not math.isfinite(da):
            raise ValueError("non-finite Da: this cycle cannot be estimated")
        slip, slip_std, dphi, dphi_std, used = self.step(da, slip_ref)
        s = self.soil
        phiS, phiS_std = (s.phiS, 0.0) if s.phiS is not None else (math.nan, math.nan)
        phiD, phiD_std = (s.phiD, 0.0) if s.phiD is not None else (math.nan, math.nan)
        return CycleEstimate(slip, slip_std, dphi, dphi_std, self.kS, 0.0, phiS, phiS_std, phiD, phiD_std, math.nan,
                             used)
