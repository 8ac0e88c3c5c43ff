"""Fit the model to logged cycles: nominal soil (+ kappa), or soil plus one catalog effect.

The *objective* of a candidate (soil, effect parameters) on a set of cycles
is the mean squared difference, over cycles and analysis bins, between each
logged cycle's bin-averaged ``az`` and the model's prediction for that
cycle's slip (:class:`slipest.diagnosis.predict.Evaluator`), after removing
a constant accelerometer bias (solved in closed form; reported).

The waveform objective is very rugged in the soil parameters (a small
change of ``kS`` or ``phiS`` shifts the stick-slip oscillation's phase and
the residual jumps), so :func:`fit` works in named stages on the unit cube
of the search ranges (:class:`SearchSpace`):

1. :func:`descriptor_stage`: differential evolution (scipy,
   ``vectorized=True``) over the whole box on a phase-insensitive
   *descriptor* misfit (:mod:`slipest.diagnosis.descriptors`, smoother in
   the parameters), which finds the basin where multi-start local searches
   did not;
2. :func:`waveform_stage`: CMA-ES (:mod:`slipest.diagnosis.cmaes`) on the
   waveform residual;
3. :func:`refine_stage`: a short CMA-ES at the project's step.

Every candidate of a generation is simulated in one compiled parallel
batch. The search runs at coarse integration steps (``DT_COARSE``,
``DT_SEARCH``, or the effect's ``search_steps``), the refinement and every
reported number at ``DT_FINE``.

Fitted quantities and their search ranges are the soil's
(:data:`~slipest.diagnosis.predict.SOIL_PARAMS`) and the effect's
``fit_params`` (:mod:`slipest.model.effects`, SI), which may be a better
conditioned form of the catalog's parameters (:func:`catalog_params` converts
back); a categorical parameter gets one search instance per value; a
``linear`` one is solved in closed form with the bias. An effect that leaves
a model-free signature in the data seeds its own fit
(:meth:`~slipest.model.effects.base.Effect.signature_seeds`, given a
:class:`Signature`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
from scipy.optimize import differential_evolution
from scipy.stats import qmc

from slipest.diagnosis.cmaes import run_cmas
from slipest.diagnosis.cycles import CycleSet
from slipest.diagnosis.descriptors import descriptors
from slipest.diagnosis.predict import DT_FINE, SOIL_NAMES, Evaluator, Geometry, effect_model

__all__ = [
    "DT_COARSE", "DT_SEARCH", "DT_FINE", "COARSE_LEVELS", "FitBudget", "FitResult", "Geometry", "SearchSpace",
    "Signature", "catalog_params", "evaluate", "fit", "fit_effect", "descriptor_stage", "waveform_stage",
    "refine_stage",
]

#: Integration step of the first (descriptor) stage [s].
DT_COARSE = 8e-4
#: Integration step of the population search [s] (waveform within ~0.005 g of DT_FINE's).
DT_SEARCH = 4e-4
#: Most slip levels the first stage uses.
COARSE_LEVELS = 4


def catalog_params(effect: str | None, values: dict, geometry: Geometry) -> dict:
    """The catalog's parameters (:mod:`slipest.model.effects`) of a fitted effect (floats, ints for integers)."""
    if effect is None:
        return {}
    model = effect_model(effect)
    fitted = {p.name: float(values[p.name]) for p in model.fit_params}
    soil = {n: float(values[n]) for n in SOIL_NAMES}
    cat = model.catalog_values(fitted, soil, geometry)
    return {p.name: (int(round(float(cat[p.name]))) if p.integer else float(cat[p.name])) for p in model.params}


@dataclass
class FitResult:
    """A fitted model: effect (None: nominal), fitted values (soil + effect, SI), bias [m/s^2], training MSE."""

    effect: str | None
    values: dict
    bias: float
    mse_train: float
    n_evals: int = 0
    x: np.ndarray = field(default=None, repr=False)

    def soil(self) -> dict:
        return {k: self.values[k] for k in SOIL_NAMES}


@dataclass(frozen=True)
class FitBudget:
    """Effort of :func:`fit`: differential-evolution population (per free parameter) and generations of
    the descriptor stage, CMA-ES population and generations of the waveform stages."""

    de_popsize: int = 15
    de_gens: int = 60
    lam: int = 16
    gen_wave: int = 40
    gen_fine: int = 8

    def scaled(self, factor: float) -> "FitBudget":
        """The same budget with the generation counts scaled (at least a few)."""
        return FitBudget(
            de_popsize=self.de_popsize,
            de_gens=max(5, int(self.de_gens * factor)),
            lam=self.lam,
            gen_wave=max(4, int(self.gen_wave * factor)),
            gen_fine=max(2, int(self.gen_fine * factor)),
        )

    @property
    def generations(self) -> int:
        """Upper bound of ``progress()`` calls of one :func:`fit`."""
        return 1 + self.de_gens + self.gen_wave + self.gen_fine


class SearchSpace:
    """The fitted parameters on the unit cube: points ``u`` in ``[0, 1]^D`` <-> search coordinates ``z``.

    ``z = lo + u (hi - lo)`` in each parameter's search coordinate (its log
    for a log-scaled one), integers rounded. ``fixed`` parameters (given
    values) and ``linear`` ones stay at their starting values; of the
    others (``free``), ``cat`` are categorical (searched by instance) and
    ``cont`` continuous.
    """

    def __init__(self, ev: Evaluator, fixed: dict | None = None):
        self.params = ev.params
        self.fixed = dict(fixed or {})
        self._z_of = ev.z_of
        self.D = len(self.params)
        self.lo = np.array([p.zbounds[0] for p in self.params])
        self.hi = np.array([p.zbounds[1] for p in self.params])
        self.width = self.hi - self.lo
        self.integer = np.array([p.integer for p in self.params])
        held = [j for j, p in enumerate(self.params) if p.name in self.fixed or p.linear]
        self.free = [j for j in range(self.D) if j not in held]
        self.cat = [j for j, p in enumerate(self.params) if p.categorical and j not in held]
        self.cont = [j for j in self.free if j not in self.cat]

    def z(self, U: np.ndarray) -> np.ndarray:
        """Search coordinates ``(P, D)`` of unit-cube points ``U (P, D)`` (clipped to the cube)."""
        Z = self.lo + np.clip(U, 0, 1) * self.width
        Z[:, self.integer] = np.round(Z[:, self.integer])
        return Z

    def u(self, z) -> np.ndarray:
        """Unit-cube point of search coordinates ``z (D,)``."""
        return (np.asarray(z, dtype=float) - self.lo) / self.width

    def point(self, values: dict) -> np.ndarray:
        """Unit-cube point of (partial) values: fixed values first, then the given ones, else each parameter's start."""
        full = {}
        for p in self.params:
            v = self.fixed.get(p.name, values.get(p.name, p.start))
            full[p.name] = float(np.clip(v, p.lo, p.hi))
        return self.u(self._z_of(full))

    @cached_property
    def template(self) -> np.ndarray:
        """The point of no values given (every parameter at its start)."""
        return self.point({})


def _debug(*args):
    if os.environ.get("SLIPEST_FIT_DEBUG"):
        print("[fit]", *args, flush=True)


def _spread_levels(slips: np.ndarray, k: int) -> np.ndarray:
    """Up to ``k`` of the distinct values, spread over their range (ends included)."""
    levels = np.unique(slips)
    if len(levels) <= k:
        return levels
    pick = np.unique(np.round(np.linspace(0, len(levels) - 1, k)).astype(int))
    return levels[pick]


def descriptor_objective(ev: Evaluator, space: SearchSpace, dt: float) -> Callable[[np.ndarray], np.ndarray]:
    """Weighted mean squared descriptor misfit of unit-cube points ``(P, D)`` (1e6 where the model fails)."""
    grid = ev.grid
    d_data = descriptors(ev.g_mean, grid)
    wg = ev.g_n / ev.g_n.sum()

    def f(U):
        out = np.empty(len(U))
        for i in range(0, len(U), 256):
            pred, ok = ev.predict(space.z(U[i : i + 256]), dt)
            pred = np.nan_to_num(pred)
            if ev.common:  # the data's descriptors against the prediction with the common waveform added
                pred = pred + ev.common_waveform(pred)[:, None, :]
            dd = descriptors(pred, grid)
            m = np.sum(np.mean((dd - d_data[None]) ** 2, axis=2) * wg[None], axis=1)
            out[i : i + 256] = np.where(ok & np.isfinite(m), m, 1e6)
        return out

    return f


def waveform_objective(ev: Evaluator, space: SearchSpace, dt: float) -> Callable[[np.ndarray], np.ndarray]:
    """Waveform MSE [(m/s^2)^2] of unit-cube points ``(P, D)`` after the best bias (1e6 where the model fails)."""

    def f(U):
        m, _ = ev.mse(space.z(U), dt)
        return np.where(np.isfinite(m), m, 1e6)

    return f


def descriptor_stage(f: Callable, space: SearchSpace, seeds: np.ndarray, rng: np.random.Generator, budget: FitBudget,
                     progress: Callable[[], None] | None = None) -> np.ndarray:
    """Stage 1: differential evolution over the free coordinates, on the descriptor objective ``f``.

    The initial population is a Latin-hypercube sample of the cube with up
    to a quarter of it replaced by the ``seeds`` (unit-cube points); the
    other coordinates stay at the template's values. Integer parameters are
    searched in their own units (DE's integrality). Returns the candidates
    for stage 2 ``(K, D)``: the best point and the seeds (just the seeds, or
    the template, when nothing is free).
    """
    free, template = space.free, space.template
    if not free:
        return seeds if len(seeds) else template[None]
    n_free = len(free)
    lo, hi, width, integer = space.lo, space.hi, space.width, space.integer

    def f_de(x):
        X = np.atleast_2d(x.T) if x.ndim == 2 else x[None, :]
        U = np.tile(template, (X.shape[0], 1))
        U[:, free] = X
        return f(U)

    n_pop = max(budget.de_popsize * n_free, 10)
    sob = qmc.LatinHypercube(n_free, seed=rng).random(n_pop)
    if len(seeds):
        sob[: min(len(seeds), n_pop // 4)] = seeds[: n_pop // 4][:, free]
    int_free = np.array([integer[j] for j in free])

    def cb(*_a, **_k):
        if progress is not None:
            progress()
        return False

    de = dict(maxiter=budget.de_gens, tol=1e-7, mutation=(0.5, 1.0), recombination=0.9, seed=rng, polish=False,
              vectorized=True, updating="deferred", callback=cb)
    if int_free.any():
        # DE with integrality needs integer bounds: search integers in their own units
        scale = np.where(int_free, width[free], 1.0)
        off = np.where(int_free, lo[free], 0.0)

        def f_int(x):
            X = np.atleast_2d(x.T) if x.ndim == 2 else x[None, :]
            return f_de(((X - off) / scale).T)

        bounds = [(lo[j], hi[j]) if integer[j] else (0.0, 1.0) for j in free]
        init_pop = sob * scale + off
        init_pop[:, int_free] = np.round(init_pop[:, int_free])
        res = differential_evolution(f_int, bounds, init=init_pop, integrality=int_free, **de)
        x_best = (res.x - off) / scale
    else:
        res = differential_evolution(f_de, [(0.0, 1.0)] * n_free, init=sob, **de)
        x_best = res.x
    u1 = template.copy()
    u1[free] = x_best
    return np.vstack([u1[None], seeds])


def waveform_stage(f: Callable, cand: np.ndarray, space: SearchSpace, rng: np.random.Generator, budget: FitBudget,
                   progress: Callable[[], None] | None = None) -> tuple[np.ndarray, float]:
    """Stage 2: CMA-ES on the waveform objective ``f`` from the best of the candidates ``cand (K, D)``.

    One instance per value of a categorical parameter (the worse dropped
    after a third of the generations); the continuous coordinates are
    searched. Returns the best point and its value.
    """
    fc = f(cand)
    _debug("stage1", np.round(np.sqrt(fc) / 9.81, 4))
    j = int(np.argmin(fc))
    u2, f2 = cand[j], fc[j]
    if not space.cont:
        return u2, f2
    starts = [(cand[j], 0.02)]
    if space.cat:
        jc = space.cat[0]
        for value in np.unique(np.round(np.linspace(0, 1, int(round(space.width[jc])) + 1), 9)):
            if abs(value - cand[j, jc]) < 1e-9:
                continue
            start = cand[j].copy()
            start[jc] = value
            starts.append((start, 0.02))
    u2b, f2b = run_cmas(f, starts, rng, budget.lam, budget.gen_wave, dims=space.cont, tol=2e-4,
                        keep_after={max(1, budget.gen_wave // 3): 1}, progress=progress)[0]
    if f2b < f2:
        u2, f2 = u2b, f2b
    return u2, f2


def refine_stage(f: Callable, cand: np.ndarray, space: SearchSpace, rng: np.random.Generator, budget: FitBudget,
                 progress: Callable[[], None] | None = None) -> tuple[np.ndarray, float]:
    """Stage 3: a short small-step CMA-ES on the fine-step waveform objective ``f`` from the best of ``cand``."""
    fc = f(cand)
    j = int(np.argmin(fc))
    u3, f3 = cand[j], fc[j]
    if space.cont:
        u3b, f3b = run_cmas(f, [(cand[j], 0.004)], rng, max(10, budget.lam // 2), budget.gen_fine, dims=space.cont,
                            tol=1e-5, progress=progress)[0]
        if f3b < f3:
            u3, f3 = u3b, f3b
    return u3, f3


def fit(cycles: CycleSet, idx, effect: str | None, geometry: Geometry, *, seed=0, budget: FitBudget = FitBudget(),
        init: list[dict] | None = None, fixed: dict | None = None, bias0: float = 0.0,
        progress: Callable[[], None] | None = None, common: bool = False) -> FitResult:
    """Fit soil (+ ``effect``) to the cycles ``idx``; the objective is the mean squared waveform residual.

    1. :func:`descriptor_stage` at ``DT_COARSE`` on at most
       ``COARSE_LEVELS`` slip levels; the initial population holds the
       ``init`` points (values dicts; missing effect parameters at their
       starts, :attr:`FitParam.start`);
    2. :func:`waveform_stage` on all training cycles at ``DT_SEARCH`` from
       the stage-1 result and the ``init`` points;
    3. :func:`refine_stage` at ``DT_FINE``.

    ``fixed``: parameter values held fixed (not searched). ``progress()`` is
    called once per generation. ``common``: the nominal model (``effect``
    None) fitted with a waveform common to every cycle profiled out
    (:class:`~slipest.diagnosis.predict.Evaluator`'s ``common``; the result's
    ``bias`` is that waveform's mean), as a phase-locked disturbance is learnt
    (:func:`slipest.rover.waveform.learn_disturbance`).
    """
    idx = np.asarray(idx, dtype=np.int64)
    ev = Evaluator(cycles, idx, effect, geometry, bias0=bias0, solve_linear=True, common=common)
    levels = _spread_levels(cycles.slip[idx], COARSE_LEVELS)
    ev1 = Evaluator(cycles, idx[np.isin(cycles.slip[idx], levels)], effect, geometry, bias0=bias0,
                    solve_linear=True, common=common)
    rng = np.random.default_rng(seed)
    space = SearchSpace(ev, fixed)
    dt_coarse, dt_search = ev.model.search_steps or (DT_COARSE, DT_SEARCH)
    seeds = np.array([space.point(v) for v in (init or [])]).reshape(-1, space.D)

    cand = descriptor_stage(descriptor_objective(ev1, space, dt_coarse), space, seeds, rng, budget, progress)
    u2, f2 = waveform_stage(waveform_objective(ev, space, dt_search), cand, space, rng, budget, progress)
    u3, f3 = refine_stage(waveform_objective(ev, space, DT_FINE), np.vstack([u2[None], seeds]), space, rng, budget,
                          progress)
    _debug("stage2/3", effect, sorted(space.fixed), np.sqrt(min(f2, 1e9)) / 9.81, np.sqrt(f3) / 9.81)

    z = space.z(u3[None])[0]
    mse, bias = ev.mse(z[None], DT_FINE)
    values = ev.values(z)
    for name, v in ev.last_linear.items():  # parameters solved in closed form
        values[name] = float(v[0])
    return FitResult(effect=effect, values=values, bias=float(bias[0]), mse_train=float(mse[0]),
                     n_evals=ev.n_evals + ev1.n_evals, x=ev.z_of(values))


@dataclass
class Signature:
    """What an effect may read off the training cycles ``idx`` to seed its fit (``Effect.signature_seeds``).

    grid; y ``(C, nb)`` bin means [m/s^2]; speed ``(C, nb)`` encoder leg
    speed per bin [rad/s]; omega: mean leg speed [rad/s]; mean_residual
    ``(nb,)`` [m/s^2]: mean over the cycles of data minus the nominal fit's
    prediction (computed when first asked for).
    """

    cycles: CycleSet
    idx: np.ndarray
    nominal: FitResult
    geometry: Geometry

    @property
    def grid(self):
        return self.cycles.grid

    @property
    def y(self) -> np.ndarray:
        return self.cycles.y[self.idx]

    @property
    def speed(self) -> np.ndarray:
        return self.cycles.speed[self.idx]

    @property
    def omega(self) -> float:
        return float(np.mean(self.cycles.omega[self.idx]))

    @cached_property
    def mean_residual(self) -> np.ndarray:
        pred = evaluate(self.cycles, self.idx, self.nominal, self.geometry)["pred"]
        return np.mean(self.y - pred, axis=0)


def fit_effect(cycles: CycleSet, idx, effect: str, geometry: Geometry, nominal: FitResult, *, seed=0,
               budget: FitBudget = FitBudget(), progress: Callable[[], None] | None = None) -> FitResult:
    """Fit soil + ``effect`` to the cycles ``idx`` with a joint :func:`fit`.

    Its first population holds, besides the quasi-random points, the
    nominal soil with the effect off and, for an effect with a model-free
    signature in the data (``Effect.signature_seeds``), the soil refitted
    with the effect parameters read off the data held fixed (a 4-D fit at
    half the budget): the nominal fit absorbs part of an effect into a
    biased soil, and a strong effect (a touchdown transient) can dominate
    the joint search's first stage.
    """
    idx = np.asarray(idx, dtype=np.int64)
    soil = nominal.soil()
    init = [soil]
    found = effect_model(effect).signature_seeds(Signature(cycles, idx, nominal, geometry))
    for j, v in enumerate(found):
        r = fit(cycles, idx, effect, geometry, seed=seed + 100 + j, budget=budget.scaled(0.5),
                init=[{**soil, **v}], fixed=v, bias0=nominal.bias, progress=progress)
        init.append(r.values)
    return fit(cycles, idx, effect, geometry, seed=seed, budget=budget, init=init, bias0=nominal.bias,
               progress=progress)


def evaluate(cycles: CycleSet, idx, result: FitResult, geometry: Geometry, dt: float = DT_FINE) -> dict:
    """Residuals of a fitted model on cycles ``idx`` (e.g. held out): per-cycle predictions and errors.

    Returns ``pred (C, nb)`` [m/s^2] including the fitted bias, ``resid (C, nb)`` and ``mse``.
    """
    ev = Evaluator(cycles, idx, result.effect, geometry, bias0=0.0)
    if ev.model.bias_inside:
        ev.bias0 = result.bias
    pred, ok = ev.predict(ev.z_of(result.values)[None], dt)
    pred_c = pred[0][ev.group_of] + result.bias
    y = cycles.y[ev.idx]
    resid = y - pred_c
    return {"pred": pred_c, "resid": resid, "mse": float(np.mean(resid**2)) if ok[0] else float("inf"), "ok": bool(ok[0])}
