"""One cycle's slip by Bayes on the feature surrogate, with the soil known or not (pure computation).

The measurement model is :class:`~slipest.inverse.surrogate.FeatureSurrogate`:
``f ~ N(mu(slip, soil, omega, noise_smooth), R(omega, noise_smooth))``, the leg
speed ``omega`` [rad/s] and the smoothed noise ``noise_smooth`` [g] read off
the feature row itself. With the soil complete (kS, phiS, phiD) slip is
inverted on a fine slip grid (0-0.55 by 0.0025, prior flat on 0-0.5); else it
is marginalised over the soil grid (:class:`~slipest.inverse.grid.SoilGrid`,
uniform over its cells, restricted to the known parts when some are given).
:mod:`slipest.estimator` does the same recursively, learning the soil over
cycles. Units: slip [-], kS [N/m], phiS, phiD, dphi [rad].
"""

from __future__ import annotations

import math

import numpy as np

from slipest.features import INDEX
from slipest.inverse.base import SlipInverse, Soil
from slipest.inverse.grid import SLIP_NODES, SoilGrid, grid_tables, slip_prior
from slipest.inverse.grid_kernels import grid_loglik, marginal_from_rows, node_moments, select_cells, whiten_into
from slipest.inverse.surrogate import FeatureSurrogate, load_inverse_model

_OMEGA = INDEX["omega"]
_NOISE_SMOOTH = INDEX["noise_smooth"]
#: Fine slip grid of the soil-known inversion [-].
FINE_SLIP = np.round(np.arange(0.0, 0.5501, 0.0025), 6)


class FeatureInverse(SlipInverse):
    """Slip [-] and its standard deviation from one feature row (see the module docstring)."""

    name = "surrogate"
    needs_soil = ()

    def __init__(self, model: FeatureSurrogate | None = None, grid: SoilGrid | None = None):
        self.model = model or load_inverse_model()
        self.features = self.model.features
        self.grid = grid or SoilGrid.default()
        self._cols = np.ascontiguousarray(self.model.columns, dtype=np.int64)
        self._lp_fine = slip_prior(FINE_SLIP)

    @staticmethod
    def conditions(features) -> tuple[float, float]:
        """The leg speed [rad/s] and smoothed noise [g] a feature row was measured at."""
        f = np.asarray(features, dtype=float)
        return float(f[_OMEGA]), float(f[_NOISE_SMOOTH])

    def slip_known_soil(self, features, kS, phiS, phiD, scale: float = 1.0) -> tuple[float, float]:
        """Posterior mean and std of slip [-] on a known soil (fine slip grid; the std times the model's
        ``interval_scale``); ``scale``: the likelihood's exponent (tempering). NaN when a modelled feature is
        not finite. No misfit test: :meth:`known_soil_posterior` with ``fit_level`` inf."""
        m, sd, _, _ = self.known_soil_posterior(features, kS, phiS, phiD, scale)
        return m, sd

    def known_soil_posterior(self, features, kS, phiS, phiD, scale: float = 1.0, fit_level: float = math.inf,
                             floor: float = 1.0) -> tuple[float, float, float, float]:
        """``(mean, std, best, misfit)`` of slip [-] on a known soil, as :meth:`slip_known_soil`, with the
        misfit test of the grid path (:func:`~slipest.inverse.grid_kernels.grid_loglik`): ``best`` is the
        smallest squared whitened distance over the slips; above ``fit_level`` the cycle's ``misfit`` is
        ``best / fit_level`` (else 1), and the likelihood's exponent is divided by ``max(misfit, floor)``.
        All NaN but ``misfit`` 1 when a modelled feature is not finite."""
        f = self.model.observe(features)
        if not np.all(np.isfinite(f)):
            return math.nan, math.nan, math.nan, 1.0
        omega, sig = self.conditions(features)
        x = np.empty((FINE_SLIP.size, 6))
        x[:, 0] = FINE_SLIP
        x[:, 1:] = (kS, phiS, phiS - phiD, omega, sig)
        r = f - self.model.mean(x)
        ri = np.linalg.inv(self.model.cov(omega, sig))
        d2 = np.einsum("ij,jk,ik->i", r, ri, r)
        best = float(d2.min())
        misfit = best / fit_level if best > fit_level else 1.0
        ll = -0.5 * scale / max(misfit, floor) * d2 + self._lp_fine
        p = np.exp(ll - ll.max())
        m, sd = node_moments(p, FINE_SLIP, 0.0025**2 / 12)
        return m, sd * self.model.interval_scale, best, misfit

    def soil_logprior(self, soil: Soil | None) -> np.ndarray:
        """Log prior over the grid cells: uniform, restricted (Gaussian, one grid step wide) to known soil parts."""
        cells = self.grid.cells()
        lp = np.zeros(cells.shape[0])
        if soil is None:
            return lp
        step = self.grid.steps()
        dphi_step = step[2]
        if soil.kS is not None:
            lp += -0.5 * ((cells[:, 0] - soil.kS) / step[0]) ** 2
        if soil.phiS is not None:
            lp += -0.5 * ((cells[:, 1] - soil.phiS) / step[1]) ** 2
        if soil.dphi is not None:
            lp += -0.5 * ((cells[:, 1] - cells[:, 2] - soil.dphi) / dphi_step) ** 2
        elif soil.phiD is not None:
            lp += -0.5 * ((cells[:, 2] - soil.phiD) / step[1]) ** 2
        return lp - lp.max()

    def slip(self, features, soil: Soil | None = None) -> tuple[float, float]:
        f = np.asarray(features, dtype=float)
        if not np.all(np.isfinite(self.model.observe(f))):
            return math.nan, math.nan
        if soil is not None and soil.complete:
            return self.slip_known_soil(f, soil.kS, soil.phiS, soil.phiD)
        table = grid_tables(self.model, self.grid).get(*self.conditions(f))
        tc = table.columnar
        _, k, s = tc.shape
        fw = np.zeros(tc.shape[0], dtype=np.float32)
        whiten_into(f, self._cols, table.whitener, fw)
        dmat = np.empty((k, s), dtype=np.float32)
        lc = np.empty(s)
        grid_loglik(tc, table.step, fw, slip_prior(SLIP_NODES).astype(np.float32), 1.0, 1.0, np.inf, dmat, lc,
                    np.empty((2, s), dtype=np.float32))
        sel = np.empty(s, dtype=np.int64)
        base = np.empty(s, dtype=np.float32)
        n = select_cells(self.soil_logprior(soil), lc, 20.0, sel, base)
        ps = np.zeros(k)
        marginal_from_rows(dmat, sel, base, n, ps)
        m, sd = node_moments(ps, SLIP_NODES, 0.01**2 / 12)
        return m, sd * self.model.interval_scale


__all__ = ["FINE_SLIP", "FeatureInverse"]
