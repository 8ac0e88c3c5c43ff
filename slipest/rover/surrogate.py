"""The calibrated surrogate of one rover: the shipped measurement model plus what calibration learnt (pure computation).

:class:`RoverSurrogate` is a :class:`~slipest.inverse.surrogate.FeatureSurrogate`
(the estimator takes it wherever it takes the shipped model, one code path)
whose mean features carry the rover's discrepancy and whose covariance
carries what the discrepancy does not explain::

    mu_rover(x)   = mu(x) + D(slip, kS, phiS, dphi)        (:class:`~slipest.rover.discrepancy.Discrepancy`)
    R_rover(w, s) = R(w, s) + Q                            (Q: extra covariance, (d, d), feature units^2)

``D`` and ``Q`` do not depend on the leg speed or the IMU noise: they are
learnt at the testbed's speed and noise (the rover file says which) and
applied as they are elsewhere. ``disturbance``: an ``az`` disturbance
locked to the leg phase that the calibration learnt from the testbed's
waveforms (``{"phase": [rad], "az": [m/s^2]}``, :mod:`slipest.rover.waveform`),
or None; :attr:`sample_correction` removes it from a cycle's samples before
their features are computed (:class:`slipest.online.SlipEstimator` applies it).
``angle_offset`` [rad]: the encoder's angle minus the true leg angle that the
calibration found (an encoder zero off the true midstance, or a time skew
between IMU and encoder times the testbed's leg speed; 0: none);
:class:`slipest.online.SlipEstimator` subtracts it from every ``theta``
sample before the stream is cut into cycles. ``eq515``: the Eq. 5.15 calibration refitted
on the same testbed logs (a calibration dict as
:meth:`slipest.inverse.eq515.Eq515Tracker.from_calibration` reads it), or
None. ``interval_scale`` (>= 1): the factor on the estimator's standard
deviations that made the blind estimates of held-out testbed logs cover
95 % of their slips (1: they did without). ``testbed_speeds``: ``(lo, hi)`` [rad/s], the leg speeds of
the testbed logs, or None (not known: a model made in memory, a file from before they were kept);
with them (:meth:`RoverSurrogate.of`) the model covers the speeds within :data:`SPEED_MARGIN` of them and no
others (``covered``, which the estimator flags a cycle outside of as ``"speed"``): ``D``, ``Q`` and a learnt
angle offset hold at the testbed's speeds (docs/calibration.md, "Limits", has the figures). ``source``: where the rover model came from (its file), for messages.
Made by :func:`slipest.rover.calibrate.calibrate`, read by
:func:`slipest.rover.file.load_rover`.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, fields

import numpy as np

from slipest.inverse.surrogate import FeatureSurrogate
from slipest.rover.discrepancy import Discrepancy


#: Relative margin around the testbed's leg speeds within which a rover model is used (Eq. 5.15's speed_tol).
SPEED_MARGIN = 0.1

def _checked_speeds(speeds, source: str) -> tuple[float, float]:
    """``(lo, hi)`` [rad/s] of the testbed's leg speeds as floats; ValueError naming ``source`` unless
    ``0 < lo <= hi``, both finite."""
    lo, hi = (float(v) for v in speeds)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
        raise ValueError(f"{source}: the testbed's leg speeds must be 0 < lo <= hi rad/s, got {speeds}")
    return lo, hi


#: The shipped surrogate's mean on a grid (:meth:`FeatureSurrogate.grid_factors`, not whitened), kept for the rover
#: models built on it (calibration builds many: each would otherwise recompute the same factors for every leg
#: speed and noise); least recently used first out.
_BASE_FACTORS: OrderedDict = OrderedDict()
_BASE_FACTORS_KEPT = 12


def _base_factors(model: FeatureSurrogate, levels, omega: float, noise_smooth: float) -> tuple[np.ndarray, np.ndarray]:
    key = (id(model.coef), tuple(np.asarray(v, dtype=float).tobytes() for v in levels), float(omega),
           float(noise_smooth))
    hit = _BASE_FACTORS.get(key)
    if hit is not None and hit[0] is model.coef:
        _BASE_FACTORS.move_to_end(key)
        return hit[1]
    factors = FeatureSurrogate.grid_factors(model, *levels, omega, noise_smooth)
    for f in factors:
        f.flags.writeable = False
    _BASE_FACTORS[key] = (model.coef, factors)
    while len(_BASE_FACTORS) > _BASE_FACTORS_KEPT:
        _BASE_FACTORS.popitem(last=False)
    return factors


@dataclass(frozen=True)
class RoverSurrogate(FeatureSurrogate):
    """The shipped surrogate's fields, and ``discrepancy``, ``extra_cov`` ``(d, d)``, ``rover_legs``, ``eq515``,
    ``source`` (see the module docstring)."""

    discrepancy: Discrepancy = None
    extra_cov: np.ndarray = None
    rover_legs: int = 4
    eq515: dict | None = None
    source: str = "rover model"
    disturbance: dict | None = None
    interval_scale: float = 1.0
    angle_offset: float = 0.0
    testbed_speeds: tuple | None = None

    def __post_init__(self):
        super().__post_init__()
        d = len(self.features)
        if self.testbed_speeds is not None:
            _checked_speeds(self.testbed_speeds, self.source)
        if not (math.isfinite(self.angle_offset) and abs(self.angle_offset) < math.pi / self.n_legs):
            raise ValueError(f"{self.source}: angle_offset must be finite and within half a leg cycle "
                             f"(|offset| < pi/nL), got {self.angle_offset} rad")
        if not (math.isfinite(self.interval_scale) and self.interval_scale >= 1.0):
            raise ValueError(f"{self.source}: interval_scale must be finite and >= 1, got {self.interval_scale}")
        if self.discrepancy is None or tuple(self.discrepancy.features) != tuple(self.features):
            raise ValueError(f"{self.source}: the discrepancy must be over the model's features {list(self.features)}")
        q = np.asarray(self.extra_cov, dtype=float)
        if q.shape != (d, d) or not np.all(np.isfinite(q)) or not np.allclose(q, q.T, atol=1e-12 * max(1.0, abs(q).max())):
            raise ValueError(f"{self.source}: extra_cov must be a symmetric finite ({d}, {d}) matrix")
        if np.linalg.eigvalsh(0.5 * (q + q.T)).min() < -1e-9 * max(1.0, abs(q).max()):
            raise ValueError(f"{self.source}: extra_cov must be positive semi-definite")
        if self.disturbance is not None:
            if not isinstance(self.disturbance, dict):
                raise ValueError(f"{self.source}: the disturbance must be an object of phases and accelerations, "
                                 f"not {type(self.disturbance).__name__}")
            ph = np.asarray(self.disturbance.get("phase", ()), dtype=float)
            az = np.asarray(self.disturbance.get("az", ()), dtype=float)
            if ph.ndim != 1 or ph.shape != az.shape or ph.size < 4 or not (np.all(np.isfinite(ph))
                                                                           and np.all(np.isfinite(az))):
                raise ValueError(f"{self.source}: the disturbance must be equal lists of at least 4 finite phases "
                                 "and accelerations")

    @classmethod
    def of(cls, base: FeatureSurrogate, discrepancy: Discrepancy, extra_cov, **rover) -> "RoverSurrogate":
        """The rover model on ``base`` (the shipped surrogate, or a model of the same kind); with
        ``testbed_speeds`` it covers the leg speeds within :data:`SPEED_MARGIN` of them (ValueError when the
        base covers none of them)."""
        own = {f.name: getattr(base, f.name) for f in fields(FeatureSurrogate)}
        speeds = rover.get("testbed_speeds")
        if speeds is not None:
            lo, hi = rover["testbed_speeds"] = _checked_speeds(speeds, rover.get("source", "rover model"))
            blo, bhi = base.covered_range("omega")
            rlo, rhi = max(blo, lo * (1.0 - SPEED_MARGIN)), min(bhi, hi * (1.0 + SPEED_MARGIN))
            if not rlo <= rhi:
                raise ValueError(f"{rover.get('source', 'rover model')}: calibrated at leg speeds {lo:.3g}-{hi:.3g} "
                                 f"rad/s, which the inverse model (covering {blo:.3g}-{bhi:.3g}) does not cover")
            own["covered"] = dict(base.covered, omega=[rlo, rhi])
        return cls(**own, discrepancy=discrepancy, extra_cov=np.asarray(extra_cov, dtype=float), **rover)

    @property
    def describes_imu_path(self) -> bool:
        """True: the calibration learnt this rover's IMU as its testbed logs show it, and checked the intervals
        on held-out cycles, so the online estimator does not widen them again for an IMU that settles slowly
        after the leg swaps (:mod:`slipest.swap_timing`)."""
        return True

    @property
    def sample_correction(self):
        """``correct(theta_phase [rad], az [m/s^2]) -> az`` removing the learnt disturbance from a cycle's
        samples, or None when the rover has none."""
        if self.disturbance is None:
            return None
        from functools import partial

        from slipest.rover.waveform import phase_correction

        return partial(phase_correction, np.asarray(self.disturbance["phase"], dtype=float),
                       np.asarray(self.disturbance["az"], dtype=float), self.n_legs)

    @property
    def base(self) -> FeatureSurrogate:
        """The surrogate without the rover's correction."""
        return FeatureSurrogate(**{f.name: getattr(self, f.name) for f in fields(FeatureSurrogate)})

    @property
    def n_legs(self) -> int:
        """Legs of the rover's wheel-leg [-]."""
        return int(self.rover_legs)

    def mean(self, x) -> np.ndarray:
        """Mean features ``(..., d)`` at points ``x`` ``(..., 6)`` (as :meth:`FeatureSurrogate.mean`), corrected."""
        x = np.asarray(x, dtype=float)
        return super().mean(x) + self.discrepancy.evaluate(x[..., :4])

    def grid_factors(self, slip_nodes, kS_levels, phiS_levels, dphi_levels, omega: float,
                     noise_smooth: float, right: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`FeatureSurrogate.grid_factors`, corrected: the base model's factors and the discrepancy's,
        stacked along the slip degrees (``right`` multiplies both; the base's, cached unmultiplied, along
        their features)."""
        levels = (slip_nodes, kS_levels, phiS_levels, dphi_levels)
        partial, basis = _base_factors(self, levels, omega, noise_smooth)
        if right is not None:
            a, d = partial.shape[:2]
            partial = np.matmul(np.asarray(right, dtype=float).T, partial.reshape(a, d, -1)).reshape(
                (a, -1) + partial.shape[2:])
        extra, extra_basis = self.discrepancy.factors(*levels, right=right)
        return np.concatenate([partial, extra]), np.concatenate([basis, extra_basis], axis=1)

    def cov(self, omega: float, noise_smooth: float) -> np.ndarray:
        """``R + Q`` ``(d, d)`` (:meth:`FeatureSurrogate.cov` plus the extra covariance)."""
        return super().cov(omega, noise_smooth) + self.extra_cov


__all__ = ["RoverSurrogate"]
