"""The feature discrepancy of a rover: a smooth correction of the surrogate's mean features (pure computation).

What a rover's features do that the simulator's do not, as a polynomial
per modelled feature in the tensor Legendre basis of the normalised
``(slip, kS, phiS, dphi)`` (the surrogate's own basis,
:mod:`slipest.inverse.surrogate`)::

    f_rover ~ mu(slip, soil, omega, noise) + D(slip, kS, phiS, dphi)

A term set with degree 0 in the soil variables is a correction that does
not depend on the soil (what a testbed of one or two soils can support); a
term set of low total degree in all four follows an effect that changes
the features differently on different soils (fitted on simulated cycles,
:mod:`slipest.rover.physics`). :func:`fit_discrepancy` is a ridge least
squares fit; :meth:`Discrepancy.evaluate` and :meth:`Discrepancy.on_grid`
evaluate it at points and on the estimator's tensor grid.

Units: slip [-], kS [N/m], phiS, dphi [rad]; ``D`` in the features' units
(:data:`slipest.features.FEATURE_UNITS`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from slipest.inverse.surrogate import contract_slip, legendre_design, legendre_factors

#: The variables of a discrepancy, in order.
VARIABLES = ("slip", "kS", "phiS", "dphi")


def soil_terms(degree: int, slip_degree: int | None = None) -> np.ndarray:
    """Tensor Legendre terms ``(T, 4)`` of total degree at most ``degree`` in :data:`VARIABLES` (and at most
    ``slip_degree`` in slip alone, when given)."""
    out = [e for e in itertools.product(range(degree + 1), repeat=4) if sum(e) <= degree]
    if slip_degree is not None:
        out += [(k, 0, 0, 0) for k in range(degree + 1, slip_degree + 1)]
    out.sort(key=lambda e: (sum(e), tuple(-v for v in e)))
    return np.array(out, dtype=np.int64).reshape(-1, 4)


def slip_terms(degree: int) -> np.ndarray:
    """Terms ``(degree + 1, 4)`` in slip alone: a correction that does not depend on the soil."""
    return np.array([(k, 0, 0, 0) for k in range(degree + 1)], dtype=np.int64).reshape(-1, 4)


@dataclass(frozen=True)
class Discrepancy:
    """``D`` of the module docstring: ``terms`` ``(T, 4)`` Legendre degrees, ``coef`` ``(T, d)`` [feature
    units], the normalisation ``u = (x - center) / halfwidth`` (``(4,)`` each, SI) and the feature names."""

    features: tuple
    terms: np.ndarray
    coef: np.ndarray
    center: np.ndarray
    halfwidth: np.ndarray

    def __post_init__(self):
        t, c = np.asarray(self.terms), np.asarray(self.coef)
        if t.ndim != 2 or t.shape[1] != 4 or (t < 0).any():
            raise ValueError("discrepancy terms must be (T, 4) degrees >= 0")
        if c.shape != (t.shape[0], len(self.features)):
            raise ValueError(f"discrepancy coef {c.shape} does not match {t.shape[0]} terms x "
                             f"{len(self.features)} features")
        if not np.all(np.isfinite(c)):
            raise ValueError("discrepancy has non-finite coefficients")
        if np.shape(self.center) != (4,) or np.shape(self.halfwidth) != (4,) or not np.all(np.asarray(self.halfwidth) > 0):
            raise ValueError("discrepancy center and halfwidth must be 4 values (halfwidth > 0)")

    @classmethod
    def zero(cls, features, center, halfwidth) -> "Discrepancy":
        """No correction."""
        return cls(tuple(features), slip_terms(0), np.zeros((1, len(features))), np.asarray(center, float),
                   np.asarray(halfwidth, float))

    def basis(self, x4) -> np.ndarray:
        """Design matrix ``(n, T)`` at points ``x4`` ``(n, 4)`` (:data:`VARIABLES`, SI)."""
        u = (np.asarray(x4, dtype=float).reshape(-1, 4) - self.center) / self.halfwidth
        return legendre_design(u, self.terms)

    def evaluate(self, x4) -> np.ndarray:
        """``D`` ``(..., d)`` at points ``x4`` ``(..., 4)``."""
        x4 = np.asarray(x4, dtype=float)
        return (self.basis(x4) @ self.coef).reshape(x4.shape[:-1] + (self.coef.shape[1],))

    def factors(self, slip_nodes, kS_levels, phiS_levels, dphi_levels,
                right: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``D`` on a tensor grid as the factors of :func:`~slipest.inverse.surrogate.legendre_factors`
        (``partial`` ``(A, d, nk, nphiS, ndphi)``, ``basis`` ``(K, A)``); ``right``: a ``(d, m)`` matrix ``D``
        is multiplied by (through the coefficients)."""
        coef = self.coef if right is None else self.coef @ right
        return legendre_factors(self.terms, coef, self.center, self.halfwidth,
                                (slip_nodes, kS_levels, phiS_levels, dphi_levels))

    def on_grid(self, slip_nodes, kS_levels, phiS_levels, dphi_levels) -> np.ndarray:
        """``D`` on a tensor grid, ``(nk, nphiS, ndphi, K, d)`` (the layout of
        :meth:`~slipest.inverse.surrogate.FeatureSurrogate.mean_on_grid`)."""
        return contract_slip(*self.factors(slip_nodes, kS_levels, phiS_levels, dphi_levels))

    def plus(self, other: "Discrepancy") -> "Discrepancy":
        """The sum of two discrepancies on the same normalisation (their terms merged)."""
        if tuple(other.features) != tuple(self.features) or not (np.allclose(other.center, self.center)
                                                                  and np.allclose(other.halfwidth, self.halfwidth)):
            raise ValueError("only discrepancies of the same features and normalisation add up")
        rows = {tuple(t): c.copy() for t, c in zip(self.terms.tolist(), self.coef)}
        for t, c in zip(other.terms.tolist(), other.coef):
            rows[tuple(t)] = rows.get(tuple(t), 0.0) + c
        keys = sorted(rows, key=lambda e: (sum(e), tuple(-v for v in e)))
        return Discrepancy(self.features, np.array(keys, dtype=np.int64), np.array([rows[k] for k in keys]),
                           self.center, self.halfwidth)

    def to_dict(self) -> dict:
        return {"variables": list(VARIABLES), "features": list(self.features), "center": self.center.tolist(),
                "halfwidth": self.halfwidth.tolist(), "terms": self.terms.tolist(), "coef": self.coef.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Discrepancy":
        if list(d.get("variables", [])) != list(VARIABLES):
            raise ValueError(f"discrepancy variables {d.get('variables')} are not {list(VARIABLES)}")
        return cls(tuple(d["features"]), np.asarray(d["terms"], dtype=np.int64).reshape(-1, 4),
                   np.asarray(d["coef"], dtype=float).reshape(len(d["terms"]), len(d["features"])),
                   np.asarray(d["center"], dtype=float), np.asarray(d["halfwidth"], dtype=float))


def fit_discrepancy(x4, resid, terms, features, center, halfwidth, ridge: float = 1e-3,
                    weights=None) -> Discrepancy:
    """Least squares ``D`` through residuals ``resid`` ``(n, d)`` [feature units] at points ``x4`` ``(n, 4)``,
    with a ridge ``ridge * n`` on every coefficient (so that what the data do not determine stays 0).
    ``weights``: per-row weights ``(n,)`` (default 1). Rows with a non-finite value are left out."""
    x4 = np.asarray(x4, dtype=float).reshape(-1, 4)
    resid = np.asarray(resid, dtype=float)
    ok = np.all(np.isfinite(x4), axis=1) & np.all(np.isfinite(resid), axis=1)
    w = np.ones(len(x4)) if weights is None else np.asarray(weights, dtype=float)
    ok &= np.isfinite(w) & (w > 0)
    if not ok.any():
        raise ValueError("no finite residual to fit a discrepancy to")
    d0 = Discrepancy(tuple(features), np.asarray(terms, dtype=np.int64), np.zeros((len(terms), resid.shape[1])),
                     np.asarray(center, float), np.asarray(halfwidth, float))
    b = d0.basis(x4[ok])
    sw = np.sqrt(w[ok])[:, None]
    a = (b * sw).T @ (b * sw)
    coef = np.linalg.solve(a + ridge * ok.sum() * np.eye(len(terms)), (b * sw).T @ (resid[ok] * sw))
    return Discrepancy(d0.features, d0.terms, coef, d0.center, d0.halfwidth)


__all__ = ["VARIABLES", "Discrepancy", "fit_discrepancy", "slip_terms", "soil_terms"]
