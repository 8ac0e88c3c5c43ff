"""The per-cycle estimator interface: one leg cycle's features in, slip and soil out (pure computation).

Every estimation method :class:`slipest.online.SlipEstimator` offers implements
:class:`CycleEstimator`: the multi-feature surrogate with its recursive soil
filter (:class:`slipest.estimator.SoilSlipEstimator`) and the thesis's Eq. 5.15
(:class:`slipest.inverse.eq515.Eq515Tracker`). The online layer (segmentation,
quality flags, reference slips, the :class:`~slipest.online.Estimate` rows) is
the same for both.

Units: slip [-], kS [N/m], phiS, phiD, dphi [rad]; every value comes with its
standard deviation (``*_std``; 0 when the value is known, NaN when the method
does not estimate it).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass


@dataclass(frozen=True)
class CycleEstimate:
    """What a :class:`CycleEstimator` says of one cycle.

    slip [-]; dphi, phiS, phiD [rad] and kS [N/m]: the soil after this
    cycle (known: std 0; not estimated: NaN); change_prob: posterior
    probability that the soil changed at this cycle [-] (NaN when the
    method has no change detector); used_reference: the reference slip
    given with the cycle updated what the method learns; misfit: how much
    the cycle's features exceed what the method's model explains (1: within
    it; above 1: the likelihood was widened by that factor; NaN: the method
    does not check); discrepancy: how far the recent cycles' features have
    been from the model, as a variance factor (1: as far as on clean
    simulated cycles, or nearer; NaN: the method does not check); the
    likelihood was widened by the larger of the two.
    """

    slip: float
    slip_std: float
    dphi: float
    dphi_std: float
    kS: float
    kS_std: float
    phiS: float
    phiS_std: float
    phiD: float
    phiD_std: float
    change_prob: float
    used_reference: bool
    misfit: float = math.nan
    discrepancy: float = math.nan

    @classmethod
    def nan(cls) -> "CycleEstimate":
        n = math.nan
        return cls(n, n, n, n, n, n, n, n, n, n, n, False, n, n)


class CycleEstimator(ABC):
    """One estimation method, fed one leg cycle at a time, in order.

    ``model_legs``: the wheel-leg geometry the method's model was made for
    (the online layer refuses another number of legs); ``omega_range``:
    ``(lo, hi)`` [rad/s], the leg speeds it covers (the online layer flags a
    cycle at another speed ``"speed"`` and does not estimate it).
    """

    model_legs: int
    omega_range: tuple[float, float]

    @abstractmethod
    def update(self, features, slip_ref: float | None = None, widen: float = 1.0) -> CycleEstimate:
        """One cycle: its full feature row (:data:`slipest.features.FEATURE_NAMES` order and units) and,
        optionally, a reference slip [-] (a method that does not learn from references ignores it).
        ``widen`` (>= 1): a variance factor the caller knows the cycle's likelihood needs, the data's own
        path not being the model's (an IMU that smooths the signal); a method without a likelihood to
        widen ignores it.

        Raises ``ValueError`` when the row cannot be estimated from (non-finite features the method reads).
        """

    @abstractmethod
    def reset(self) -> None:
        """Forget everything learnt (back to the prior)."""

    def prefetch(self, omega: float | None = None, noise_smooth: float | None = None) -> None:
        """Get ready for the next :meth:`update` (called shortly before a cycle closes, with the cycle's leg
        speed [rad/s] and smoothed noise [g] so far when known); optional."""


__all__ = ["CycleEstimate", "CycleEstimator"]
