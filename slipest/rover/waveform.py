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
training cycles only: the nominal model is refitted with a waveform common
to every cycle profiled out (``fit(..., common=True)``: the soil and
``kappa`` are then fitted to how the cycles differ from one slip to another,
which a disturbance locked to the phase does not change), and the
disturbance is the training cycles' mean residual, the binned ``az`` minus
that model's prediction. (Refitting the nominal model alternately with
the mean residual taken out settles at wrong points where the soil and
``kappa`` keep part of a large disturbance: ``docs/calibration.md``.)
The held-out cycles (slip levels never fitted) then
say whether it explains the log: their gap (:mod:`slipest.diagnosis.rank`)
with the disturbance removed and the refitted model, against the nominal
model's, as the diagnosis judges a catalog effect.

:func:`effect_disturbance` gives the same kind of disturbance from a
catalog effect the diagnosis fitted, when that effect adds to ``az``
something that does not depend on ``az`` (a touchdown impact): its
steady-state waveform over a leg cycle at the testbed's leg speed, exact
where a learnt mean is noisy. :func:`effect_angle_offset` gives the encoder
angle offset of a catalog effect that only moves the angle against the
``az`` samples (an encoder offset; a time skew, at the testbed's leg speed),
which the rover's model subtracts from ``theta``.

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


#: Phases of an effect's disturbance table per leg cycle (:func:`effect_disturbance`).
EFFECT_PHASES = 4000
#: An effect's disturbance is built after this long at steady speed [s] (its train of transients builds up;
#: the catalog impact's longest fitted decay, 8 s, is then steady to 0.2 %).
EFFECT_SETTLE_S = 50.0


def effect_disturbance(specs, omega: float, n_legs: int, rate: float = 20000.0):
    """The ``az`` [m/s^2] the catalog effects ``specs`` (``{"name": ..., params}``) add at steady leg speed
    ``omega`` [rad/s], as ``(phases (EFFECT_PHASES,) [rad], values (EFFECT_PHASES,) [m/s^2], zero mean)``
    over a leg cycle of ``n_legs`` legs, sampled at ``rate`` [Hz]; None when they do not just add to ``az``
    (a physics effect, a filter, a clip, a change of the angle or the time: their output minus their input
    depends on the input, or they add nothing)."""
    from slipest.model.effects import EFFECTS, compile_effects
    from slipest.model.params import StickSlipParams

    if not specs or any(EFFECTS[s["name"]].kind == "physics" for s in specs):
        return None
    step = 2.0 * math.pi / n_legs
    period = step / omega
    t = np.arange(0.0, EFFECT_SETTLE_S + 1.5 * period, 1.0 / rate)
    theta = -math.pi / n_legs + omega * t
    rng = np.random.default_rng(0)
    probe = rng.normal(0.0, 5.0, t.size)

    def added(az):
        transform, stages = compile_effects(specs)
        transform(StickSlipParams(nL=n_legs, omega=omega))
        out, th = az.copy(), theta.copy()
        for st in stages:
            out, th = st.apply(t, out, th, np.random.default_rng(1))
        return out - az, th

    zero, th0 = added(np.zeros_like(t))
    moved, _ = added(probe)
    scale = float(np.max(np.abs(zero)))
    if scale < 1e-6 or not np.allclose(moved, zero, rtol=1e-9, atol=1e-9 * max(1.0, scale)) \
            or not np.array_equal(th0, theta):
        return None
    last = t >= t[-1] - period  # the last whole cycle, the train built up
    phase = np.mod(theta[last] + math.pi / n_legs, step) - math.pi / n_legs
    order = np.argsort(phase)
    phases = -math.pi / n_legs + (np.arange(EFFECT_PHASES) + 0.5) * step / EFFECT_PHASES
    values = np.interp(phases, phase[order], zero[last][order], period=step)
    return phases, values - np.mean(values)


def band_limited(phases, values, n_legs: int, n_out: int = EFFECT_PHASES):
    """The periodic band-limited signal whose averages over equal phase bins are ``values`` [m/s^2].

    ``phases``: ``(nb,)`` bin centres [rad], evenly spaced over a leg cycle
    (``[-pi/nL, pi/nL)``); ``values``: the signal averaged over each bin (a
    learnt disturbance). Each harmonic ``k`` of the cycle is divided by the
    bin average's gain ``sinc(k / nb)`` and the Fourier series is evaluated
    at ``n_out`` phases (centres of equal bins): an oscillation of a few bins
    per period keeps its amplitude, where interpolating the averages loses
    5-15 % of it. Returns ``(phases (n_out,) [rad], values (n_out,) [m/s^2],
    zero mean)``."""
    phases = np.asarray(phases, dtype=float)
    values = np.asarray(values, dtype=float)
    nb = values.size
    half = math.pi / n_legs
    if nb < 4 or not np.allclose(phases, -half + (np.arange(nb) + 0.5) * 2.0 * half / nb, atol=1e-9):
        raise ValueError("band_limited needs the values at the centres of at least 4 equal bins over [-pi/nL, pi/nL)")
    k = np.arange(nb // 2 + 1)
    spectrum = np.fft.rfft(values) / np.sinc(k / nb)
    weight = np.where((k == 0) | (2 * k == nb), 1.0, 2.0) / nb  # the real series of the one-sided spectrum
    weight[0] = 0.0  # zero mean
    out = -half + (np.arange(n_out) + 0.5) * 2.0 * half / n_out
    pos = (out + half) / (2.0 * half) * nb - 0.5  # in bins from the first centre
    series = (np.exp(2j * math.pi * np.outer(pos, k) / nb) * (weight * spectrum)).real.sum(axis=1)
    return out, series - np.mean(series)


def effect_angle_offset(specs, omega: float, n_legs: int) -> float | None:
    """The encoder angle offset [rad] the catalog effects ``specs`` (``{"name": ..., params}``) amount to at
    steady leg speed ``omega`` [rad/s] (:meth:`slipest.model.effects.base.Effect.angle_offset_at`: an encoder
    offset, a time skew), summed; None when one of them does anything else or the sum is not within half a leg
    cycle (``|offset| < pi/nL``)."""
    from slipest.model.effects import EFFECTS

    if not specs:
        return None
    total = 0.0
    for spec in specs:
        effect = EFFECTS[spec["name"]]
        offset = effect.angle_offset_at({**effect.defaults(), **{k: v for k, v in spec.items() if k != "name"}}, omega)
        if offset is None:
            return None
        total += offset
    return total if math.isfinite(total) and abs(total) < math.pi / n_legs else None


def learn_disturbance(diagnosis, geometry, seed: int = 0, budget=None) -> LearntDisturbance:
    """The disturbance of a diagnosed log (:class:`~slipest.diagnosis.run.Diagnosis`), learnt on its training
    cycles and judged on its held-out ones (see the module docstring). ``budget``: the nominal refit's
    (:class:`~slipest.diagnosis.fit.FitBudget`; default half the diagnosis's full one)."""
    from slipest.diagnosis.fit import FitBudget, evaluate, fit
    from slipest.diagnosis.rank import gap_of

    cycles = diagnosis.cycles
    train, test = diagnosis.split.train, diagnosis.split.test
    budget = budget or FitBudget().scaled(0.5)
    nominal = fit(cycles, train, None, geometry, seed=seed, budget=budget, init=[diagnosis.nominal.values],
                  common=True)
    r = np.mean(cycles.y[train] - evaluate(cycles, train, nominal, geometry)["pred"], axis=0)
    total = r - np.mean(r)
    shifted = replace(cycles, y=cycles.y - total)
    gap = gap_of(evaluate(shifted, test, nominal, geometry)["resid"], diagnosis.noise.var_bin[test])
    return LearntDisturbance(cycles.grid.bin_centres, total, float(diagnosis.gap_nominal), float(gap),
                             float(nominal.values["kappa"]))


__all__ = ["LearntDisturbance", "band_limited", "effect_angle_offset", "effect_disturbance", "learn_disturbance", "phase_correction"]
