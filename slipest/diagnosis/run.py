"""The diagnosis of logged cycles against the model: fit, localise, rank, verdict (pure computation).

:func:`diagnose` takes cycles (:func:`slipest.diagnosis.cycles.cut_cycles`)
and the known hardware (:class:`slipest.diagnosis.fit.Geometry`) and

1. splits them into training and held-out cycles (held-out slip levels
   included, :func:`slipest.diagnosis.rank.split_cycles`) and estimates the
   noise floor from the data (:func:`slipest.diagnosis.rank.noise_floor`);
2. fits the nominal model's soil and ``kappa`` on the training cycles and
   measures its held-out gap (definition: :mod:`slipest.diagnosis.rank`);
3. localises that gap by leg-angle window, feature and slip level
   (:mod:`slipest.diagnosis.localize`);
4. unless the nominal model already explains the data within noise, fits
   soil + each catalog effect on the training cycles (except an effect the
   data cannot tell from another one that is fitted:
   :meth:`~slipest.model.effects.base.Effect.equivalent_on`, e.g. a time
   skew at one leg speed is an angle offset; listed in ``skipped``)
   (:func:`slipest.diagnosis.fit.fit_effect`) and measures each held-out
   gap; re-fits the nominal model from the soils those fits found (so that
   no effect gets credit for a better soil alone; the better nominal fit,
   by training error, is the reference); ranks the effects and gives the
   verdict (:func:`slipest.diagnosis.rank.verdict`).

Nothing here reads or writes files; progress is reported through a callback.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from slipest.diagnosis import localize
from slipest.diagnosis.cycles import CycleSet
from slipest.diagnosis.fit import FitBudget, FitResult, Geometry, catalog_params, evaluate, fit, fit_effect
from slipest.diagnosis.rank import (
    Candidate,
    NoiseFloor,
    Split,
    Thresholds,
    gap_of,
    noise_floor,
    rank,
    shrink_of,
    split_cycles,
    verdict,
)
from slipest.model.effects import EFFECTS, ORDER

#: ``progress(done, total, label)``: work units done of the planned total, and what is running.
Progress = Callable[[int, int, str], None]


@dataclass
class Diagnosis:
    """Everything the diagnosis found (gaps in g, parameters SI).

    verdict: effect name, ``"none"`` or ``"unexplained"``. gap_nominal /
    gap_after: held-out gap before / after the best effect; shrink:
    ``1 - gap_after/gap_before``. ranking: effects, best first (empty when
    the nominal model already explained the data and ``rank_all`` was off).
    where: localisation of the nominal model's held-out gap (and of the best
    effect's, under ``"after"``). predictions: held-out predictions
    ``(C_test, nb)`` [m/s^2] of the nominal model and of each fitted effect.
    skipped: effects not fitted because these cycles cannot tell them from
    another fitted one -> the reason. swaps: ``(log label, SwapSummary)``
    per log, the IMU's timing against the encoder at the leg swaps
    (:func:`slipest.swap_timing.swap_summary`; empty when not measured).
    """

    verdict: str
    gap_nominal: float
    gap_nominal_train: float
    gap_after: float
    shrink: float
    noise: NoiseFloor
    split: Split
    nominal: FitResult
    ranking: list
    where: dict
    thresholds: Thresholds
    geometry: Geometry
    cycles: CycleSet
    predictions: dict = field(default_factory=dict)
    fits: dict = field(default_factory=dict)
    effects_fitted: bool = True
    elapsed_s: float = 0.0
    swaps: tuple = ()
    skipped: dict = field(default_factory=dict)

    @property
    def best(self) -> Candidate | None:
        return self.ranking[0] if self.ranking else None


def _where(cycles: CycleSet, idx, pred, var, split: Split) -> dict:
    resid = cycles.y[idx] - pred
    omega = float(np.mean(cycles.omega[idx]))
    return {
        "angle_windows": localize.by_window(resid, var, cycles.grid),
        "features": localize.by_feature(cycles.y[idx], pred, cycles.slip[idx], cycles.grid, omega),
        "slip_levels": localize.by_slip(resid, var, cycles.slip[idx], split.heldout_levels),
    }


def equivalent_effects(effects, omega) -> dict:
    """Effects of ``effects`` the cycles (leg speeds ``omega`` [rad/s]) cannot tell from another one in ``effects``.

    Returns name -> reason. Only the effect that names the other as its
    equivalent is dropped (``Effect.equivalent_on``), so one of a pair stays.
    """
    out = {}
    omega = np.asarray(omega, dtype=float)
    for name in effects:
        other = EFFECTS[name].equivalent_on(omega)
        if other is not None and other in effects and other not in out:
            out[name] = (f"the same as {other} on these cycles (leg speed {np.nanmin(omega):.3g}-"
                         f"{np.nanmax(omega):.3g} rad/s); fitted as {other}")
    return out


def planned_units(effects, budget: FitBudget) -> int:
    """Work units (optimiser generations) a diagnosis plans: nominal fit, one fit per effect, nominal re-fit."""
    return budget.generations * (1 + len(effects)) + budget.scaled(0.5).generations


def diagnose(
    cycles: CycleSet,
    geometry: Geometry,
    effects=None,
    *,
    seed: int = 0,
    budget: FitBudget = FitBudget(),
    thresholds: Thresholds = Thresholds(),
    rank_all: bool = False,
    progress: Progress | None = None,
) -> Diagnosis:
    """Diagnose the cycles (see the module docstring). ``effects``: catalog names (default: all)."""
    t_start = time.perf_counter()
    effects = list(ORDER if effects is None else effects)
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; known: {', '.join(ORDER)}")
    skipped = equivalent_effects(effects, cycles.omega)
    effects = [e for e in effects if e not in skipped]
    split = split_cycles(cycles.slip)
    noise = noise_floor(cycles)
    var_test = noise.var_bin[split.test]
    total = planned_units(effects, budget)
    done = [0]

    def tick_factory(label: str):
        def tick():
            done[0] += 1
            if progress is not None:
                progress(min(done[0], total), total, label)

        return tick

    nominal = fit(cycles, split.train, None, geometry, seed=seed, budget=budget, progress=tick_factory("nominal"))
    done[0] = budget.generations
    ev_nom = evaluate(cycles, split.test, nominal, geometry)
    gap_nom = gap_of(ev_nom["resid"], var_test)
    gap_nom_train = gap_of(evaluate(cycles, split.train, nominal, geometry)["resid"], noise.var_bin[split.train])
    predictions = {"nominal": ev_nom["pred"]}
    where = _where(cycles, split.test, ev_nom["pred"], var_test, split)

    fitted = rank_all or gap_nom > thresholds.none_level(noise.bin_g)
    candidates, fits = [], {}
    per_effect = budget.generations
    if fitted:
        for k, name in enumerate(effects):
            r = fit_effect(cycles, split.train, name, geometry, nominal, seed=seed + 10 * (k + 1), budget=budget,
                           progress=tick_factory(name))
            done[0] = budget.generations + (k + 1) * per_effect
            ev = evaluate(cycles, split.test, r, geometry)
            g = gap_of(ev["resid"], var_test)
            g_train = gap_of(evaluate(cycles, split.train, r, geometry)["resid"], noise.var_bin[split.train])
            fits[name] = r
            predictions[name] = ev["pred"]
            candidates.append(
                Candidate(
                    effect=name,
                    params=catalog_params(name, r.values, geometry),
                    gap_heldout=g,
                    shrink=shrink_of(gap_nom, g),
                    gap_train=g_train,
                    n_params=len(EFFECTS[name].fit_params),
                    soil=r.soil(),
                )
            )
    if fitted and fits:
        # Re-fit the nominal model from the soils the effect fits found: a misspecified nominal search can
        # stop in a poor optimum, and an effect must not get credit for merely finding a better soil.
        refit = fit(cycles, split.train, None, geometry, seed=seed + 7, budget=budget.scaled(0.5),
                    init=[nominal.soil()] + [r.soil() for r in fits.values()], progress=tick_factory("nominal refit"))
        if refit.mse_train < nominal.mse_train:
            nominal = refit
            ev_nom = evaluate(cycles, split.test, nominal, geometry)
            gap_nom = gap_of(ev_nom["resid"], var_test)
            gap_nom_train = gap_of(evaluate(cycles, split.train, nominal, geometry)["resid"],
                                   noise.var_bin[split.train])
            predictions["nominal"] = ev_nom["pred"]
            where = _where(cycles, split.test, ev_nom["pred"], var_test, split)
            for c in candidates:
                c.shrink = shrink_of(gap_nom, c.gap_heldout)
    if progress is not None:
        progress(total, total, "done")
    ranking = rank(candidates, gap_nom)
    v = verdict(gap_nom, ranking, noise.bin_g, thresholds)
    best = ranking[0] if ranking else None
    gap_after = best.gap_heldout if best else gap_nom
    if best is not None:
        where["after"] = {"effect": best.effect, **_where(cycles, split.test, predictions[best.effect], var_test, split)}
    return Diagnosis(
        verdict=v,
        gap_nominal=gap_nom,
        gap_nominal_train=gap_nom_train,
        gap_after=gap_after,
        shrink=shrink_of(gap_nom, gap_after),
        noise=noise,
        split=split,
        nominal=nominal,
        ranking=ranking,
        where=where,
        thresholds=thresholds,
        geometry=geometry,
        cycles=cycles,
        predictions=predictions,
        fits=fits,
        effects_fitted=fitted,
        elapsed_s=time.perf_counter() - t_start,
        skipped=skipped,
    )
