"""Fitting a rover model to testbed logs: each log's soil, the residuals, the soil-free discrepancy, the extra covariance, and blind scores (pure computation).

Each testbed log is on its own unknown soil; its cycles' slips are known.

* :func:`log_soil`: the soil cell of the estimator's grid that explains a
  log's cycles best at their known slips (maximum likelihood over the
  grid, the model's mean on the grid at the log's median leg speed and
  noise);
* :func:`log_residuals`: each cycle's features minus the model's mean at
  its slip, that soil, its leg speed and noise;
* :func:`fit_testbed_discrepancy`: a correction in slip alone (the same on
  every soil: two or three testbed soils cannot say how it changes with the
  soil), fitted jointly with the logs' soils (alternating: soils given the
  correction, the correction given the soils);
* :func:`whitened_sq`: the cycles' squared whitened residuals (their mean
  per feature says by how much the covariance must grow);
* :func:`blind_score`: the estimator run over a log as on a drive (soil
  unknown, reference ignored): slip RMSE and 95 % interval coverage from
  the ``start``-th cycle, what the calibration is judged by.

Units: slip [-], kS [N/m], phiS, dphi [rad]; features in their units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from slipest.features import INDEX
from slipest.inverse.grid import SoilGrid
from slipest.inverse.surrogate import whitener
from slipest.rover.discrepancy import Discrepancy, fit_discrepancy, slip_terms
from slipest.rover.testbed import TestbedLog

#: Slips are rounded to this for the grid search [-] (a testbed's levels stay distinct).
SLIP_ROUND = 0.005


@dataclass(frozen=True)
class LogSoil:
    """A log's best soil cell: kS [N/m], phiS, dphi [rad], and the log-likelihood of its cycles there."""

    kS: float
    phiS: float
    dphi: float
    loglik: float

    def as_dict(self) -> dict:
        return {"kS": self.kS, "phiS": self.phiS, "phiD": self.phiS - self.dphi, "dphi": self.dphi}


def log_soil(model, log: TestbedLog, grid: SoilGrid | None = None, keep=None) -> LogSoil:
    """The grid cell maximising the likelihood of the log's cycles (``keep``: a subset, boolean) at their
    known slips under ``model`` (:class:`~slipest.inverse.surrogate.FeatureSurrogate` or a rover model)."""
    g = grid or SoilGrid.default()
    lg = log if keep is None else log.subset(keep)
    s = np.round(lg.slip / SLIP_ROUND) * SLIP_ROUND
    levels, inv = np.unique(s, return_inverse=True)
    mu = model.mean_on_grid(levels, g.kS, g.phiS, g.dphi, lg.omega, lg.noise_smooth)[g.mask]  # (S, L, d)
    w = whitener(model.cov(lg.omega, lg.noise_smooth))
    f = model.observe(lg.features)
    ll = np.zeros(mu.shape[0])
    mw = mu @ w  # (S, L, d)
    fw = f @ w  # (n, d)
    for j in range(len(levels)):
        rows = fw[inv == j]  # (m, d)
        diff = rows[None, :, :] - mw[:, j, None, :]
        ll -= 0.5 * np.einsum("smd,smd->s", diff, diff)
    best = int(np.argmax(ll))
    cell = g.cells()[best]
    return LogSoil(float(cell[0]), float(cell[1]), float(cell[1] - cell[2]), float(ll[best]))


def log_points(log: TestbedLog, soil: LogSoil) -> np.ndarray:
    """``(n, 6)`` model inputs of the log's cycles on ``soil``: slip, kS, phiS, dphi, omega, noise_smooth."""
    f = log.features
    n = len(log)
    return np.column_stack([log.slip, np.full(n, soil.kS), np.full(n, soil.phiS), np.full(n, soil.dphi),
                            f[:, INDEX["omega"]], f[:, INDEX["noise_smooth"]]])


def log_residuals(model, log: TestbedLog, soil: LogSoil) -> np.ndarray:
    """Features minus the model's mean ``(n, d)`` at each cycle's slip on ``soil``."""
    return model.observe(log.features) - model.mean(log_points(log, soil))


def whitened_sq(model, log: TestbedLog, resid: np.ndarray) -> np.ndarray:
    """Each cycle's squared whitened residual under the model's covariance at its leg speed and noise ``(n,)``."""
    w = whitener(model.cov(log.omega, log.noise_smooth))
    return np.sum((resid @ w) ** 2, axis=1)


def fit_testbed_discrepancy(model, logs, degree: int = 2, ridge: float = 1e-2, iterations: int = 3,
                            grid: SoilGrid | None = None) -> tuple[Discrepancy, list]:
    """A correction in slip alone (degree ``degree``) fitted jointly with each log's soil: returns it and the
    logs' soils. ``model``: the model it corrects (its mean is what the correction adds to)."""
    terms = slip_terms(degree)
    feats = model.features
    d = Discrepancy.zero(feats, model.center[:4], model.halfwidth[:4])
    soils: list = []
    for it in range(iterations):
        corrected = model if it == 0 else with_discrepancy(model, d)
        soils = [log_soil(corrected, lg, grid) for lg in logs]
        x4 = np.vstack([log_points(lg, s)[:, :4] for lg, s in zip(logs, soils)])
        resid = np.vstack([log_residuals(model, lg, s) for lg, s in zip(logs, soils)])
        d = fit_discrepancy(x4, resid, terms, feats, model.center[:4], model.halfwidth[:4], ridge)
    return d, soils


def with_discrepancy(model, extra: Discrepancy):
    """``model`` with ``extra`` added to its discrepancy (a rover model from the shipped surrogate)."""
    from slipest.rover.surrogate import RoverSurrogate

    if isinstance(model, RoverSurrogate):
        return replace(model, discrepancy=model.discrepancy.plus(extra))
    return RoverSurrogate.of(model, extra, np.zeros((len(model.features),) * 2), rover_legs=model.n_legs)


def blind_errors(model, log: TestbedLog, start: int = 9, n_legs: int | None = None, mask=None):
    """The estimator with ``model`` over the log's cycles in order, soil unknown and the reference ignored:
    ``(err, sd)`` of slip [-] (estimate minus reference, and the reported std) for the cycles scored, from the
    ``start``-th (or the ``mask`` cycles, boolean ``(n,)``, when given); NaN where a cycle was not estimated
    (a cycle the model cannot explain at all: ``SoilSlipEstimator.gross_misfit``)."""
    from slipest.estimator import SoilSlipEstimator

    est = SoilSlipEstimator(model=model, n_legs=n_legs or model.n_legs)
    out = est.update_batch(log.features)
    sel = np.arange(len(log)) >= start if mask is None else np.asarray(mask, dtype=bool)
    return (out["slip"] - log.slip)[sel], out["slip_std"][sel]


def blind_score(model, log: TestbedLog, start: int = 9, n_legs: int | None = None, mask=None) -> dict:
    """The estimator with ``model`` over the log's cycles in order, soil unknown and the reference ignored,
    scored from the ``start``-th cycle (or on the ``mask`` cycles, boolean ``(n,)``, when given):
    ``slip_rmse`` [-], ``coverage`` (share within 1.96 std) and ``bias`` of the cycles it estimated, ``n``
    of them, and ``n_scored``: the cycles scored, estimated or not (a cycle the model cannot explain at all
    is not estimated: :func:`blind_errors`)."""
    err, sd = blind_errors(model, log, start, n_legs, mask)
    ok = np.isfinite(err)
    if not ok.any():
        return {"slip_rmse": math.nan, "coverage": math.nan, "bias": math.nan, "n": 0, "n_scored": int(err.size)}
    return {"slip_rmse": float(np.sqrt(np.mean(err[ok] ** 2))), "coverage": float(np.mean(np.abs(err[ok]) <= 1.96 * sd[ok])),
            "bias": float(np.mean(err[ok])), "n": int(ok.sum()), "n_scored": int(err.size)}


__all__ = ["LogSoil", "SLIP_ROUND", "blind_errors", "blind_score", "fit_testbed_discrepancy", "log_points",
           "log_residuals", "log_soil", "whitened_sq", "with_discrepancy"]
