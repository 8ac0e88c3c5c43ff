"""A disturbance learnt from the testbed waveforms, removed from the samples: what the catalog does not explain (pure computation).

What a log's cycles show beyond the nominal model may repeat every cycle
as the same function of the leg phase: a hub that rocks after each
touchdown, a transient of a shape the catalog's touchdown impact does not
have. Such an additive ``az`` disturbance swamps the stick-slip features
(it can be larger than the oscillation they measure), so it is best
*removed from the samples* before the features are computed, as the
rover's model does when it has one
(:meth:`slipest.rover.surrogate.RoverSurrogate.correct_az`, applied by
:class:`slipest.online.SlipEstimator` to every cycle).

:func:`learn_disturbance` estimates it from a diagnosed log, on its
training cycles only: the mean over them of the binned ``az`` minus the
nominal model's prediction; because the nominal fit absorbed part of the
disturbance into its soil and ``kappa``, the nominal model is refitted on
the cycles with the disturbance taken out and what is still left is added,
``iterations`` times. The held-out cycles (slip levels never fitted) then
say whether it explains the log: their gap (:mod:`slipest.diagnosis.rank`)
with the disturbance removed and the refitted model, against the nominal
model's, as the diagnosis judges a catalog effect.

Units: phase [rad] (``[-pi/nL, pi/nL)``), disturbance [m/s^2], gaps [g].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class LearntDisturbance:
    """A log's disturbance: ``phases`` ``(nb,)`` [rad], ``values`` ``(nb,)`` [m/s^2] (zero mean), the
    held-out gap [g] of the nominal model and with the disturbance removed, and the refitted ``kappa``."""

    phases: np.ndarray
    values: np.ndarray
    gap_nominal: float
    gap_after: float
    kappa: float

    @property
    def shrink(self) -> float:
        """``1 - gap_after / gap_nominal`` (as the diagnosis's shrink)."""
        return 1.0 - self.gap_after / self.gap_nominal if self.gap_nominal > 0 else 0.0


def phase_correction(phases, values, n_legs: int, theta_phase, az) -> np.ndarray:
    """``az`` [m/s^2] minus the disturbance ``values`` [m/s^2] at ``phases`` [rad], interpolated periodically
    (period ``2 pi / nL``) at each sample's leg phase ``theta_phase`` [rad]."""
    return np.asarray(az, dtype=float) - np.interp(theta_phase, phases, values, period=2.0 * math.pi / n_legs)


def learn_disturbance(diagnosis, geometry, iterations: int = 2, seed: int = 0, budget=None) -> LearntDisturbance:
    """The disturbance of a diagnosed log (:class:`~slipest.diagnosis.run.Diagnosis`), learnt on its training
    cycles and judged on its held-out ones (see the module docstring)."""
    from slipest.diagnosis.fit import FitBudget, evaluate, fit
    from slipest.diagnosis.rank import gap_of

    cycles = diagnosis.cycles
    train, test = diagnosis.split.train, diagnosis.split.test
    budget = budget or FitBudget().scaled(0.5)
    nominal = diagnosis.nominal
    total = np.zeros(cycles.y.shape[1])
    shifted = cycles
    for it in range(iterations + 1):
        pred = evaluate(shifted, train, nominal, geometry)["pred"]
        r = np.mean(shifted.y[train] - pred, axis=0)
        total += r - np.mean(r)
        shifted = replace(cycles, y=cycles.y - total)
        if it < iterations:
            nominal = fit(shifted, train, None, geometry, seed=seed + it, budget=budget, init=[nominal.values])
    var_test = diagnosis.noise.var_bin[test]
    gap = gap_of(evaluate(shifted, test, nominal, geometry)["resid"], var_test)
    return LearntDisturbance(cycles.grid.bin_centres, total, float(diagnosis.gap_nominal), float(gap),
                             float(nominal.values["kappa"]))


__all__ = ["LearntDisturbance", "learn_disturbance", "phase_correction"]
