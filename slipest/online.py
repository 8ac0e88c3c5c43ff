"""The API a rover program calls: samples in, one slip estimate per leg cycle out.

    from slipest.online import SlipEstimator

    est = SlipEstimator(n_legs=4)                 # soil unknown, learnt as it goes
    for t, az, theta in imu_and_encoder:          # live: one sample at a time
        for e in est.push(t, az, theta):
            print(e.cycle, e.slip, e.slip_std, e.dphi, e.quality)

    est.push_many(t_array, az_array, theta_array) # replay: arrays, same results

Samples: ``t`` [s], ``az`` [m/s^2] vertical specific force as the IMU
reports it (gravity included, +9.81 at rest), ``theta`` [rad] wheel-leg
angle (0 at a midstance; wrapped or not). The stream is cut into leg
cycles by :class:`slipest.segmentation.CycleSegmenter`; each closed cycle
gives exactly one :class:`Estimate`, on the sample that closes it. A cycle
that cannot be estimated (segmenter flag such as ``"gap"``, ``"nan"``,
``"saturated"``, ``"partial"``, a stuck sensor's repeated ``az``
(``"stuck"``), or features that could not be computed)
or a leg speed outside the models' (``"speed"``)
still gives an Estimate, with NaN values and ``quality`` naming the reason:
nothing is dropped silently, and nothing is estimated from corrupted data.
A cycle with a few samples missing or unusable in short holes (see
:class:`~slipest.segmentation.CycleSegmenter`) or with isolated outliers
(:mod:`slipest.despike`) is estimated without them, with quality
``"repaired"`` and their count in ``n_repaired``.

The IMU is checked against the encoder on every leg swap, where the hub's
acceleration steps to the new leg's rigid level (:mod:`slipest.swap_timing`;
``swap_checks=False``: never):

* when the IMU sees the swaps consistently later or earlier than the
  encoder (an encoder zero offset, a time skew between their time stamps),
  the angle is corrected from then on (``theta`` less the offset, or the
  skew times the leg speed), the cycle being filled is dropped (the stream
  re-synchronises, counted in ``segmenter_resyncs``), and the ``"timing"``
  hint says by how much;
* when the IMU settles slowly after the recent swaps (a low-pass filter or
  a soft mount the model does not know), each cycle's likelihood is widened
  (:data:`slipest.swap_timing.SLUGGISH_WIDENING`) and the ``"imu"`` hint
  says so; not with a calibrated rover model (``describes_imu_path``),
  whose calibration learnt the rover's IMU.

Methods (each a :class:`~slipest.cycle_estimator.CycleEstimator`):

* ``"default"``: the multi-feature surrogate with the recursive soil filter
  (:class:`slipest.estimator.SoilSlipEstimator`). Works with the soil
  unknown; a known soil (``soil=``) is used (complete: slip only, each
  cycle still tested against the model on that soil; partial: restricts
  the soil prior), within the soils the model covers (``ValueError``
  otherwise).
* ``"eq515"``: thesis Eq. 5.15 on ``Da`` (:mod:`slipest.inverse.eq515`).
  Needs ``kS`` and either ``dphi`` (slip from ``Da``) or
  ``use_reference=True`` (``dphi`` learnt from reference slips by a
  Kalman filter, as the thesis uses the equation).

Reference slip: ``push(..., slip_ref=...)`` (per sample; e.g. a log's
``slip`` column or a later message). It is **ignored** unless
``use_reference=True``; a cycle's reference is the finite reference
given most often with the samples since the previous cycle closed, the
latest of them on a tie (:class:`ReferenceTally`: a log's slip column
changes value near a cycle's boundary, a sample early or late, and the few
samples of the neighbouring cycle's value must not label the cycle; a
reference sent as one message a cycle is that message, a later one
replacing an earlier one) (also reported as ``Estimate.slip_ref``, used or
not: a blind test can carry the truth along).

The same object serves replay and live streams; :meth:`SlipEstimator.iter_estimates`
runs it over an iterable of sample chunks and ``on_estimate`` calls back
with every estimate as soon as it exists.

Live, once set up (estimator built, bus or port open), call
:func:`slipest.startup_gc.freeze_startup_objects`, as the live commands
do: otherwise CPython's occasional full garbage collection walks the ~120k
start-up objects and stops the process for 30-60 ms, samples and estimates
alike.
"""

from __future__ import annotations

import inspect
import math
import statistics
from collections import deque
from dataclasses import asdict, dataclass, fields
from typing import Callable, Iterable, Iterator

import numba
import numpy as np

from slipest.cycle_estimator import CycleEstimate
from slipest.dequantize import AngleDequantizer
from slipest.despike import outliers
from slipest.features import INDEX, cycle_features, sample_noise, smoothed_noise, stance_noise
from slipest.inverse.base import Soil
from slipest.segmentation import CycleSegmenter
from slipest.stuck import STUCK_NOISE_MIN, STUCK_TIME, repeat_runs, stuck_run_length
from slipest.swap_timing import SLUGGISH_WIDENING, SwapTiming
from slipest.units import G

#: Estimation methods (``method=``).
METHODS = ("default", "eq515")
#: Qualities of an estimated cycle.
ESTIMATED = ("ok", "repaired")
#: Hints that say the data differ from the model, or how they were taken, not that the input is wrong ("fit"
#: aside).
MODEL_HINTS = ("imu", "encoder", "noise", "rover_speed")
#: Cycles whose noise measures make the running noise estimate (their median) [-].
NOISE_CYCLES = 9
#: A cycle whose own noise measure exceeds the running estimate by this factor and by :data:`BURST_MARGIN` is a
#: noise burst (vibration, interference): it is referred to its own noise, not the running one [-], [g].
BURST_FACTOR = 2.0
BURST_MARGIN = 0.005
#: The same test on the stance's own measure (:func:`slipest.features.stance_noise`) needs this much more than the
#: running estimate [g]: the stick-slip signal adds up to 0.006 g to it on clean cycles at 200 Hz.
STANCE_BURST_MARGIN = 0.01
_DELTA_A, _NOISE, _NOISE_SMOOTH = INDEX["delta_a"], INDEX["noise"], INDEX["noise_smooth"]


@numba.njit(cache=True)
def _window_speed(t, theta_phase, half):
    """Mean leg speed [rad/s] over the samples with phase in ``[0, half]`` (NaN when fewer than two): the phase
    travelled from the first such sample to the last over the time between them."""
    n = theta_phase.size
    i0 = 0
    while i0 < n and not (0.0 <= theta_phase[i0] <= half):
        i0 += 1
    i1 = n - 1
    while i1 > i0 and not (0.0 <= theta_phase[i1] <= half):
        i1 -= 1
    if i1 <= i0:
        return math.nan
    span = t[i1] - t[i0]
    return (theta_phase[i1] - theta_phase[i0]) / span if span > 0 else math.nan


#: Mean ``az`` over a cycle's rigid half [g] outside of which the input's units or axis are taken as wrong
#: (the hub's own acceleration there is a few hundredths of g; a tilted IMU reads cos(tilt)).
GRAVITY_RANGE = (0.8, 1.2)


def units_hint(mean_g: float, level: str = "rigid-phase mean") -> str:
    """What a cycle's rigid-half mean ``az`` [g] (or the ``level`` said, e.g. a log's median) outside
    :data:`GRAVITY_RANGE` most likely means."""
    lo, hi = GRAVITY_RANGE
    if lo <= mean_g * G <= hi:
        return (f"az looks like it is in g (a {level} of {mean_g * G:.2f} where gravity reads 9.81): "
                "slipest wants m/s^2")
    if -hi <= mean_g <= -lo or -hi <= mean_g * G <= -lo:
        return f"az points down (a {level} of {mean_g * G:.2f} m/s^2): the IMU axis is reversed"
    if abs(mean_g) < 0.2:
        return (f"az has no gravity in it (a {level} of {mean_g * G:.2f} m/s^2): slipest wants the specific "
                "force the IMU reports, +9.81 m/s^2 at rest")
    return (f"az's {level} is {mean_g * G:.2f} m/s^2, not gravity's 9.81: check the IMU's axis, units and "
            "mounting")


@numba.njit(cache=True)
def _rigid_mean(theta_phase, az, half):
    """Mean ``az`` [input units] over the rigid half's phases ``[-0.8 half, -0.05 half]`` (NaN when empty;
    compiled, for the closing sample's latency)."""
    lo = -0.8 * half
    hi = -0.05 * half
    acc = 0.0
    n = 0
    for i in range(theta_phase.size):
        p = theta_phase[i]
        if lo <= p <= hi:
            acc += az[i]
            n += 1
    return acc / n if n else math.nan


#: Running discrepancy (:attr:`Estimate.discrepancy`) from which an estimated cycle counts as off the model:
#: the recent cycles' best candidates twice as far (squared) from the model as on clean simulated cycles.
DISCREPANCY_LEVEL = 2.0
#: Share of the estimated cycles off the model (misfit, or discrepancy from ``DISCREPANCY_LEVEL``) from which a run
#: is said not to fit the model, once at least ``FIT_MIN_CYCLES`` of them are (:func:`fit_advice`).
OFF_MODEL_SHARE = 0.2
FIT_MIN_CYCLES = 5


def off_model(misfit: float, discrepancy: float) -> bool:
    """An estimated cycle the model did not explain: its own features (``misfit`` above 1) or, persistently,
    the recent cycles' (``discrepancy`` from :data:`DISCREPANCY_LEVEL`)."""
    return misfit > 1.0 or discrepancy >= DISCREPANCY_LEVEL


def fit_advice(cycles: int, cycles_off_model: int) -> str | None:
    """What to tell people when the data do not fit the estimator's model: a sentence (None when they fit).

    ``cycles``: cycles that reached the estimator (estimated, or flagged ``"misfit"``);
    ``cycles_off_model``: those off the model (:attr:`SlipEstimator.counters`; see
    :data:`OFF_MODEL_SHARE`, :data:`FIT_MIN_CYCLES`).
    """
    if cycles_off_model < max(FIT_MIN_CYCLES, OFF_MODEL_SHARE * cycles):
        return None
    return (f"the data do not fit the estimator's model ({cycles_off_model} of {cycles} cycles off it): this rover "
            "or soil differs from the simulator, so those cycles got wider intervals or, when the model could not "
            "explain them at all, no estimate (quality 'misfit'), and slip may still be biased; 'slipest calibrate' "
            "on testbed logs with a reference slip fits the model to this rover (then estimate with --rover)")


#: Parameters of a cycle estimator's constructor that :class:`SlipEstimator` (or the calibration) sets itself.
_SET_BY_SLIP_ESTIMATOR = frozenset({"self", "model", "inverse", "soil", "use_reference", "n_legs", "model_legs",
                                    "model_omega"})


def _check_options(cls, options: dict, method: str) -> None:
    """``ValueError`` naming the options of ``options`` that ``cls``'s constructor does not take (or that
    :class:`SlipEstimator` sets itself), with those it takes."""
    known = set(inspect.signature(cls).parameters) - _SET_BY_SLIP_ESTIMATOR
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"unknown option(s) {unknown} of the {method!r} estimator; it takes {sorted(known)}")


#: :meth:`SlipEstimator.push` gets the estimator ready for the next close in three steps, off the closing
#: sample's latency (:meth:`SlipEstimator._warm_for_next_close`): once this fraction of the last cycle's
#: duration has passed since it closed, it measures the open cycle's leg speed so far and predicts its close
#: (a cycle up to four times faster than the last is still caught before its close) ...
PREFETCH_PLAN = 0.25
#: ... when this fraction of the predicted cycle is left (the window half done), it builds the table of the
#: window's speed so far if that is a new bin (three tables, about 0.1 s; the speed may change from one cycle to
#: the next) ...
PREFETCH_BUILD = 0.25
#: ... and when this fraction is left (about 25 ms at the models' speed), it brings the table into the CPU
#: caches (building it now only if the speed moved to another bin since): the estimate on the closing sample
#: then waits less on memory.
PREFETCH_TOUCH = 0.01
#: When the open cycle has no speed to predict its close from yet (a new stream, the rover stopped), the next
#: look [s].
PREFETCH_RETRY = 0.1


class ReferenceTally:
    """The reference slip of the cycle being filled: the finite value given most often since :meth:`take`, the
    latest of them on a tie (NaN: none given). Values are compared exactly (a log's column repeats one value a
    cycle)."""

    __slots__ = ("_counts", "_n")

    def __init__(self):
        self._counts: dict[float, list] = {}  # value -> [count, position of its latest occurrence]
        self._n = 0

    def add(self, value: float) -> None:
        """One reference [-] (ignored unless finite)."""
        if math.isfinite(value):
            self._n += 1
            c = self._counts.get(value)
            if c is None:
                self._counts[value] = [1, self._n]
            else:
                c[0] += 1
                c[1] = self._n

    def add_many(self, values: np.ndarray) -> None:
        """The references of consecutive samples, in order (non-finite ones ignored): as :meth:`add` on each."""
        v = values[np.isfinite(values)]
        if v.size == 0:
            return
        if v[0] == v[-1] and np.all(v == v[0]):  # the usual case: one value over the whole slice
            uniq, counts, last = v[:1], np.array([v.size]), np.array([v.size - 1])
        else:
            uniq, first_rev, counts = np.unique(v[::-1], return_index=True, return_counts=True)
            last = v.size - 1 - first_rev
        for value, count, pos in zip(uniq.tolist(), counts.tolist(), last.tolist()):
            c = self._counts.get(value)
            if c is None:
                self._counts[value] = [count, self._n + pos + 1]
            else:
                c[0] += count
                c[1] = self._n + pos + 1
        self._n += v.size

    def take(self) -> float:
        """The cycle's reference (see the class docstring), and start the next cycle's."""
        if not self._counts:
            return math.nan
        value = max(self._counts.items(), key=lambda kv: (kv[1][0], kv[1][1]))[0]
        self._counts = {}
        return value


@dataclass(frozen=True)
class Estimate:
    """One leg cycle's estimate.

    cycle: the cycle's index ``k`` (midstance at ``theta = 2 pi k / nL``);
    t_start, t_end [s]: times of the samples that opened and closed it;
    delta_a [g]: ``Da``;
    slip [-] and slip_std [-]; dphi, dphi_std [rad]; kS, kS_std [N/m] and
    phiS, phiS_std [rad] where estimated (or known: std 0), else NaN;
    change_prob [-]: probability the soil changed at this cycle (default
    method; NaN otherwise); slip_ref [-]: the reference slip given with
    this cycle's samples (the most frequent finite one; NaN: none), whether used or not;
    used_reference: the estimator learnt the soil from it; n_samples:
    samples in the cycle; quality: ``"ok"``, ``"repaired"`` (estimated
    without ``n_repaired`` of its samples: missing in short holes,
    unusable or isolated outliers), or why the cycle was not estimated
    (all estimated values NaN); misfit [-]: 1 when the
    model explains the cycle's features, above 1 the factor by which it
    did not and by which the likelihood was widened (NaN: not checked);
    noise [g]: the IMU noise's standard deviation the cycle was estimated with;
    discrepancy [-]: how far the recent cycles' features have been from the
    model, as a variance factor (1: no farther than clean simulated cycles;
    NaN: not checked); the likelihood was widened by the larger of misfit
    and discrepancy, and from :data:`DISCREPANCY_LEVEL` on the data are
    taken as not fitting the model (``"fit"`` in :attr:`SlipEstimator.hints`).
    """

    cycle: int
    t_end: float
    delta_a: float
    slip: float
    slip_std: float
    dphi: float
    dphi_std: float
    quality: str
    t_start: float
    kS: float
    kS_std: float
    phiS: float
    phiS_std: float
    change_prob: float
    slip_ref: float
    used_reference: bool
    n_samples: int
    misfit: float = math.nan
    noise: float = math.nan
    n_repaired: int = 0
    discrepancy: float = math.nan

    @property
    def ok(self) -> bool:
        """True when the cycle was estimated (``quality`` ``"ok"`` or ``"repaired"``)."""
        return self.quality in ESTIMATED

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def of_cycle(cls, cyc, quality: str, slip_ref: float, delta_a: float = math.nan,
                 r: CycleEstimate | None = None, noise: float = math.nan, n_repaired: int = 0) -> "Estimate":
        """The row of closed cycle ``cyc`` (a :class:`~slipest.segmentation.LegCycle`): estimated when
        ``r`` is given (``quality`` "ok" or "repaired"), else every estimated value NaN and ``quality``
        says why (with ``r`` given too for ``"misfit"``: its values are NaN but ``misfit`` and
        ``discrepancy``)."""
        r = r or _NO_ESTIMATE
        return cls(cycle=int(cyc.k), t_end=float(cyc.t_end), delta_a=delta_a, slip=r.slip, slip_std=r.slip_std,
                   dphi=r.dphi, dphi_std=r.dphi_std, quality=quality, t_start=float(cyc.t_start), kS=r.kS,
                   kS_std=r.kS_std, phiS=r.phiS, phiS_std=r.phiS_std, change_prob=r.change_prob, slip_ref=slip_ref,
                   used_reference=bool(r.used_reference), n_samples=int(cyc.n_samples), misfit=r.misfit, noise=noise,
                   n_repaired=int(n_repaired), discrepancy=r.discrepancy)


_NO_ESTIMATE = CycleEstimate.nan()


#: Column order of :class:`Estimate` (for CSV/JSON writers): the eight columns every slipest command
#: prints (``cycle, t_end, delta_a, slip, slip_std, dphi, dphi_std, quality``), then the rest.
ESTIMATE_FIELDS = tuple(f.name for f in fields(Estimate))


def _soil_from(soil) -> Soil | None:
    if soil is None or isinstance(soil, Soil):
        return soil
    if isinstance(soil, dict):
        return Soil.from_args(**soil)
    raise TypeError(f"soil must be a Soil, a dict of kS/phiS/phiD/dphi or None, not {type(soil).__name__}")


class SlipEstimator:
    """Online slip (and soil) estimation from ``(t, az, theta)`` samples; see the module docstring.

    n_legs: legs of the wheel-leg. method: ``"default"`` or ``"eq515"``.
    soil: known soil (a :class:`~slipest.inverse.base.Soil` or a dict with
    any of ``kS`` [N/m], ``phiS``, ``phiD``, ``dphi`` [rad]), or None.
    use_reference: learn the soil from reference slips (see module docstring).
    on_estimate: callable called with each :class:`Estimate` as soon as it exists.
    segmenter: options for :class:`~slipest.segmentation.CycleSegmenter`.
    estimator: options of the method's cycle estimator
    (:class:`~slipest.estimator.SoilSlipEstimator`: ``hazard``,
    ``soil_temper``, ...; :class:`~slipest.inverse.eq515.Eq515Tracker`:
    ``dphi0``, ``dphi0_std``, ``q``). model / calibration: the inverse
    model and calibration dicts to use instead of the shipped files; a
    rover model (:func:`slipest.rover.load_rover`) as ``model`` also gives
    ``method="eq515"`` its refitted calibration, removes the
    disturbance it learnt (if any) from every cycle's samples, and its
    encoder angle offset (if any) from every ``theta`` sample.
    noise: the IMU noise's standard deviation [g] when known (None: estimated
    from the data, see below).
    stuck_time, stuck_samples: a cycle holding a run of bit-identical ``az``
    lasting ``stuck_time`` [s] (at least 12 samples), or of
    ``stuck_samples`` samples when given, is a stuck sensor's: flagged
    ``"stuck"``, not estimated (:mod:`slipest.stuck`; a run at the cycle's
    largest or smallest ``az`` is a clipped sensor, not a stuck one; not
    applied when the IMU's noise is below 1 mg, where a smooth signal
    repeats itself; 0: never).

    Each cycle is taken whole, leg phase ``-pi/nL`` to ``pi/nL``: the stance
    half (from 0) holds the features, the rigid half before it, where the hub
    rides smoothly on the planted foot, measures the IMU noise
    (:func:`slipest.features.sample_noise`); the noise the features are
    referred to is the median of the last :data:`NOISE_CYCLES` cycles'
    measures (``noise_estimate``), or the cycle's own measure when it is
    a burst: above twice that median and 0.005 g more (:data:`BURST_FACTOR`,
    :data:`BURST_MARGIN`; counted, said once in :attr:`hints`), so that a
    noisy cycle among quiet ones gets the wider intervals its noise
    warrants. A burst confined to the stance is found by the same measure
    taken over the stance (above twice the median and 0.01 g more,
    :data:`STANCE_BURST_MARGIN`), and the cycle is referred to the larger
    of the two measures. A cycle whose mean leg speed lies outside
    the speeds the method's model covers (``filter.omega_range``) is flagged
    ``"speed"``, not estimated. A cycle whose mean ``az`` over the rigid
    half is not gravity (:data:`GRAVITY_RANGE`) is flagged ``"units"``; the
    likely mistake (``az`` in g, gravity removed, axis reversed; ``theta``
    in degrees for a speed 57 times too high) is said once in :attr:`hints`.
    """

    def __init__(
        self,
        n_legs: int = 4,
        method: str = "default",
        soil=None,
        use_reference: bool = False,
        on_estimate: Callable[[Estimate], None] | None = None,
        segmenter: dict | None = None,
        estimator: dict | None = None,
        model=None,
        calibration: dict | None = None,
        noise: float | None = None,
        swap_checks: bool = True,
        dequantize: bool = True,
        stuck_time: float = STUCK_TIME,
        stuck_samples: int | None = None,
    ):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, not {method!r}")
        if isinstance(n_legs, bool) or not isinstance(n_legs, (int, np.integer)) or n_legs < 1:
            raise ValueError(f"n_legs must be a whole number of legs >= 1, got {n_legs!r}")
        self.n_legs = int(n_legs)
        self.method = method
        self.soil = _soil_from(soil)
        self.use_reference = bool(use_reference)
        self.on_estimate = on_estimate
        half = math.pi / self.n_legs
        # whole cycles (the rigid half measures the noise); 'partial' and the theta-step limit refer to the
        # feature window, as for a feature-window segmenter
        self._seg_opts = {"window": (-half, half), "complete_from": 0.0, "max_dtheta": half / 10.0, **(segmenter or {})}
        self._est_opts = dict(estimator or {})
        self._model = model
        # a rover model (slipest.rover) may remove a learnt phase-locked disturbance from the samples, and an
        # encoder angle offset from theta
        self._correct = getattr(model, "sample_correction", None)
        self._theta_offset = float(getattr(model, "angle_offset", 0.0))
        # a calibrated rover model answers for its IMU's signal path: no widening for a sluggish IMU on top
        self._imu_described = bool(getattr(model, "describes_imu_path", False))
        # a rover model holds at its testbed's leg speeds (slipest.rover.surrogate.SPEED_MARGIN): say so once
        self._testbed_speeds = getattr(model, "testbed_speeds", None)
        self._calibration = calibration
        if noise is not None and not (math.isfinite(noise) and noise >= 0):
            raise ValueError(f"noise={noise} g must be a finite number >= 0")
        self.noise = noise
        self.swap_checks = bool(swap_checks)
        self.dequantize = bool(dequantize)
        if not (math.isfinite(stuck_time) and stuck_time >= 0) or stuck_samples is not None and stuck_samples < 0:
            raise ValueError(f"stuck_time={stuck_time} s and stuck_samples={stuck_samples} must be >= 0")
        self.stuck_time = float(stuck_time)
        self.stuck_samples = None if stuck_samples is None else int(stuck_samples)
        self.segmenter = CycleSegmenter(self.n_legs, **self._seg_opts)
        self._make_filter()
        self._reset_counts()
        # load the compiled feature kernel now, not on the first cycle's latency (the segmenter hands
        # over read-only arrays: numba compiles those separately)
        ph = np.linspace(-half, half, 128)
        az = np.full(ph.size, 9.81)
        tt = (ph + half) / 0.63
        for arr in (ph, az, tt):
            arr.flags.writeable = False
        cycle_features(ph, az, tt, n_legs=self.n_legs)
        sample_noise(ph, az, n_legs=self.n_legs)
        for a, b in ((ph, az), (np.array(ph), np.array(az))):  # (read-only and writable: 11 ms each when first met)
            stance_noise(a, b, n_legs=self.n_legs)
        repeat_runs(az, math.nan, 0)
        _rigid_mean(ph, az, half)
        _rigid_mean(np.array(ph), np.array(az), half)  # (and on writable ones: a cycle's samples cleaned)

    def _make_filter(self) -> None:
        """The cycle estimator of ``method`` (one place that knows the methods), checked against the geometry."""
        if self.method == "eq515":
            from slipest.inverse.eq515 import Eq515Tracker

            _check_options(Eq515Tracker, self._est_opts, self.method)
            # a rover model (slipest.rover) carries its own refitted Eq. 5.15 calibration
            calibration = self._calibration if self._calibration is not None else getattr(self._model, "eq515", None)
            if calibration is None and hasattr(self._model, "eq515"):  # a rover model without one: not the shipped
                raise ValueError(f"{getattr(self._model, 'source', 'the rover model')} holds no refitted Eq. 5.15 "
                                 "calibration: use the default method, or re-run slipest calibrate")
            self.filter = Eq515Tracker.from_calibration(self.soil, self.use_reference, calibration, **self._est_opts)
            what = "the Eq. 5.15 calibration"
        else:
            from slipest.estimator import SoilSlipEstimator

            _check_options(SoilSlipEstimator, self._est_opts, self.method)
            self.filter = SoilSlipEstimator(model=self._model, soil=self.soil, use_reference=self.use_reference,
                                            n_legs=self.n_legs, **self._est_opts)
            what = "the inverse model"
        if self.filter.model_legs != self.n_legs:
            raise ValueError(f"{what} was made for a {self.filter.model_legs}-leg wheel-leg, not {self.n_legs} legs: "
                             "recalibrate/retrain it for this geometry")

    def _reset_counts(self) -> None:
        self._ref = ReferenceTally()  # the references given since the last cycle closed
        self._prefetch_at = -math.inf  # sample time [s] of the next step getting ready for the next close
        self._prefetch_step = 0  # that step: 0 plan, 1 build, 2 touch (_warm_for_next_close)
        self._n_samples = 0
        self._n_estimates = 0
        self._n_flagged: dict[str, int] = {}
        self._n_reference = 0
        self._n_misfit = 0
        self._n_off_model = 0
        self._n_repaired_cycles = 0  # estimated cycles with samples left out
        self._n_repaired = 0  # samples left out of estimated cycles (missing, unusable, outliers)
        self._n_spikes = 0  # isolated outliers found
        self._noises: deque = deque(maxlen=NOISE_CYCLES)  # the last cycles' noise measures [g]
        self._tail = (math.nan, 0)  # the last cycle's closing run of bit-identical az: value, samples (stuck rule)
        self._noise_smooth = math.nan  # the last estimated cycle's smoothed noise [g]
        self._hints: dict[str, str] = {}
        self._timing = SwapTiming(self.n_legs) if self.swap_checks else None
        self._dequant = AngleDequantizer() if self.dequantize else None
        self._timing_shift = 0.0  # angle taken off theta for the IMU's timing so far [rad]
        self._timing_corrections = 0
        self._timing_job = None  # the last estimated cycle's samples for the swap checks, not yet looked at
        self._retimed_through = -(2**62)  # cycles up to this one were emitted before the last re-timing
        self._n_retime_dropped = 0  # cycles cut again after a re-timing, already emitted: not emitted twice
        self._n_sluggish = 0  # cycles estimated while the IMU settled slowly after the swaps (widened)
        self._n_bursts = 0  # cycles referred to their own noise, a burst above the running estimate
        #: The feature row (:data:`slipest.features.FEATURE_NAMES`) of the last cycle that reached the estimator.
        self.last_features = None

    @property
    def hints(self) -> dict:
        """What looks wrong with the input, once per kind: a sentence for people naming the likely mistake
        (``"units"``, ``"degrees"``, ``"timing"``: the IMU and the encoder disagree on the leg swaps and the
        angle was corrected), saying a rover file is used outside the leg speeds it was calibrated at
        (``"rover_speed"``), saying how the IMU or the encoder differs from the model's (``"imu"``: it does
        not settle after the leg swaps, see the module docstring; ``"encoder"``: it reports whole counts, and
        the angle is interpolated between them, :mod:`slipest.dequantize`; the kinds of :data:`MODEL_HINTS`),
        or saying that the data do not fit the model (``"fit"``, from :func:`fit_advice` as soon as it
        holds)."""
        return dict(self._hints)

    @property
    def noise_estimate(self) -> float:
        """The IMU noise's standard deviation [g] the next cycle is referred to (the given ``noise``, else the
        median of the last cycles' measures; NaN before the first)."""
        if self.noise is not None:
            return self.noise
        return float(statistics.median(self._noises)) if self._noises else math.nan  # numpy's value, 40 us less

    def reset(self) -> None:
        """Forget the stream and everything learnt (segmenter, soil filter, counters, timing correction)."""
        self.segmenter = CycleSegmenter(self.n_legs, **self._seg_opts)
        self.filter.reset()
        self._theta_offset -= self._timing_shift
        self._reset_counts()

    @property
    def counters(self) -> dict:
        """``samples``, ``cycles`` (estimates emitted), ``cycles_ok`` (estimated, repaired ones
        included), ``cycles_flagged``,
        ``flagged_<reason>`` per reason (``flagged_misfit``: not explained at all, not estimated),
        ``reference_used``, ``cycles_misfit`` (estimated cycles whose features the model did not explain,
        their intervals widened), ``cycles_off_model`` (cycles off the model: estimated ones with a misfit
        or a persistent discrepancy, see :func:`off_model`, and those flagged ``misfit``),
        ``cycles_repaired`` and ``samples_repaired`` (estimated cycles with samples left out, and how many),
        ``spikes`` (isolated outliers found), ``noise_g`` (the running noise estimate [g]),
        ``timing_corrections`` and ``timing_shift_rad`` (how often the angle was corrected for the IMU's
        timing, and the correction in force [rad], see the module docstring), ``cycles_retimed`` (the rest
        of an estimated cycle cut again on the corrected angle: not emitted twice), ``swaps_measured`` (leg
        swaps whose IMU step was found, of ``swaps_looked`` at), ``cycles_sluggish_imu`` (cycles that
        reached the estimator while the IMU settled slowly after the swaps, their likelihood widened),
        ``cycles_noise_burst`` (cycles referred to their own noise, a burst, see the class docstring),
        ``samples_interpolated`` (samples of a whole-count encoder whose angle was interpolated between its
        count changes, :mod:`slipest.dequantize`), and the segmenter's counters prefixed ``segmenter_``."""
        c = {
            "samples": self._n_samples,
            "cycles": self._n_estimates,
            "cycles_ok": self._n_estimates - sum(self._n_flagged.values()),
            "cycles_flagged": sum(self._n_flagged.values()),
            "reference_used": self._n_reference,
            "cycles_misfit": self._n_misfit,
            "cycles_off_model": self._n_off_model,
            "cycles_repaired": self._n_repaired_cycles,
            "samples_repaired": self._n_repaired,
            "spikes": self._n_spikes,
            "noise_g": self.noise_estimate,
            "timing_corrections": self._timing_corrections,
            "timing_shift_rad": self._timing_shift,
            "cycles_retimed": self._n_retime_dropped,
            "swaps_measured": self._timing.measured if self._timing is not None else 0,
            "swaps_looked": self._timing.looked if self._timing is not None else 0,
            "cycles_sluggish_imu": self._n_sluggish,
            "cycles_noise_burst": self._n_bursts,
            "samples_interpolated": self._dequant.interpolated if self._dequant is not None else 0,
        }
        for k, v in sorted(self._n_flagged.items()):
            c[f"flagged_{k}"] = v
        for k, v in self.segmenter.counters.items():
            c[f"segmenter_{k}"] = v
        return c

    # ------------------------------------------------------------------
    def _flagged(self, cyc, quality: str, ref: float, **known) -> Estimate:
        """The row of a cycle not estimated, counted by ``quality``; ``known``: what is known of it anyway
        (:meth:`Estimate.of_cycle`'s ``delta_a``, ``r``, ``noise``)."""
        self._n_flagged[quality] = self._n_flagged.get(quality, 0) + 1
        return Estimate.of_cycle(cyc, quality, ref, **known)

    def _clean(self, cyc) -> tuple:
        """The cycle's samples to estimate from: ``(t, az, theta_phase, n_repaired)``, without the unusable
        samples of its short holes (``cyc.n_missing`` counts them with the rows missing) and without its
        isolated outliers (:func:`slipest.despike.outliers`)."""
        tt, az, ph = cyc.t, cyc.az, cyc.theta_phase
        repaired = cyc.n_missing
        if repaired:
            good = self.segmenter.usable(az)
            tt, az, ph = tt[good], az[good], ph[good]
        spikes = outliers(az)
        n_spikes = int(np.count_nonzero(spikes))
        if n_spikes:
            keep = ~spikes
            tt, az, ph = tt[keep], az[keep], ph[keep]
            self._n_spikes += n_spikes
            repaired += n_spikes
        return tt, az, ph, repaired

    def _stuck(self, cyc) -> bool:
        """Whether the cycle holds a stuck sensor's run of bit-identical ``az`` (:mod:`slipest.stuck`), counted on
        from the cycle before it; every closed cycle passes here, in order."""
        n = cyc.az.size
        longest, tail = repeat_runs(cyc.az, *self._tail)
        self._tail = (float(cyc.az[-1]), tail) if n else (math.nan, 0)
        if self.stuck_samples is not None:
            need = self.stuck_samples
        elif self.stuck_time > 0:
            need = stuck_run_length(self.stuck_time, (cyc.t[-1] - cyc.t[0]) / (n - 1) if n > 1 else None)
        else:
            need = 0
        if not 0 < need <= longest:
            return False
        # a noise-free signal (a simulated log's printed digits) repeats itself where it is smooth: the rule needs
        # noise (the given, the running, else this cycle's own without its repeats; unknown: applied)
        level = self.noise_estimate
        if not math.isfinite(level):
            fresh = np.flatnonzero(np.diff(cyc.az, prepend=math.nan) != 0.0)
            level = sample_noise(cyc.theta_phase[fresh], cyc.az[fresh], n_legs=self.n_legs)
        return not level < STUCK_NOISE_MIN

    def _estimate(self, cyc, ref: float) -> Estimate:
        stuck = self._stuck(cyc)
        if cyc.quality != "ok":
            return self._flagged(cyc, cyc.quality, ref)
        if stuck:
            return self._flagged(cyc, "stuck", ref)
        half = math.pi / self.n_legs
        omega = _window_speed(cyc.t, cyc.theta_phase, half)
        lo, hi = self.filter.omega_range
        if not lo <= omega <= hi:
            if lo <= omega * math.pi / 180.0 <= hi and "degrees" not in self._hints:
                self._hints["degrees"] = (f"theta looks like it is in degrees (a leg speed of {omega:.3g} per s, "
                                          f"{omega * math.pi / 180:.3g} if degrees): slipest wants radians")
            elif self._testbed_speeds is not None and "rover_speed" not in self._hints:
                slo, shi = self._testbed_speeds
                self._hints["rover_speed"] = (
                    f"a leg speed of {omega:.3g} rad/s: the rover file was calibrated on testbed runs at "
                    f"{slo:.3g}-{shi:.3g} rad/s and holds within {lo:.3g}-{hi:.3g}, so cycles at other speeds are not "
                    "estimated (flagged 'speed'): calibrate with testbed runs at the speeds the rover drives, or "
                    "estimate without --rover")
            return self._flagged(cyc, "speed", ref)
        tt, az, ph, repaired = self._clean(cyc)
        if self._correct is not None:
            az = self._correct(ph, az)
        gravity = _rigid_mean(ph, az, half) / G
        if math.isfinite(gravity) and not GRAVITY_RANGE[0] <= gravity <= GRAVITY_RANGE[1]:
            self._hints.setdefault("units", units_hint(gravity))
            return self._flagged(cyc, "units", ref)
        if self._timing is not None:  # looked at after the estimate is out (_run_timing_job)
            self._timing_job = (cyc.k, tt, az, ph, omega, self.noise_estimate * G)
        noise = self.noise_estimate  # the running estimate before this cycle
        burst = False
        if self.noise is None:  # measured only when not given (noise_estimate then ignores the measures)
            running = noise
            measured = sample_noise(ph, az, n_legs=self.n_legs)
            if math.isfinite(measured):
                burst = math.isfinite(running) and measured > max(BURST_FACTOR * running, running + BURST_MARGIN)
                self._noises.append(measured)
            if math.isfinite(running):  # a burst on the stance alone: the rigid half, measured above, is quiet
                stance = stance_noise(ph, az, n_legs=self.n_legs)
                if stance > max(BURST_FACTOR * running, running + STANCE_BURST_MARGIN):
                    measured = stance if not burst else max(measured, stance)
                    burst = True
            noise = measured if burst else self.noise_estimate
        if burst:
            self._n_bursts += 1
            self._hints.setdefault("noise", (
                f"a cycle's IMU noise ({measured:.3f} g) was more than twice the running estimate ({running:.3f} g): a "
                "burst of vibration or interference; such cycles are referred to their own noise, their intervals "
                "wider (counted: cycles_noise_burst)"))
        try:
            f = cycle_features(ph, az, tt, n_legs=self.n_legs, noise=noise if math.isfinite(noise) else None)
        except ValueError:
            return self._flagged(cyc, "features", ref)
        if not all(map(math.isfinite, f.tolist())):  # (numpy's reductions cost more on 20 values)
            return self._flagged(cyc, "features", ref)
        self.last_features = f
        use = self.use_reference and math.isfinite(ref)
        widen = 1.0
        if self._timing is not None and self._timing.sluggish and not self._imu_described:
            widen = SLUGGISH_WIDENING
            self._n_sluggish += 1
            self._hints.setdefault("imu", (
                "after each leg swap the IMU does not settle at the new leg's rigid level as the model's does "
                f"({self._timing.settling:.0%} of the step is left 10-60 ms after it, where the model leaves "
                "none): an IMU low-pass filter (below about 7 Hz), a soft mount or touchdown impacts the model "
                "does not know; intervals widened, and slipest calibrate would learn it"))
        r = self.filter.update(f, ref if use else None, widen)
        if r.misfit > 1.0 and math.isnan(r.slip):  # not explained at all (SoilSlipEstimator.gross_misfit)
            self._off_model()
            return self._flagged(cyc, "misfit", ref, delta_a=float(f[_DELTA_A]), r=r, noise=float(f[_NOISE]))
        if r.used_reference:
            self._n_reference += 1
        if r.misfit > 1.0:
            self._n_misfit += 1
        if off_model(r.misfit, r.discrepancy):
            self._off_model()
        if repaired:
            self._n_repaired_cycles += 1
            self._n_repaired += repaired
        if not burst:  # (the next cycle's table is prepared for the running noise)
            self._noise_smooth = float(f[_NOISE_SMOOTH])
        return Estimate.of_cycle(cyc, "repaired" if repaired else "ok", ref, float(f[_DELTA_A]), r, float(f[_NOISE]),
                                 repaired)

    def _off_model(self) -> None:
        """Count the cycle being estimated as off the model (before it is counted as estimated or flagged); the
        ``"fit"`` hint once :func:`fit_advice` holds."""
        self._n_off_model += 1
        if "fit" not in self._hints:
            # the cycles that reached the estimator so far, this one included
            n = self._n_estimates - sum(self._n_flagged.values()) + self._n_flagged.get("misfit", 0) + 1
            advice = fit_advice(n, self._n_off_model)
            if advice:
                self._hints["fit"] = advice

    def _emit(self, cycles, refs, defer: bool = False) -> tuple[list, int | None]:
        """The estimates of ``cycles``, in order, and the index of the cycle after which theta was re-timed
        (None: not). After each estimate the swap checks look at its cycle (now, or with ``defer`` when the
        next sample comes, :meth:`push`: off the closing sample's latency); when they re-time theta, stops
        there (the later cycles were cut on the old angle: the caller pushes their samples again, see
        :meth:`push_many`)."""
        out = []
        for i, (cyc, ref) in enumerate(zip(cycles, refs)):
            if self._run_timing_job():  # a deferred look at the previous cycle re-timed theta before this one
                return out, i - 1
            if cyc.k <= self._retimed_through:  # the rest of a cycle already estimated, seen again re-timed
                self._n_retime_dropped += 1
                self._retimed_through = -(2**62)  # only the first cycle after a re-timing (a restart may go back)
                continue
            self._retimed_through = -(2**62)
            if self._timing is not None and cyc.quality != "ok":
                self._timing.forget_tail()
            e = self._estimate(cyc, ref)
            self._n_estimates += 1
            if self.on_estimate is not None:
                self.on_estimate(e)
            out.append(e)
            if not defer and self._run_timing_job():
                return out, i
        return out, None

    def _run_timing_job(self) -> bool:
        """The swap checks on the last estimated cycle, if not done yet; True when they re-timed theta (from
        the sample after that cycle's closing one)."""
        job, self._timing_job = self._timing_job, None
        if job is None:
            return False
        shift = self._timing.add_cycle(*job)
        if shift is None:
            return False
        self._retime(job[0], shift)
        return True

    def _retime(self, cycle: int, shift: float) -> None:
        """Take the timing correction ``shift`` [rad, in all] off theta from the next sample on (the caller
        re-synchronises the segmenter after the closing sample of ``cycle``: the open cycle is dropped)."""
        self._theta_offset += shift - self._timing_shift
        self._timing_shift = shift
        self._timing_corrections += 1
        self._retimed_through = cycle
        tm = self._timing
        what = (f"{1e3 * abs(tm.offset):.0f} ms {'after' if tm.offset > 0 else 'before'} the encoder does, at any "
                f"leg speed (a time skew between IMU and encoder)" if tm.model == "time" else
                f"{abs(tm.offset):.3f} rad of leg angle {'after' if tm.offset > 0 else 'before'} the encoder does (an "
                f"encoder zero offset)")
        self._hints["timing"] = (f"the IMU sees the leg swaps {what}: theta corrected for it from cycle {cycle + 1} "
                                 "on; fix the encoder zero or the time stamps, or calibrate the rover (slipest "
                                 "calibrate)")

    def push(self, t: float, az: float, theta: float, slip_ref: float | None = None) -> list:
        """Add one sample (``t`` [s], ``az`` [m/s^2], ``theta`` [rad], optional reference slip [-]).

        Returns the estimates of the cycles it closed (usually none, at most one or two).
        """
        t, az, theta = float(t), float(az), float(theta)  # (TypeError or ValueError here, nothing counted)
        self._n_samples += 1
        if self._dequant is not None:  # a whole-count encoder: its samples come out a count later
            held = self._dequant.push(t, az, theta, math.nan if slip_ref is None else slip_ref)
            if held is not None:
                self._encoder_hint()
                out = self._push_chunk(*held) if held[0].size else []
                if out:
                    self._plan_prefetch(out[-1])
                elif held[0].size:
                    self._warm_for_next_close(float(held[0][-1]))
                return out
        if self._timing_job is not None and self._run_timing_job():  # re-timed: this sample starts the stream again
            self.segmenter.resync()
        cycles = self.segmenter.push(t, az, theta - self._theta_offset)
        out = []
        if cycles:
            out, retimed = self._emit(cycles, [self._ref.take()] + [math.nan] * (len(cycles) - 1), defer=True)
            if retimed is not None:  # re-timed (two cycles closed at once): as above
                self.segmenter.resync()
            self._plan_prefetch(cycles[-1])
        else:
            self._warm_for_next_close(t)
        if slip_ref is not None:
            self._ref.add(float(slip_ref))
        return out

    def _plan_prefetch(self, last) -> None:
        """After the cycle ``last`` (a cycle or an estimate: ``t_start``, ``t_end`` [s]) closed: plan the next."""
        self._prefetch_at = last.t_end + PREFETCH_PLAN * (last.t_end - last.t_start)
        self._prefetch_step = 0

    def _warm_for_next_close(self, t: float) -> None:
        """Get the estimator's table for the next close built and warm before it (sample time ``t`` [s]; the
        steps are those of :data:`PREFETCH_PLAN`, :data:`PREFETCH_BUILD`, :data:`PREFETCH_TOUCH`)."""
        if t < self._prefetch_at:
            return
        wt, waz, wph = self.segmenter.open_window()
        half = math.pi / self.n_legs
        speed = (wph[-1] - wph[0]) / (wt[-1] - wt[0]) if wt.size >= 2 and wt[-1] > wt[0] else math.nan
        if not speed > 0.0:  # nothing to predict the close from yet (a new stream, a stop): look again soon
            self._prefetch_at = t + PREFETCH_RETRY
            return
        left = (half - wph[-1]) / speed  # to the predicted close [s]
        duration = 2.0 * half / speed  # of the open cycle at this speed [s]
        if self._prefetch_step == 0:
            self._prefetch_step = 1
            if left > PREFETCH_BUILD * duration:
                self._prefetch_at = t + left - PREFETCH_BUILD * duration
                return
        ws = _window_speed(wt, wph, half)
        noise = self._noise_smooth
        if not math.isfinite(noise):  # no cycle estimated yet: the open cycle's own noise, its rigid half done
            measured = self.noise if self.noise is not None else sample_noise(wph, waz, n_legs=self.n_legs)
            noise = smoothed_noise(measured, (wt.size - 1) / (wt[-1] - wt[0]))
        self.filter.prefetch(ws if math.isfinite(ws) else speed, noise)
        if self._prefetch_step == 1 and left > PREFETCH_TOUCH * duration:
            self._prefetch_step = 2
            self._prefetch_at = t + left - PREFETCH_TOUCH * duration
        else:
            self._prefetch_at = math.inf

    def push_many(self, t, az, theta, slip_ref=None, warm: bool = False) -> list:
        """Add arrays of samples (and optionally one reference slip per sample, NaN: none).

        Returns the estimates of the cycles they closed, in order: exactly
        what :meth:`push` on each sample would have returned. ``warm``: then
        get ready for the next close as :meth:`push` does after each sample
        (its table built and in the caches before the closing sample comes):
        for a live stream that comes in chunks; a replay gains nothing from it.
        """
        t = np.ascontiguousarray(t, dtype=np.float64)
        az = np.ascontiguousarray(az, dtype=np.float64)
        theta = np.ascontiguousarray(theta, dtype=np.float64)
        if t.ndim != 1 or az.shape != t.shape or theta.shape != t.shape:
            raise ValueError(
                f"push_many() needs equal-length 1-D arrays, got t{t.shape}, az{az.shape}, theta{theta.shape}")
        if slip_ref is not None:
            slip_ref = np.asarray(slip_ref, dtype=float)
            if slip_ref.shape != t.shape:
                raise ValueError(f"slip_ref must have the shape of t {t.shape}, got {slip_ref.shape}")
        self._n_samples += t.size
        if self._dequant is not None:  # a whole-count encoder: its samples come out a count later
            t, az, theta, slip_ref = self._dequant.feed(t, az, theta, slip_ref)
            if self._dequant.active:
                self._encoder_hint()
            if t.size == 0:
                return []
        out = self._push_chunk(t, az, theta, slip_ref)
        if warm and np.ndim(t) == 1 and np.size(t):
            if out:
                self._plan_prefetch(out[-1])
            self._warm_for_next_close(float(t[-1]))
        return out

    def _encoder_hint(self) -> None:
        """Say once that the encoder counts whole steps and its angle is interpolated."""
        if "encoder" not in self._hints:
            step = self._dequant.step
            self._hints["encoder"] = (f"the encoder reports whole counts of {step:.4g} rad (about "
                                      f"{2 * math.pi / step:.0f} a revolution): the leg angle is interpolated "
                                      "between its count changes, and each estimate comes up to one count later")

    def _push_chunk(self, t, az, theta, slip_ref) -> list:
        """:meth:`push_many` after the checks; when a cycle re-times theta, the samples after its closing
        sample are pushed again on the new angle, as :meth:`push` would have taken them."""
        if self._timing_job is not None and self._run_timing_job():  # left by push(): re-timed before this chunk
            self.segmenter.resync()
        shifted = np.asarray(theta, dtype=np.float64) - self._theta_offset if self._theta_offset else theta
        snap = self.segmenter.snapshot() if self._timing is not None else None
        cycles = self.segmenter.push_many(t, az, shifted)
        if not cycles:
            if slip_ref is not None:
                self._ref.add_many(slip_ref)
            return []
        # index of each cycle's closing sample in the chunk (first sample at or after the previous one's with
        # t == t_end; -1: closed by the same sample as the previous cycle, as skipped cycles are)
        ends = []
        start = 0
        for j, cyc in enumerate(cycles):
            hit = np.flatnonzero(t[start:] == cyc.t_end)
            if hit.size == 0 or j > 0 and cycles[j - 1].t_end == cyc.t_end:
                ends.append(-1)
                continue
            start += int(hit[0])
            ends.append(start)
        if slip_ref is None:
            refs = [math.nan] * len(cycles)
            refs[0] = self._ref.take()
        else:
            refs = []
            start = 0
            for end in ends:
                if end < 0:
                    refs.append(math.nan)
                    continue
                self._ref.add_many(slip_ref[start:end])
                refs.append(self._ref.take())
                start = end
            self._ref.add_many(slip_ref[start:])
        out, retimed = self._emit(cycles, refs)
        if retimed is not None:  # re-timed after cycles[retimed]
            j = max(ends[:retimed + 1])
            # the segmenter as it was after the closing sample (the cycles it closes again are the ones emitted)
            self.segmenter.restore(snap)
            self.segmenter.push_many(t[:j + 1], np.asarray(az)[:j + 1], np.asarray(shifted)[:j + 1])
            self.segmenter.resync()
            if slip_ref is not None:  # the references from the closing sample on are the next cycle's again
                self._ref = ReferenceTally()
                self._ref.add(float(slip_ref[j]))
            rest = slice(j + 1, None)
            out += self._push_chunk(t[rest], np.asarray(az)[rest], np.asarray(theta)[rest],
                                    None if slip_ref is None else slip_ref[rest])
        return out

    def finish(self) -> list:
        """Say the stream ended: the estimate of its last cycle, which no sample will close (``"partial"`` when
        the stream stopped inside its window; see :meth:`slipest.segmentation.CycleSegmenter.finish`). Samples
        pushed afterwards start a new stream; the soil filter keeps what it learnt."""
        out = []
        if self._dequant is not None:  # the last count's samples, held for a change that will not come
            held = self._dequant.flush()
            if held is not None and held[0].size:
                out = self._push_chunk(*held)
        cycles = self.segmenter.finish()
        ref = self._ref.take()
        last, _ = self._emit(cycles, [ref] * len(cycles))
        out += last
        self._run_timing_job()  # (the next sample starts a new stream anyway)
        self._prefetch_at, self._prefetch_step = -math.inf, 0  # the new stream's first close is planned too
        return out

    def iter_estimates(self, chunks: Iterable) -> Iterator[Estimate]:
        """Estimates over an iterable of sample chunks, as they come.

        A chunk is ``(t, az, theta)`` or ``(t, az, theta, slip_ref)`` arrays,
        or any object with ``t``, ``az``, ``theta`` (and optionally ``slip``)
        attributes (e.g. :class:`slipest.io.log_csv.LogChunk`,
        :class:`slipest.model.stream.SampleChunk`). When the chunks run out,
        the stream has ended (:meth:`finish`).
        """
        for ch in chunks:
            if isinstance(ch, tuple):
                yield from self.push_many(*ch)
            else:
                yield from self.push_many(ch.t, ch.az, ch.theta, getattr(ch, "slip", None))
        yield from self.finish()


__all__ = ["Estimate", "ESTIMATE_FIELDS", "METHODS", "SlipEstimator", "fit_advice", "off_model"]
