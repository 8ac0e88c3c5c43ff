"""Which effect: held-out split, noise floor, the gap, ranking and verdict (pure computation).

**The gap.** For a fitted model and a set of cycles ``C`` (the held-out
cycles unless said otherwise), each cycle's logged ``az`` is averaged over
the analysis bins of its leg phase (``nb`` equal bins over
``[-pi/nL, pi/nL)``, :mod:`slipest.diagnosis.cycles`) and compared with the
model's prediction for that cycle's slip, on the same bins, after the
fitted constant bias. With ``r`` those residuals [m/s^2]::

    gap(C) = sqrt(max(0, mean_{c in C, bins}(r^2) - s_noise^2)) / g      [g]

i.e. the RMS model error in excess of the measurement noise, where
``s_noise^2`` is the variance of one cycle's bin average about what the
cycle would show without noise: estimated from the data by
*repeatability* (cycles of one log with equal slip, previous slip and leg
speeds are deterministic copies in the model; their pooled within-group variance)
when at least :data:`MIN_REPEAT_DOF` such degrees of freedom exist, else
from the white-noise level of the raw samples (median absolute second
difference) divided by the samples per bin. A model that explains the data
within noise has a gap near 0.

**Held-out cycles.** :func:`split_cycles` keeps every third distinct slip
level (interior ones: 2nd, 5th, 8th, ...) out of training altogether, and
every third cycle of the other levels; at most :data:`MAX_TRAIN_LEVELS`
levels are fitted (spread over the range), the rest are held out too.

**Verdict.** ``none`` when the nominal model's held-out gap is at most
``NONE_FACTOR`` times the bin noise (and at most ``NONE_FLOOR_G`` when the
data are nearly noise-free: the model's own resampling error); otherwise the
best-ranked effect when it shrinks the held-out gap by at least
``MIN_SHRINK`` (``1 - gap_after/gap_before``) *and* by at least
``MIN_GAIN_FACTOR`` bin-noise standard deviations; otherwise
``unexplained``. The minimum shrink is the penalty for the effect's added
parameters: an effect that fits noise or a little of the discrepancy does
not get named. Effects are ranked by held-out gap; within
``TIE_FRACTION`` of the nominal gap, fewer parameters first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slipest.diagnosis.cycles import CycleSet
from slipest.units import G

#: Most slip levels used for fitting (the rest are held out; keeps the fit fast).
MAX_TRAIN_LEVELS = 6
#: Every n-th interior slip level is held out entirely; every n-th cycle of the others.
HOLDOUT_EVERY = 3
#: Fewest repeat degrees of freedom (cycles beyond the first of their group) to trust repeatability.
MIN_REPEAT_DOF = 3
#: ``none`` when the nominal held-out gap is at most this many bin-noise standard deviations ...
NONE_FACTOR = 1.5
#: ... or at most this [g] (resampling error of the prediction on noise-free data).
NONE_FLOOR_G = 0.004
#: An effect is named only if it shrinks the held-out gap by at least this fraction ...
MIN_SHRINK = 0.5
#: ... and by at least this many bin-noise standard deviations (absolute gain).
MIN_GAIN_FACTOR = 1.0
#: Ranking ties: held-out gaps within this fraction of the nominal gap count as equal (fewer parameters first).
TIE_FRACTION = 0.02


@dataclass(frozen=True)
class Split:
    """Training and held-out cycle indices, and which slip levels were not fitted at all."""

    train: np.ndarray
    test: np.ndarray
    train_levels: tuple
    heldout_levels: tuple


def split_cycles(slip: np.ndarray, max_train_levels: int = MAX_TRAIN_LEVELS, every: int = HOLDOUT_EVERY) -> Split:
    """Split cycles (by their slips) into training and held-out sets (see the module docstring)."""
    slip = np.asarray(slip, dtype=float)
    if slip.size < 2:
        raise ValueError("the diagnosis needs at least 2 complete leg cycles")
    key = np.round(slip, 6)
    levels = np.unique(key)
    held = set(levels[1:-1][::every].tolist()) if len(levels) >= 3 else set()
    train_levels = [lv for lv in levels if lv not in held]
    if len(train_levels) > max_train_levels:
        pick = np.unique(np.round(np.linspace(0, len(train_levels) - 1, max_train_levels)).astype(int))
        keep = [train_levels[i] for i in pick]
        held |= set(train_levels) - set(keep)
        train_levels = keep
    train, test = [], []
    for lv in levels:
        members = np.flatnonzero(key == lv)
        if lv in held:
            test.extend(members.tolist())
            continue
        out = members[every - 1 :: every] if members.size >= 2 else members[:0]
        test.extend(out.tolist())
        train.extend(np.setdiff1d(members, out).tolist())
    if not test:
        # one level with one cycle per ... : hold out the last cycle
        test = [train.pop()]
    if not train:
        raise ValueError("too few cycles to fit and hold out")
    return Split(
        train=np.array(sorted(train)),
        test=np.array(sorted(test)),
        train_levels=tuple(float(x) for x in train_levels),
        heldout_levels=tuple(float(x) for x in sorted(held)),
    )


@dataclass(frozen=True)
class NoiseFloor:
    """Noise of one cycle's bin average: ``var_bin`` [(m/s^2)^2] per cycle and bin ``(C, nb)``.

    ``source``: "repeatability" or "white"; ``sample_g``: white noise of a
    raw sample [g]; ``repeat_g``: pooled repeatability [g] per bin (NaN if
    not available); ``white_bin_g``: white noise of a bin average [g].
    """

    var_bin: np.ndarray
    source: str
    sample_g: float
    repeat_g: float
    white_bin_g: float

    @property
    def bin_g(self) -> float:
        """RMS bin noise [g]."""
        return float(math.sqrt(np.mean(self.var_bin))) / G


def noise_floor(cycles: CycleSet, min_dof: int = MIN_REPEAT_DOF) -> NoiseFloor:
    """Estimate the bin noise from repeatability (equal slip, previous slip and leg speeds, same log) or white noise."""
    white = cycles.noise_bin
    keys = np.stack([cycles.log.astype(float), np.round(cycles.prev_slip, 6), np.round(cycles.slip, 6),
                     np.round(cycles.omega, 9), np.round(cycles.prev_omega, 9)], axis=1)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.ravel()
    ss, dof = 0.0, 0
    for g in np.unique(inv):
        y = cycles.y[inv == g]
        if len(y) >= 2:
            ss += float(np.sum((y - y.mean(axis=0)) ** 2))
            dof += len(y) - 1
    repeat = ss / (dof * cycles.grid.nb) if dof else float("nan")
    sample_g = float(np.sqrt(np.mean(cycles.noise**2))) / G
    white_bin_g = float(math.sqrt(np.mean(white))) / G
    if dof >= min_dof:
        var = np.full_like(white, repeat)
        source = "repeatability"
    else:
        var = white
        source = "white"
    return NoiseFloor(var, source, sample_g, math.sqrt(repeat) / G if dof else float("nan"), white_bin_g)


def gap_of(resid: np.ndarray, var_bin: np.ndarray) -> float:
    """The gap [g] of residuals ``(C, nb)`` [m/s^2] given the bin noise variance (see the module docstring)."""
    resid = np.asarray(resid, dtype=float)
    if resid.size == 0 or not np.all(np.isfinite(resid)):
        return float("inf")
    excess = float(np.mean(resid**2) - np.mean(var_bin))
    return math.sqrt(max(excess, 0.0)) / G


@dataclass
class Candidate:
    """One entry of the ranking: effect, catalog parameters, held-out and training gaps [g], shrink."""

    effect: str
    params: dict
    gap_heldout: float
    shrink: float
    gap_train: float = float("nan")
    n_params: int = 0
    soil: dict = field(default_factory=dict)
    named: bool = False

    def as_dict(self) -> dict:
        return {
            "effect": self.effect,
            "params": self.params,
            "gap_heldout": self.gap_heldout,
            "shrink": self.shrink,
            "gap_train": self.gap_train,
            "n_params": self.n_params,
            "soil": self.soil,
            "named": self.named,
        }


def shrink_of(gap_before: float, gap_after: float) -> float:
    """``1 - gap_after / gap_before`` (0 when there is no gap to shrink)."""
    if not gap_before > 0 or not math.isfinite(gap_after):
        return 0.0
    return 1.0 - gap_after / gap_before


def rank(candidates: list[Candidate], gap_nominal: float, tie_fraction: float = TIE_FRACTION) -> list[Candidate]:
    """Best first: smallest held-out gap; gaps within ``tie_fraction * gap_nominal`` tie, fewer parameters first."""
    tol = tie_fraction * max(gap_nominal, 1e-12)
    ordered = sorted(candidates, key=lambda c: (c.gap_heldout if math.isfinite(c.gap_heldout) else np.inf))
    out: list[Candidate] = []
    while ordered:
        best = ordered[0]
        ties = [c for c in ordered if c.gap_heldout <= best.gap_heldout + tol]
        ties.sort(key=lambda c: (c.n_params, c.gap_heldout))
        out.append(ties[0])
        ordered.remove(ties[0])
    return out


@dataclass(frozen=True)
class Thresholds:
    """Verdict thresholds (see the module docstring)."""

    none_factor: float = NONE_FACTOR
    none_floor_g: float = NONE_FLOOR_G
    min_shrink: float = MIN_SHRINK
    min_gain_factor: float = MIN_GAIN_FACTOR

    def none_level(self, noise_bin_g: float) -> float:
        return max(self.none_factor * noise_bin_g, self.none_floor_g)


def verdict(gap_nominal: float, ranking: list[Candidate], noise_bin_g: float,
            thresholds: Thresholds = Thresholds()) -> str:
    """``none``, the name of the best effect, or ``unexplained`` (see the module docstring).

    Marks the named candidate (``named = True``) in ``ranking``.
    """
    for c in ranking:
        c.named = False
    if gap_nominal <= thresholds.none_level(noise_bin_g):
        return "none"
    if ranking:
        best = ranking[0]
        gain = gap_nominal - best.gap_heldout
        if best.shrink >= thresholds.min_shrink and gain >= thresholds.min_gain_factor * noise_bin_g:
            best.named = True
            return best.effect
    return "unexplained"
