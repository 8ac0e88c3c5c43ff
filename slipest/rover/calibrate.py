"""Calibrating the estimator to one rover from its testbed logs: the whole procedure (pure computation).

Input: one or more runs of the rover (samples ``t`` [s], ``az`` [m/s^2],
``theta`` [rad] and the reference ``slip`` [-] of every cycle), each on
its own unknown soil, and the rover's known hardware
(:class:`~slipest.diagnosis.fit.Geometry`). :func:`calibrate`:

1. cuts every run into leg cycles and computes their features through the
   estimator's own path (:class:`~slipest.rover.testbed.TestbedLog`); the
   shipped model's blind estimates of them are the *before* figures;
2. diagnoses every run on its own (:func:`slipest.diagnosis.run.diagnose`:
   one soil per run): ``kappa``, the catalog effect it names with fitted
   parameters, the held-out waveform gap before and after;
3. for every effect named (and a nominal model at another ``kappa`` when
   every run says ``none`` at a ``kappa`` away from the model's), simulates
   a batch of cycles with it on soils over the whole grid and fits the
   physics discrepancy (:mod:`slipest.rover.physics`) and its extra
   covariance; uses the effect the diagnosis named unless the blind
   estimates of the testbed runs (soil unknown, reference ignored, as on a
   drive) get worse by more than :data:`MAX_LOSS`, else an effect it did not
   name if those beat the shipped model's by :data:`MIN_GAIN` (:func:`_choose`).
   An effect that only adds to ``az`` (a touchdown impact) is also tried
   removed from the samples (its waveform over the leg phase at the
   testbed's speed), and one that only moves the angle (an encoder offset,
   a time skew) removed from ``theta``; the blind estimates choose between
   the two forms.
   When no named effect explains a log well (shrink below
   :data:`WELL_EXPLAINED`), a phase-locked ``az`` disturbance learnt from the
   logs' waveforms (:mod:`slipest.rover.waveform`) is a candidate too, as if
   named when it shrinks their held-out gaps by :data:`DISTURBANCE_SHRINK`:
   the rover model then removes it from the samples;
4. on top, a correction in slip alone learnt from the testbed cycles with
   each run's soil estimated jointly (:func:`~slipest.rover.fit.fit_testbed_discrepancy`),
   kept only when it improves the blind estimates of runs it was not fitted
   on (leave one run out; with one run, held-out slip levels);
5. widens the covariance by what the held-out slip levels still scatter
   beyond it (:func:`covariance_factor`: the median of their squared
   whitened residuals against a chi-square's, each log's soil fitted on its
   other levels);
6. scales the estimator's standard deviations so that the blind estimates
   of held-out runs (each run estimated without what was fitted on it)
   cover 95 % of their reference slips, never below 1 (:func:`_interval_scale`);
7. refits Eq. 5.15 on the runs' ``Da`` and slips on the soils found
   (:mod:`slipest.rover.eq515`).

The result (:class:`Calibration`) holds the rover model (a
:class:`~slipest.rover.surrogate.RoverSurrogate`) and a report (a JSON-able
dict: what was found, the held-out figures before and after, what is left
unexplained). Progress goes through ``progress(done, total, label)`` per
stage. Design and measurements: ``docs/calibration.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.stats import chi2

from slipest.diagnosis.fit import Geometry
from slipest.inverse.surrogate import whitener
from slipest.rover.discrepancy import Discrepancy
from slipest.rover.fit import (
    LogSoil,
    blind_errors,
    blind_score,
    fit_testbed_discrepancy,
    log_residuals,
    log_soil,
    whitened_sq,
    with_discrepancy,
)
from slipest.rover.physics import effect_batch, fit_effect_discrepancy
from slipest.rover.surrogate import RoverSurrogate
from slipest.rover.testbed import MIN_HELDOUT_LEVELS, TestbedLog

#: ``progress(done, total, label)``: work done of the current stage's total, and what is running.
Progress = Callable[[int, int, str], None]

#: A candidate the diagnosis did not name must lower the testbed runs' blind slip RMSE by this fraction to be used.
MIN_GAIN = 0.1
#: The effect the diagnosis named is used unless it raises the testbed runs' blind slip RMSE by more than this
#: fraction (the waveform gap it shrank is stronger evidence than a few blind estimates of easy testbed cycles).
MAX_LOSS = 0.25
#: Held-out testbed cycles needed to learn the rover model's interval scale (fewer: it stays 1).
MIN_SCALE_CYCLES = 20
#: A nominal candidate at the diagnosed ``kappa`` is tried when it differs from the model's by more than this.
KAPPA_TOLERANCE = 0.04
#: The model's own ``kappa`` (the shipped surrogate was trained with it).
MODEL_KAPPA = 0.3
#: An effect the diagnosis ranks first without naming it is still tried when it shrinks the gap this much.
PARTIAL_SHRINK = 0.3
#: A disturbance learnt from the waveforms is learnt when no named effect shrank a log's gap this much ...
WELL_EXPLAINED = 0.98
#: ... and counts as named (as an effect the diagnosis names) when it shrinks the logs' held-out gaps this much;
#: against a named catalog effect it must leave at most this share of the gap the effect leaves (the effect's
#: physics carries to other soils, a mean waveform may not).
DISTURBANCE_SHRINK = 0.5
DISTURBANCE_GAP_RATIO = 0.5


@dataclass(frozen=True)
class TestbedRun:
    """One testbed run: a name for messages and its samples (``t`` [s], ``az`` [m/s^2], ``theta`` [rad],
    ``slip`` [-])."""

    name: str
    t: np.ndarray
    az: np.ndarray
    theta: np.ndarray
    slip: np.ndarray


@dataclass(frozen=True)
class CalibrateOptions:
    """diagnose: run the diagnosis (off: the correction is learnt from the testbed cycles alone). quick:
    the diagnosis's half budget. effects: catalog effects the diagnosis tries (None: all). batch: simulated
    cycles per candidate effect. degree: total degree of the physics discrepancy. testbed_degree: degree in
    slip of the testbed correction. seed: of the optimiser and the batches. blind_start: cycles of a run
    before its blind estimates are scored (the soil is learnt first)."""

    diagnose: bool = True
    quick: bool = True
    effects: tuple | None = None
    batch: int = 1500
    degree: int = 4
    testbed_degree: int = 2
    seed: int = 0
    blind_start: int = 9


@dataclass
class Candidate:
    """A correction tried: ``effects`` (catalog specs), ``kappa``, where it came from, its model and scores."""

    label: str
    effects: tuple
    kappa: float
    origin: str
    named: bool = False
    shrink: float = 0.0
    disturbance: dict | None = None
    angle_offset: float = 0.0
    learnt: bool = False
    model: object = None
    logs: list | None = None
    scores: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def corrects_samples(self) -> bool:
        """Its model corrects the samples (a disturbance removed from ``az``, an offset from ``theta``)."""
        return self.disturbance is not None or self.angle_offset != 0.0

    def choice_rmse(self, spread: float) -> float:
        """:func:`_choice_rmse` of its blind scores."""
        return _choice_rmse(self.scores, spread)


@dataclass
class Calibration:
    """What :func:`calibrate` found: the rover ``model`` and its ``report`` (see the module docstring)."""

    model: RoverSurrogate
    report: dict


def _mean_rmse(scores) -> float:
    """RMS over runs of their blind slip RMSE (weighted by their scored cycles)."""
    n = np.array([s["n"] for s in scores], dtype=float)
    r = np.array([s["slip_rmse"] for s in scores], dtype=float)
    ok = np.isfinite(r) & (n > 0)
    return float(np.sqrt(np.sum(n[ok] * r[ok] ** 2) / np.sum(n[ok]))) if ok.any() else math.nan


def _mean_coverage(scores) -> float:
    n = np.array([s["n"] for s in scores], dtype=float)
    c = np.array([s["coverage"] for s in scores], dtype=float)
    ok = np.isfinite(c) & (n > 0)
    return float(np.sum(n[ok] * c[ok]) / np.sum(n[ok])) if ok.any() else math.nan


def _choice_rmse(scores, spread: float) -> float:
    """What the choices compare: the blind slip RMSE over every scored cycle, a cycle the model did not
    estimate counting as ``spread`` (the slip's prior spread: what is known of a cycle not estimated), so a
    model that estimates few cycles well does not beat one that estimates them all."""
    n = np.array([s["n"] for s in scores], dtype=float)
    r = np.array([s["slip_rmse"] for s in scores], dtype=float)
    scored = np.array([s["n_scored"] for s in scores], dtype=float)
    sq = np.where(n > 0, n * np.nan_to_num(r) ** 2, 0.0) + (scored - n) * spread**2
    return float(np.sqrt(np.sum(sq) / np.sum(scored))) if np.sum(scored) > 0 else math.nan


def _slip_spread(model) -> float:
    """The standard deviation of slip uniform over the model's slip range [-]."""
    return float(model.halfwidth[0]) / math.sqrt(3.0)


def _figures(scores) -> dict:
    return {"slip_rmse": _mean_rmse(scores), "coverage": _mean_coverage(scores),
            "estimated": float(sum(s["n"] for s in scores) / max(1, sum(s["n_scored"] for s in scores))),
            "per_run": [{k: s[k] for k in ("slip_rmse", "coverage", "bias", "n", "n_scored")} for s in scores]}


def _stage(progress: Progress | None, done: int, total: int, label: str) -> None:
    if progress is not None:
        progress(done, total, label)


def diagnose_runs(runs, geometry: Geometry, options: CalibrateOptions, progress: Progress | None = None) -> list:
    """The diagnosis of every run on its own (one soil each): a list of
    :class:`~slipest.diagnosis.run.Diagnosis` (None for a run it could not cut into cycles, with why)."""
    from slipest.diagnosis.cycles import cut_cycles
    from slipest.diagnosis.fit import FitBudget
    from slipest.diagnosis.predict import Grid
    from slipest.diagnosis.run import diagnose, planned_units

    budget = FitBudget().scaled(0.5) if options.quick else FitBudget()
    per_run = planned_units(options.effects or _all_effects(), budget)
    total = per_run * len(runs)
    out = []
    for j, run in enumerate(runs):
        cycles = cut_cycles(run.t, run.az, run.theta, run.slip, geometry.nL, grid=Grid(geometry.nL), log_index=0)

        def tick(done, _total, label, j=j):
            _stage(progress, j * per_run + min(done, per_run), total, f"diagnosing {runs[j].name}: {label}")

        out.append(diagnose(cycles, geometry, options.effects, seed=options.seed, budget=budget, progress=tick))
    return out


def _all_effects():
    from slipest.model.effects import ORDER

    return ORDER


def _effect_candidates(diagnoses, runs) -> list[Candidate]:
    """Effects the diagnoses name (or rank first with a partial shrink), one candidate per effect (the
    parameters of the run whose fit shrank its gap most), and a nominal model at the diagnosed ``kappa``
    when every run says ``none`` away from the model's."""
    best: dict = {}
    for run, d in zip(runs, diagnoses):
        if d is None or not d.ranking:
            continue
        top = d.ranking[0]
        if d.verdict != top.effect and top.shrink < PARTIAL_SHRINK:
            continue
        kappa = float(d.fits[top.effect].values["kappa"]) if top.effect in d.fits else float(d.nominal.values["kappa"])
        named = d.verdict == top.effect
        key = top.effect
        if key not in best or (named, top.shrink) > (best[key][1].named, best[key][0]):
            spec = {"name": top.effect, **top.params}
            origin = f"{'named' if named else 'ranked first (not named)'} in {run.name}, shrink {top.shrink:.0%}"
            best[key] = (top.shrink, Candidate(top.effect, (spec,), kappa, origin, named, float(top.shrink)))
    out = [c for _, c in best.values()]
    nominal = [d for d in diagnoses if d is not None and d.verdict == "none"]
    if nominal and len(nominal) == len(diagnoses):
        kappa = float(np.median([d.nominal.values["kappa"] for d in nominal]))
        if abs(kappa - MODEL_KAPPA) > KAPPA_TOLERANCE:
            out.append(Candidate(f"kappa {kappa:.2f}", (), kappa, "the nominal fits' kappa"))
    return out


def _removal_candidates(cands, logs, n_legs: int) -> list[Candidate]:
    """For each effect candidate that only adds to ``az`` (:func:`slipest.rover.waveform.effect_disturbance`:
    a touchdown impact) or only moves the angle (:func:`slipest.rover.waveform.effect_angle_offset`: an
    encoder offset, a time skew at the testbed's leg speed), the same effect removed from the samples instead
    of modelled as a feature discrepancy: as named as the effect, with its shrink."""
    from slipest.rover.waveform import effect_angle_offset, effect_disturbance

    omega = float(np.median([lg.omega for lg in logs]))
    out = []
    for c in cands:
        if c.corrects_samples or not c.effects:
            continue
        origin = f"{c.origin}; removed from the samples"
        offset = effect_angle_offset(c.effects, omega, n_legs)
        if offset is not None:
            if offset != 0.0:  # (an offset of zero removes nothing: the effect's candidate is the shipped model)
                out.append(Candidate(f"{c.label} removed", c.effects, c.kappa, origin, c.named, c.shrink,
                                     angle_offset=offset))
            continue
        wave = effect_disturbance(c.effects, omega, n_legs)
        if wave is not None:
            out.append(Candidate(f"{c.label} removed", c.effects, c.kappa, origin, c.named, c.shrink,
                                 disturbance={"phase": wave[0].tolist(), "az": wave[1].tolist()}))
    return out


def _disturbance_candidate(diagnoses, geometry: Geometry, options: CalibrateOptions, progress: Progress | None,
                           runs, base, n_legs: int) -> Candidate | None:
    """A phase-locked ``az`` disturbance learnt from each diagnosed log's training cycles (their mean,
    :func:`slipest.rover.waveform.learn_disturbance`, as a band-limited waveform,
    :func:`~slipest.rover.waveform.band_limited`), removed from the samples, with the testbed logs'
    features recomputed through the correction (``cand.logs``): no candidate when it shrinks the logs'
    held-out gaps by less than :data:`PARTIAL_SHRINK` on average, a named one (as an effect the diagnosis
    names) from :data:`DISTURBANCE_SHRINK`."""
    from slipest.rover.waveform import band_limited, learn_disturbance

    done = [d for d in diagnoses if d is not None]
    if not done:
        return None
    learnt = []
    for k, d in enumerate(done):
        _stage(progress, k, len(done), "learning the waveform disturbance")
        learnt.append(learn_disturbance(d, geometry, seed=options.seed))
    shrink = float(np.mean([x.shrink for x in learnt]))
    if shrink < PARTIAL_SHRINK:
        return None  # it does not explain the held-out cycles: not a disturbance locked to the phase
    # the logs' mean over the diagnosis's bins, as the band-limited waveform with those bin averages (an
    # oscillation of a few bins per period keeps its amplitude)
    phases, wave = band_limited(learnt[0].phases, np.mean([x.values for x in learnt], axis=0), n_legs)
    rms = float(np.sqrt(np.mean(wave**2))) / 9.81 * 1000
    cand = Candidate("learnt disturbance", (), float(np.median([x.kappa for x in learnt])),
                     f"the logs' mean residual waveform (RMS {rms:.0f} mg), held-out gap shrink {shrink:.0%}",
                     named=shrink >= DISTURBANCE_SHRINK, shrink=shrink, learnt=True)
    cand.disturbance = {"phase": phases.tolist(), "az": wave.tolist(),
                        "heldout_gap_g": [[x.gap_nominal, x.gap_after] for x in learnt]}
    return cand


def _choose(cands, shipped_rmse: float, spread: float):
    """The candidate to use, or None: the effect the diagnosis named (the one whose fit shrank the held-out gap
    most; a learnt disturbance must leave at most :data:`DISTURBANCE_GAP_RATIO` of the gap an effect leaves),
    unless its blind estimates of the testbed logs are worse than the shipped model's by more than
    :data:`MAX_LOSS`; otherwise a candidate not named (ranked first, or a nominal ``kappa``) whose blind
    estimates beat the shipped model's by :data:`MIN_GAIN`, the best of them. Blind estimates are compared
    by :func:`_choice_rmse` (``shipped_rmse`` too), ``spread`` standing for a cycle not estimated."""
    def left(c):  # the share of the held-out gap it leaves, a learnt disturbance's counted against an effect's
        return (1.0 - c.shrink) / (DISTURBANCE_GAP_RATIO if c.learnt else 1.0)

    # an effect as a feature discrepancy and removed from the samples leave the same gap: the blind estimates
    # of the testbed logs decide between them
    named = sorted((c for c in cands if c.named), key=lambda c: (left(c), c.choice_rmse(spread)))
    for c in named:
        if c.choice_rmse(spread) <= (1.0 + MAX_LOSS) * shipped_rmse:
            return c
    others = [c for c in cands if not c.named and c.choice_rmse(spread) < (1.0 - MIN_GAIN) * shipped_rmse]
    return min(others, key=lambda c: c.choice_rmse(spread)) if others else None


def _build_candidate(base, cand: Candidate, logs, options: CalibrateOptions, n_legs: int, rng, runs=()) -> None:
    """The candidate's model and blind scores (in place): a sample correction's model (a disturbance removed
    from ``az``, an offset from ``theta``) applies it to the samples (the testbed logs' features recomputed
    through it: ``cand.logs``); an effect's simulates its batch and fits the discrepancy and extra covariance."""
    t0 = time.perf_counter()
    if cand.corrects_samples:
        zero = Discrepancy.zero(base.features, base.center[:4], base.halfwidth[:4])
        disturbance = None if cand.disturbance is None else {k: cand.disturbance[k] for k in ("phase", "az")}
        cand.model = RoverSurrogate.of(base, zero, np.zeros((len(base.features),) * 2), rover_legs=n_legs,
                                       disturbance=disturbance, angle_offset=cand.angle_offset)
        cand.logs = [TestbedLog.from_samples(r.name, r.t, r.az, r.theta, r.slip, n_legs, model=cand.model)
                     for r in runs]
        cand.scores = [blind_score(cand.model, lg, options.blind_start, n_legs) for lg in cand.logs]
        cand.seconds = time.perf_counter() - t0
        return
    omega = float(np.median([lg.omega for lg in logs]))
    noise = float(np.median([lg.noise for lg in logs]))
    rate = float(np.median([lg.rate for lg in logs]))
    x4, feats = effect_batch(cand.effects, options.batch, rng, omega=omega, rate=rate, noise_g=noise,
                             kappa=cand.kappa, n_legs=n_legs)
    disc, left = fit_effect_discrepancy(base, x4, feats, options.degree)
    q = _extra_cov(base.cov(omega, float(np.median([lg.noise_smooth for lg in logs]))), left)
    cand.model = RoverSurrogate.of(base, disc, q, rover_legs=n_legs)
    cand.scores = [blind_score(cand.model, lg, options.blind_start, n_legs) for lg in logs]
    cand.seconds = time.perf_counter() - t0


def _extra_cov(r: np.ndarray, resid: np.ndarray) -> np.ndarray:
    """What the residuals ``(n, d)`` scatter beyond ``r``: the positive part of their covariance in ``r``'s
    whitened frame, mapped back (feature units^2)."""
    w = whitener(r)
    c = np.cov((resid @ w).T, bias=True) if len(resid) > 1 else np.zeros((r.shape[0],) * 2)
    ev, vec = np.linalg.eigh(0.5 * (c + c.T))
    ev = np.maximum(ev - 1.0, 0.0)
    wi = np.linalg.inv(w.T)
    q = wi @ (vec * ev) @ vec.T @ wi.T
    return 0.5 * (q + q.T)


def _heldout_split(logs):
    """Per log, the held-out slip levels (boolean) and the training log."""
    held = [lg.heldout_levels() for lg in logs]
    return held, [lg.subset(~h) for lg, h in zip(logs, held)]


def _heldout_sq(model, logs) -> np.ndarray:
    """Each held-out cycle's squared whitened residual ``(n,)`` (:func:`whitened_sq`; the held-out cycles are
    each log's ``TestbedLog.heldout_levels``, its soil fitted on its training cycles)."""
    sq = []
    for lg in logs:
        h = lg.heldout_levels()
        soil = log_soil(model, lg, keep=~h)
        ho = lg.subset(h)
        sq.append(whitened_sq(model, ho, log_residuals(model, ho, soil)))
    return np.concatenate(sq) if sq else np.zeros(0)


def _feature_misfit(model, logs) -> float:
    """Mean squared whitened residual per feature of the logs' held-out cycles (:func:`_heldout_sq`; 1:
    explained within the model's scatter). The report's figure; NaN without held-out cycles."""
    sq = _heldout_sq(model, logs)
    return float(np.mean(sq) / len(model.features)) if sq.size else math.nan


def covariance_factor(sq, n_features: int) -> float:
    """The factor (at least 1) on the feature covariance that the held-out cycles' squared whitened residuals
    ``sq`` call for: their median over the median of a chi-square with ``n_features`` degrees of freedom, so
    that one or two cycles far off the model (a log's glitch, a soil the correction missed) do not widen
    every cycle's likelihood; what they cost in coverage is the interval scale's to cover. 1 without cycles."""
    sq = np.asarray(sq, dtype=float)
    sq = sq[np.isfinite(sq)]
    if not sq.size:
        return 1.0
    return max(1.0, float(np.median(sq) / chi2.ppf(0.5, n_features)))


def _testbed_layer(model: RoverSurrogate, logs, options: CalibrateOptions, n_legs: int) -> dict:
    """The correction in slip alone: its held-out test (leave one run out, or held-out levels with one run)
    and, when it helps, the fit on every run. Returns ``{"used", "heldout_without", "heldout_with",
    "discrepancy", "soils", "heldout"}``; ``heldout``: per run, the correction fitted without it (or without
    its held-out levels) and the cycles it is scored on (None: from ``blind_start``; else a boolean mask)."""
    base_scores, with_scores, heldout = [], [], []
    if len(logs) >= 2:
        for j, lg in enumerate(logs):
            others = [o for k, o in enumerate(logs) if k != j]
            extra, _ = fit_testbed_discrepancy(model, others, options.testbed_degree)
            heldout.append((extra, None))
        how, validated = "leave one run out", True
    else:
        held, train = _heldout_split(logs)
        extra, _ = fit_testbed_discrepancy(model, train, options.testbed_degree)
        heldout.append((extra, held[0]))
        # held-out cycles that share their slip levels with the fit's do not test it (a polynomial through 3
        # levels fits them exactly): such a correction is not used
        n_levels = len(logs[0].levels())
        validated = n_levels >= MIN_HELDOUT_LEVELS
        how = ("held-out slip levels" if validated else
               f"not validated: one log with {n_levels} slip level(s), a check needs {MIN_HELDOUT_LEVELS} or more "
               "(or two logs)")
    for lg, (extra, mask) in zip(logs, heldout):
        base_scores.append(blind_score(model, lg, options.blind_start, n_legs, mask))
        with_scores.append(blind_score(with_discrepancy(model, extra), lg, options.blind_start, n_legs, mask))
    spread = _slip_spread(model)
    before, after = _choice_rmse(base_scores, spread), _choice_rmse(with_scores, spread)
    used = bool(validated and after < (1.0 - 0.5 * MIN_GAIN) * before)
    extra, soils = fit_testbed_discrepancy(model, logs, options.testbed_degree)
    return {"used": used, "how": how, "heldout_without": _figures(base_scores), "heldout_with": _figures(with_scores),
            "discrepancy": extra, "soils": soils, "heldout": heldout}


def _interval_scale(model: RoverSurrogate, layer: dict, widen: np.ndarray, logs, options: CalibrateOptions,
                    n_legs: int) -> dict:
    """The factor on the estimator's standard deviations that makes the blind estimates of held-out testbed
    runs cover 95 % of their reference slips (at least 1: intervals are widened, never narrowed).

    Each run is estimated by the final model with the parts fitted on it left out: ``model`` (the model
    before the testbed correction), plus the correction fitted without the run when it is used, plus the
    covariance widening ``widen``. The factor is the 95th percentile of ``|err| / (1.96 std)`` over their
    estimated cycles (:func:`scale_for_coverage`). Returns ``{"scale", "coverage_before", "n"}`` (the
    held-out coverage without the factor)."""
    errs, sds = [], []
    for lg, (extra, mask) in zip(logs, layer["heldout"]):
        m = with_discrepancy(model, extra) if layer["used"] else model
        m = replace(m, extra_cov=m.extra_cov + widen)
        err, sd = blind_errors(m, lg, options.blind_start, n_legs, mask)
        errs.append(err)
        sds.append(sd)
    return scale_for_coverage(np.concatenate(errs), np.concatenate(sds))


def scale_for_coverage(err, sd) -> dict:
    """The factor (at least 1) on the standard deviations ``sd`` for which ``+-1.96 sd`` covers 95 % of the
    errors ``err`` (the 95th percentile of ``|err| / (1.96 sd)``; cycles with a NaN error or no std are left
    out; 1 with fewer than :data:`MIN_SCALE_CYCLES` of them). Returns ``{"scale", "coverage_before", "n"}``:
    ``coverage_before`` the share covered without the factor."""
    err, sd = np.asarray(err, dtype=float), np.asarray(sd, dtype=float)
    ok = np.isfinite(err) & np.isfinite(sd) & (sd > 0)
    z = np.abs(err[ok]) / (1.96 * sd[ok])
    covered = float(np.mean(z <= 1.0)) if z.size else math.nan
    scale = max(1.0, float(np.quantile(z, 0.95))) if z.size >= MIN_SCALE_CYCLES else 1.0
    return {"scale": scale, "coverage_before": covered, "n": int(z.size)}


def _diagnosis_summary(run, d) -> dict:
    if d is None:
        return {"run": run.name, "verdict": "not diagnosed"}
    return {"run": run.name, "verdict": d.verdict, "kappa": float(d.nominal.values["kappa"]),
            "soil": {k: float(d.nominal.values[k]) for k in ("kS", "phiS", "dphi")},
            "gap_nominal_g": float(d.gap_nominal), "gap_after_g": float(d.gap_after), "shrink": float(d.shrink),
            "noise_bin_g": float(d.noise.bin_g),
            "ranking": [{"effect": c.effect, "params": {k: float(v) for k, v in c.params.items()},
                         "gap_heldout_g": float(c.gap_heldout), "shrink": float(c.shrink)} for c in d.ranking[:3]]}


def calibrate(runs, geometry: Geometry = Geometry(), options: CalibrateOptions = CalibrateOptions(),
              progress: Progress | None = None, base=None) -> Calibration:
    """The rover model of the testbed ``runs`` (:class:`TestbedRun`; see the module docstring).

    ``base``: the surrogate to correct (default: the shipped one). ValueError, naming the run, when a run
    has too few estimated cycles with a reference slip."""
    from slipest.inverse.surrogate import load_inverse_model
    from slipest.rover.eq515 import refit_eq515

    t_start = time.perf_counter()
    base = base or load_inverse_model()
    n_legs = int(geometry.nL)
    if base.n_legs != n_legs:
        raise ValueError(f"the inverse model was made for {base.n_legs} legs, the runs are of a {n_legs}-leg "
                         "wheel-leg: retrain it for this geometry (tools/train_inverse.py)")
    rng = np.random.default_rng(options.seed)
    logs = []
    for j, run in enumerate(runs):
        _stage(progress, j, len(runs), f"features of {run.name}")
        logs.append(TestbedLog.from_samples(run.name, run.t, run.az, run.theta, run.slip, n_legs))
    _stage(progress, len(runs), len(runs), "features")
    shipped = RoverSurrogate.of(base, Discrepancy.zero(base.features, base.center[:4], base.halfwidth[:4]),
                                np.zeros((len(base.features),) * 2), rover_legs=n_legs)
    before_scores = [blind_score(shipped, lg, options.blind_start, n_legs) for lg in logs]
    misfit_before = _feature_misfit(shipped, logs)

    diagnoses = diagnose_runs(runs, geometry, options, progress) if options.diagnose else [None] * len(runs)
    cands = _effect_candidates(diagnoses, runs) if options.diagnose else []
    cands += _removal_candidates(cands, logs, n_legs)
    for k, cand in enumerate(cands):
        label = (f"features with {cand.label} from the samples" if cand.corrects_samples
                 else f"simulating {cand.label} ({options.batch} cycles)")
        _stage(progress, k, len(cands), label)
        _build_candidate(base, cand, logs, options, n_legs, rng, runs)
    if options.diagnose and not any(c.named and c.shrink >= WELL_EXPLAINED for c in cands):
        extra = _disturbance_candidate(diagnoses, geometry, options, progress, runs, base, n_legs)
        if extra is not None:
            _build_candidate(base, extra, logs, options, n_legs, rng, runs)
            cands.append(extra)
    spread = _slip_spread(base)
    chosen = _choose(cands, _choice_rmse(before_scores, spread), spread)
    _stage(progress, len(cands), len(cands), "candidates")
    model = shipped if chosen is None else chosen.model
    if chosen is not None and chosen.logs is not None:
        logs = chosen.logs  # the features the rover model sees: through its sample correction
    _stage(progress, 0, 1, "testbed correction (leave one run out)")
    layer = _testbed_layer(model, logs, options, n_legs)
    before_layer = model
    if layer["used"]:
        model = with_discrepancy(model, layer["discrepancy"])
    soils = [log_soil(model, lg) for lg in logs]
    # held-out scatter beyond the model's covariance: soils from the training levels, residuals of the rest
    factor = covariance_factor(_heldout_sq(model, logs), len(model.features))
    noise_smooth = float(np.median([lg.noise_smooth for lg in logs]))
    omega = float(np.median([lg.omega for lg in logs]))
    widen = (factor - 1.0) * model.cov(omega, noise_smooth)
    model = replace(model, extra_cov=model.extra_cov + widen)
    misfit_after = _feature_misfit(model, logs)
    intervals = _interval_scale(before_layer, layer, widen, logs, options, n_legs)
    model = replace(model, interval_scale=intervals["scale"])
    after_scores = [blind_score(model, lg, options.blind_start, n_legs) for lg in logs]
    _stage(progress, 1, 1, "done")
    eq515 = refit_eq515(logs, soils, omega, n_legs)
    model = replace(model, eq515=eq515)
    report = {
        "runs": [{"name": lg.name, "cycles": lg.n_cycles, "estimated_with_reference": len(lg),
                  "slip_levels": len(lg.levels()), "omega": lg.omega, "noise_g": lg.noise, "rate_hz": lg.rate,
                  "flagged": dict(lg.flagged), "soil": s.as_dict()} for lg, s in zip(logs, soils)],
        "imu": {"noise_g": float(np.median([lg.noise for lg in logs])),
                "rate_hz": float(np.median([lg.rate for lg in logs]))},
        "leg_speed": {"omega": omega, "range": [float(min(lg.omega for lg in logs)),
                                                float(max(lg.omega for lg in logs))]},
        "diagnosis": [_diagnosis_summary(r, d) for r, d in zip(runs, diagnoses)],
        "candidates": [{"label": c.label, "effects": [dict(e) for e in c.effects], "kappa": c.kappa,
                        "origin": c.origin, "blind": _figures(c.scores), "seconds": c.seconds} for c in cands],
        "correction": {
            "effect": None if chosen is None else {"label": chosen.label, "effects": [dict(e) for e in chosen.effects],
                                                   "kappa": chosen.kappa, "origin": chosen.origin,
                                                   "disturbance": chosen.disturbance,
                                                   "angle_offset": chosen.angle_offset},
            "testbed": {k: layer[k] for k in ("used", "how", "heldout_without", "heldout_with")},
            "covariance_factor": factor,
            "interval_scale": intervals,
        },
        "before": {"blind": _figures(before_scores), "feature_misfit": misfit_before},
        "after": {"blind": _figures(after_scores), "feature_misfit": misfit_after},
        "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in options.__dict__.items()},
        "seconds": time.perf_counter() - t_start,
    }
    report["eq515"] = {k: eq515["eq515"][k] for k in ("how", "rmse_end_to_end", "r2_end_to_end", "n_soils")}
    report["unexplained"] = _unexplained(model, logs, soils, report)
    return Calibration(model, report)


def _unexplained(model, logs, soils: list[LogSoil], report: dict) -> dict:
    """What is left: the features whose held-out residuals stay largest (in the model's standard deviations)."""
    resid = np.vstack([log_residuals(model, lg, s) for lg, s in zip(logs, soils)])
    sd = np.sqrt(np.diag(model.cov(report["leg_speed"]["omega"], float(np.median([lg.noise_smooth for lg in logs])))))
    bias = np.mean(resid, axis=0) / sd
    order = np.argsort(-np.abs(bias))
    return {"covariance_factor": report["correction"]["covariance_factor"],
            "largest_feature_bias": [{"feature": model.features[j], "bias_sd": float(bias[j])} for j in order[:3]]}


__all__ = ["CalibrateOptions", "Calibration", "Candidate", "MIN_GAIN", "Progress", "TestbedRun", "calibrate",
           "covariance_factor", "diagnose_runs", "scale_for_coverage"]
