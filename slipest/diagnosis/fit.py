"""Fit the model to logged cycles: nominal soil (+ kappa), or soil plus one catalog effect.

The *objective* of a candidate (soil, effect parameters) on a set of cycles
is the mean squared difference, over cycles and analysis bins, between each
logged cycle's bin-averaged ``az`` and the model's prediction for that
cycle's slip (:mod:`slipest.diagnosis.predict`), after removing a constant
accelerometer bias (solved in closed form; reported). Cycles with the same
slip (and, for effects with memory across the cycle boundary, the same
previous slip) share one prediction, so the objective only needs their mean
and one stance simulation per distinct slip.

The waveform objective is very rugged in the soil parameters (a small
change of ``kS`` or ``phiS`` shifts the stick-slip oscillation's phase and
the residual jumps), so the optimiser works in stages (:func:`fit`): a
phase-insensitive *descriptor* misfit (:func:`descriptors`: window means,
RMS, slope RMS, energy quantiles, onset; smoother in the parameters) is
minimised by differential evolution over the whole search box (scipy,
``vectorized=True``), which finds the basin where multi-start local
searches did not; then CMA-ES refines the waveform residual. Every
candidate of a generation is simulated in one compiled parallel batch. The
search runs at coarse integration steps (``DT_COARSE``, ``DT_SEARCH``), the
refinement and every reported number at the project's step ``DT_FINE``.

Fitted quantities and their search ranges are :data:`SOIL_PARAMS` and
:data:`EFFECT_PARAMS` (SI). Some effects are fitted in a better-conditioned
form and converted back to the catalog's parameters
(:func:`catalog_params`): the contact damping as ``c_hc = b_hc d0^n_hc``
[N s/m] at the static sinkage ``d0 = MH g / kS``, the speed ripple as
``(A cos phase, A sin phase)``; the low-pass order is an integer (one
refinement instance per order); the touchdown amplitude enters the
prediction linearly and is solved in closed form with the bias.
:func:`signature_seeds` reads some effects' parameters off the data
directly (the encoder's speed profile for a drive ripple, the rigid half's
transient for a touchdown, flat tops for clipping) to seed the search.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import differential_evolution
from scipy.special import ndtr
from scipy.stats import qmc

from slipest.diagnosis.cycles import CycleSet
from slipest.diagnosis.predict import (
    Grid,
    bin_average_batch,
    impact_batch,
    lowpass_batch,
    rigid_batch,
    stance_fine,
)
from slipest.model import kernel as K
from slipest.model.params import StickSlipParams

#: Integration step of the population search [s] (waveform within ~0.005 g of DT_FINE's).
DT_SEARCH = 4e-4
#: Integration step of the refinement and of every reported gap [s] (the project's default).
DT_FINE = 1e-4


@dataclass(frozen=True)
class FitParam:
    """One fitted quantity: SI unit, search range, log-scaled search, integer."""

    name: str
    unit: str
    lo: float
    hi: float
    log: bool = False
    integer: bool = False
    choices: tuple = ()
    linear: bool = False  # solved in closed form during the fit (least squares), not searched

    @property
    def categorical(self) -> bool:
        return bool(self.choices)

    def to_z(self, x):
        return np.log(x) if self.log else np.asarray(x, dtype=float)

    def from_z(self, z):
        x = np.exp(z) if self.log else np.asarray(z, dtype=float)
        return np.round(x) if self.integer else x

    @property
    def zbounds(self) -> tuple[float, float]:
        if self.log:
            return (math.log(self.lo), math.log(self.hi))
        return (self.lo, self.hi)


#: Soil (and leg) parameters of the nominal model: stiffness, static friction
#: angle, friction angle drop ``phiS - phiD``, lateral leg stiffness ratio.
SOIL_PARAMS = (
    FitParam("kS", "N/m", 400.0, 2200.0, log=True),
    FitParam("phiS", "rad", 0.25, 0.85),
    FitParam("dphi", "rad", 0.0, 0.40),
    FitParam("kappa", "-", 0.12, 0.7),
)

#: Fitted parameters of each catalog effect (search ranges cover the catalog's typical ranges).
EFFECT_PARAMS: dict[str, tuple[FitParam, ...]] = {
    "contact_damping": (FitParam("c_hc", "N s/m", 0.0, 12.0), FitParam("n_hc", "-", 0.8, 2.0)),
    "stribeck": (
        FitParam("vs", "m/s", 0.001, 0.2, log=True),
        FitParam("delta", "-", 0.5, 3.0),
        FitParam("viscous", "N s/m", 0.0, 6.0),
    ),
    "speed_ripple": (FitParam("ripple_c", "-", -0.35, 0.35), FitParam("ripple_s", "-", -0.35, 0.35)),
    "touchdown_impact": (
        FitParam("amplitude", "m/s^2", -35.0, 35.0, linear=True),
        FitParam("tau", "s", 0.01, 2.0, log=True),
        FitParam("freq", "Hz", 3.0, 60.0, log=True),
    ),
    "imu_lowpass": (
        FitParam("cutoff", "Hz", 1.0, 40.0, log=True),
        FitParam("order", "-", 1, 4, integer=True, choices=(1, 2, 3, 4)),
    ),
    "imu_saturation": (FitParam("full_scale", "m/s^2", 10.0, 25.0),),
    "angle_offset": (FitParam("offset", "rad", -0.22, 0.22),),
}

#: Effects whose prediction of a cycle depends on the previous cycle's slip.
MEMORY_EFFECTS = ("imu_lowpass", "angle_offset")


@dataclass(frozen=True)
class Geometry:
    """The known hardware (not fitted): hub and foot masses [kg], spoke length [m], legs, gravity [m/s^2]."""

    MH: float = 1.0
    mF: float = 0.2
    lS: float = 0.1763
    nL: int = 4
    g: float = 9.81

    def base_row(self) -> np.ndarray:
        return StickSlipParams(MH=self.MH, mF=self.mF, lS=self.lS, nL=self.nL, g=self.g).to_row()


def space(effect: str | None) -> tuple[FitParam, ...]:
    """The fitted parameters of the nominal model (``None``) or of nominal + ``effect``."""
    return SOIL_PARAMS + (EFFECT_PARAMS[effect] if effect else ())


def catalog_params(effect: str | None, values: dict, geometry: Geometry) -> dict:
    """The catalog's parameters (:mod:`slipest.model.effects`) of a fitted effect."""
    if effect is None:
        return {}
    v = dict((k, float(x)) for k, x in values.items() if k not in ("kS", "phiS", "dphi", "kappa"))
    if effect == "contact_damping":
        d0 = geometry.MH * geometry.g / values["kS"]
        return {"b_hc": v["c_hc"] / d0 ** v["n_hc"], "n_hc": v["n_hc"]}
    if effect == "imu_lowpass":
        v["order"] = int(round(v["order"]))
    if effect == "speed_ripple":
        c, s_ = v.pop("ripple_c"), v.pop("ripple_s")
        v = {"amplitude": math.hypot(c, s_), "phase": math.atan2(s_, c)}
    return v


@dataclass
class FitResult:
    """A fitted model: effect (None: nominal), values of :func:`space` (SI), bias [m/s^2], training MSE."""

    effect: str | None
    values: dict
    bias: float
    mse_train: float
    n_evals: int = 0
    x: np.ndarray = field(default=None, repr=False)

    def soil(self) -> dict:
        return {k: self.values[k] for k in ("kS", "phiS", "dphi", "kappa")}


def expected_clip(u: np.ndarray, full_scale, sigma: float) -> np.ndarray:
    """Mean of ``clip(u + n, -FS, FS)`` for Gaussian noise ``n`` of standard deviation ``sigma``.

    The logged samples are clipped after the noise is added, so a bin average
    near the full scale sits below it; with ``d = FS - u``:
    ``E[min(u + n, FS)] = u + d (1 - Phi(d/s)) - s phi(d/s)`` (same at ``-FS``).
    """
    if sigma <= 0:
        return np.clip(u, -full_scale, full_scale)
    d_hi = (full_scale - u) / sigma
    d_lo = (u + full_scale) / sigma
    hi = sigma * (d_hi * ndtr(-d_hi) - np.exp(-0.5 * d_hi**2) / math.sqrt(2 * math.pi))
    lo = sigma * (d_lo * ndtr(-d_lo) - np.exp(-0.5 * d_lo**2) / math.sqrt(2 * math.pi))
    return u + hi - lo


class Evaluator:
    """Objective and prediction of candidates on a fixed set of cycles (see the module docstring).

    cycles: the :class:`CycleSet`; idx: the cycles used; effect: catalog
    name or None; geometry: the known hardware; bias0 [m/s^2]: bias assumed
    before the sampled stages (clipping), the rest is fitted in closed form.
    """

    def __init__(self, cycles: CycleSet, idx, effect: str | None, geometry: Geometry, bias0: float = 0.0,
                 solve_linear: bool = False):
        self.cycles = cycles
        self.solve_linear = solve_linear
        self.last_linear: dict = {}
        self.noise_sigma = float(np.sqrt(np.mean(cycles.noise**2))) if np.all(np.isfinite(cycles.noise)) else 0.0
        self.idx = np.asarray(idx, dtype=np.int64)
        if self.idx.size == 0:
            raise ValueError("no cycles to fit")
        self.effect = effect
        self.geometry = geometry
        self.grid: Grid = cycles.grid
        self.params = space(effect)
        self.names = tuple(p.name for p in self.params)
        self.bias0 = float(bias0)
        memory = effect in MEMORY_EFFECTS
        sl = cycles.slip[self.idx]
        pv = cycles.prev_slip[self.idx] if memory else sl
        om = np.round(cycles.omega[self.idx], 9)
        keys = np.stack([om, pv, sl], axis=1)
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.ravel()
        self.n_groups = len(uniq)
        self.group_of = inv
        self.g_omega = uniq[:, 0]
        self.g_prev = uniq[:, 1]
        self.g_slip = uniq[:, 2]
        y = cycles.y[self.idx]
        self.g_n = np.bincount(inv, minlength=self.n_groups).astype(float)
        self.g_mean = np.stack([y[inv == g].mean(axis=0) for g in range(self.n_groups)])
        self.within = float(np.sum((y - self.g_mean[inv]) ** 2))
        self.n_values = y.size
        sims = np.unique(np.concatenate([np.stack([self.g_omega, self.g_slip], 1), np.stack([self.g_omega, self.g_prev], 1)]), axis=0)
        self.sim_omega = sims[:, 0]
        self.sim_slip = sims[:, 1]
        lookup = {(o, s): j for j, (o, s) in enumerate(map(tuple, sims))}
        self.g_sim = np.array([lookup[(o, s)] for o, s in zip(self.g_omega, self.g_slip)])
        self.g_sim_prev = np.array([lookup[(o, s)] for o, s in zip(self.g_omega, self.g_prev)])
        self._base = geometry.base_row()
        self.n_evals = 0
        self._cache = None

    # --- parameter vectors ---------------------------------------------------
    @property
    def zbounds(self):
        return [p.zbounds for p in self.params]

    def values(self, z) -> dict:
        return {p.name: float(p.from_z(zi)) for p, zi in zip(self.params, z)}

    def z_of(self, values: dict) -> np.ndarray:
        return np.array([float(p.to_z(values[p.name])) for p in self.params])

    def _rows(self, V: np.ndarray) -> np.ndarray:
        """Kernel rows ``(P * S, N_PARAMS)`` for candidate values ``V (P, D)`` and the distinct slips."""
        P, S = V.shape[0], len(self.sim_slip)
        col = {n: j for j, n in enumerate(self.names)}
        rows = np.tile(self._base, (P, S, 1))
        ks = V[:, col["kS"]][:, None]
        phis = V[:, col["phiS"]][:, None]
        phid = np.maximum(phis - V[:, col["dphi"]][:, None], 0.02)
        rows[:, :, K.P_SLIP] = self.sim_slip[None, :]
        rows[:, :, K.P_KS] = ks
        rows[:, :, K.P_MUS] = np.tan(phis)
        rows[:, :, K.P_MUD] = np.tan(phid)
        rows[:, :, K.P_KAPPA] = V[:, col["kappa"]][:, None]
        omega0 = np.broadcast_to(self.sim_omega[None, :], (P, S)).copy()
        e = self.effect
        if e == "contact_damping":
            d0 = self.geometry.MH * self.geometry.g / ks
            n = V[:, col["n_hc"]][:, None]
            rows[:, :, K.P_BHC] = V[:, col["c_hc"]][:, None] / d0**n
            rows[:, :, K.P_NHC] = n
        elif e == "stribeck":
            rows[:, :, K.P_VS] = V[:, col["vs"]][:, None]
            rows[:, :, K.P_SEXP] = V[:, col["delta"]][:, None]
            rows[:, :, K.P_VISC] = V[:, col["viscous"]][:, None]
        elif e == "speed_ripple":
            c, sn = V[:, col["ripple_c"]][:, None], V[:, col["ripple_s"]][:, None]
            a = np.hypot(c, sn)
            rows[:, :, K.P_RIPPLE_A] = a
            rows[:, :, K.P_RIPPLE_PH] = np.arctan2(sn, c)
            omega0 = omega0 / np.sqrt(1.0 - a**2)  # same mean speed (cycle period) as the log
        rows[:, :, K.P_OMEGA] = omega0
        return rows.reshape(P * S, K.N_PARAMS)

    # --- prediction ----------------------------------------------------------
    def predict(self, Z: np.ndarray, dt: float = DT_FINE) -> tuple[np.ndarray, np.ndarray]:
        """Bin predictions ``(P, G, nb)`` [m/s^2] (without the fitted bias) and an OK mask ``(P,)``."""
        Z = np.atleast_2d(Z)
        V = np.stack([p.from_z(Z[:, j]) for j, p in enumerate(self.params)], axis=1)
        P, S = V.shape[0], len(self.sim_slip)
        rows = self._rows(V)
        first = rows[:S]
        if P > 1 and np.array_equal(rows, np.tile(first, (P, 1))):
            # every candidate shares the physics (e.g. only sensor parameters vary): simulate once
            key = (first.tobytes(), dt)
            if self._cache is None or self._cache[0] != key:
                self._cache = (key,) + stance_fine(first, dt=dt, m=self.grid.m)
            fine = np.broadcast_to(self._cache[1], (P,) + self._cache[1].shape)
            status = np.tile(self._cache[2], P)
        else:
            fine, status = stance_fine(rows, dt=dt, m=self.grid.m)
        fine = fine.reshape(P, S, -1)
        ok = np.all(status.reshape(P, S) == K.STATUS_OK, axis=1)
        self.n_evals += P
        col = {n: j for j, n in enumerate(self.names)}
        geo, grid, e = self.geometry, self.grid, self.effect
        leg = geo.lS - geo.MH * geo.g / V[:, col["kS"]]
        if e == "speed_ripple":
            c, sn = V[:, col["ripple_c"]], V[:, col["ripple_s"]]
            a = np.hypot(c, sn)
            om = self.g_omega[None, :] / np.sqrt(1.0 - a**2)[:, None]
            rig = rigid_batch(grid, leg, om, a, np.arctan2(sn, c))
        else:
            rig = rigid_batch(grid, leg, self.g_omega)
        x = np.concatenate([fine[:, self.g_sim_prev], rig, fine[:, self.g_sim], rig[:, :, : grid.n_margin]], axis=2)
        x += geo.g
        out = self._sensor(x, V, col)
        out[~ok] = np.nan
        return out, ok

    def _sensor(self, x, V, col) -> np.ndarray:
        e = self.effect
        grid = self.grid
        if e == "touchdown_impact":
            amp = V[:, col["amplitude"]]
            if self.solve_linear:
                # the transient is linear in its amplitude: least squares with the bias, per candidate
                m0 = bin_average_batch(grid, x)
                h = np.zeros_like(m0)
                for om in np.unique(self.g_omega):
                    sel = self.g_omega == om
                    train = impact_batch(grid, om, np.ones(len(V)), V[:, col["tau"]], V[:, col["freq"]])
                    h[:, sel] = bin_average_batch(grid, train[:, None, :])
                w = self.g_n[None, :, None]
                r = self.g_mean[None] - m0
                # normal equations of r ~ b + A h, weights n_g, summed over groups and bins
                s1 = float(np.sum(self.g_n)) * self.grid.nb
                sh, shh = np.sum(w * h, axis=(1, 2)), np.sum(w * h * h, axis=(1, 2))
                sr, shr = np.sum(w * r, axis=(1, 2)), np.sum(w * h * r, axis=(1, 2))
                det = s1 * shh - sh * sh
                amp = np.where(det > 1e-12, (s1 * shr - sh * sr) / np.where(det > 1e-12, det, 1.0), 0.0)
                lo, hi = EFFECT_PARAMS["touchdown_impact"][0].lo, EFFECT_PARAMS["touchdown_impact"][0].hi
                amp = np.clip(amp, lo, hi)
                self.last_linear = {"amplitude": amp}
                return m0 + amp[:, None, None] * h
            for om in np.unique(self.g_omega):
                sel = self.g_omega == om
                x[:, sel] += impact_batch(grid, om, amp, V[:, col["tau"]], V[:, col["freq"]])[:, None]
        elif e == "imu_lowpass":
            for om in np.unique(self.g_omega):
                sel = self.g_omega == om
                x[:, sel] = lowpass_batch(x[:, sel], grid, om, V[:, col["cutoff"]], V[:, col["order"]])
        elif e == "imu_saturation":
            x = expected_clip(x + self.bias0, V[:, col["full_scale"]][:, None, None], self.noise_sigma) - self.bias0
        offset = V[:, col["offset"]] if e == "angle_offset" else None
        return bin_average_batch(grid, x, offset)

    def mse(self, Z: np.ndarray, dt: float = DT_FINE) -> tuple[np.ndarray, np.ndarray]:
        """``(mse (P,), bias (P,))``: mean squared residual [(m/s^2)^2] after the best constant bias."""
        pred, ok = self.predict(Z, dt)
        r = self.g_mean[None] - pred  # (P, G, nb)
        w = self.g_n[None, :, None]
        nb = self.grid.nb
        bias = np.sum(w * r, axis=(1, 2)) / (nb * self.g_n.sum())
        sse = np.sum(w * (r - bias[:, None, None]) ** 2, axis=(1, 2)) + self.within
        mse = sse / self.n_values
        mse = np.where(ok & np.isfinite(mse), mse, np.inf)
        return mse, bias + self.bias0


class CMA:
    """One CMA-ES instance on the unit cube (ask/tell), Hansen's tutorial settings.

    Points outside the cube are clipped for evaluation and penalised by
    their squared distance to it (so the mean stays inside). Several
    instances can be stepped together so that their candidates share one
    simulation batch.
    """

    def __init__(self, u0, sigma0: float, lam: int, rng: np.random.Generator):
        n = len(u0)
        self.n, self.lam, self.rng = n, lam, rng
        self.mu = lam // 2
        w = np.log(self.mu + 0.5) - np.log(np.arange(1, self.mu + 1))
        self.w = w / w.sum()
        self.mueff = 1.0 / np.sum(self.w**2)
        mueff = self.mueff
        self.cc = (4 + mueff / n) / (n + 4 + 2 * mueff / n)
        self.cs = (mueff + 2) / (n + mueff + 5)
        self.c1 = 2 / ((n + 1.3) ** 2 + mueff)
        self.cmu = min(1 - self.c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
        self.damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (n + 1)) - 1) + self.cs
        self.chin = math.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n * n))
        self.m = np.clip(np.array(u0, dtype=float), 0.0, 1.0)
        self.sigma = float(sigma0)
        self.pc = np.zeros(n)
        self.ps = np.zeros(n)
        self.C = np.eye(n)
        self.B = np.eye(n)
        self.D = np.ones(n)
        self.gen = 0
        self.best_u = self.m.copy()
        self.best_f = np.inf
        self._X = None

    def ask(self) -> np.ndarray:
        """``lam`` candidates, clipped to the cube."""
        z = self.rng.standard_normal((self.lam, self.n))
        self._X = self.m + self.sigma * (z @ (self.B * self.D).T)
        return np.clip(self._X, 0.0, 1.0)

    def tell(self, fx: np.ndarray) -> None:
        X = self._X
        Xc = np.clip(X, 0.0, 1.0)
        fx = np.asarray(fx, dtype=float)
        finite = fx[np.isfinite(fx)]
        scale = np.max(np.abs(finite), initial=1.0)
        fx = np.where(np.isfinite(fx), fx, 10 * scale) + 1e3 * scale * np.sum((X - Xc) ** 2, axis=1)
        order = np.argsort(fx)
        if fx[order[0]] < self.best_f:
            self.best_f, self.best_u = float(fx[order[0]]), Xc[order[0]].copy()
        self.gen += 1
        n, cs, cc, c1, cmu = self.n, self.cs, self.cc, self.c1, self.cmu
        sel = order[: self.mu]
        m_old = self.m
        self.m = self.w @ X[sel]
        y_w = (self.m - m_old) / self.sigma
        inv_sqrt = (self.B / self.D) @ self.B.T
        self.ps = (1 - cs) * self.ps + math.sqrt(cs * (2 - cs) * self.mueff) * (inv_sqrt @ y_w)
        hsig = np.linalg.norm(self.ps) / math.sqrt(1 - (1 - cs) ** (2 * self.gen)) / self.chin < 1.4 + 2 / (n + 1)
        self.pc = (1 - cc) * self.pc + hsig * math.sqrt(cc * (2 - cc) * self.mueff) * y_w
        Y = (X[sel] - m_old) / self.sigma
        C = (1 - c1 - cmu) * self.C + c1 * (np.outer(self.pc, self.pc) + (1 - hsig) * cc * (2 - cc) * self.C)
        C += cmu * (Y.T * self.w) @ Y
        self.sigma *= math.exp((cs / self.damps) * (np.linalg.norm(self.ps) / self.chin - 1))
        self.sigma = min(self.sigma, 1.0)
        self.C = np.triu(C) + np.triu(C, 1).T
        evals, self.B = np.linalg.eigh(self.C)
        self.D = np.sqrt(np.maximum(evals, 1e-20))

    @property
    def spread(self) -> float:
        return self.sigma * float(self.D.max())


#: Scales [g, g, g/rad, rad, g, rad] of the descriptor groups (window means, window RMS, window RMS of
#: the slope, stance energy quantiles, stance extremes, onset) in the search's first stage.
DESCRIPTOR_SCALES = (0.01, 0.02, 1.0, 0.02, 0.03, 0.01)
#: Threshold of the onset descriptor: deviation from the stick level [g].
ONSET_G = 0.03
#: Windows of the cycle over which the descriptors are taken.
DESCRIPTOR_WINDOWS = 10
#: Integration step of the first (descriptor) stage [s].
DT_COARSE = 8e-4
#: Effects that need finer search steps ``(coarse, search)`` [s]: the Stribeck curve's velocity scale
#: (~0.01 m/s) is crossed in one step of the foot's acceleration at 4e-4 s (waveform error 0.01-0.04 g
#: at the true parameters, against 0.002-0.005 g at 2e-4 s).
FINE_SEARCH_EFFECTS = {"stribeck": (2e-4, 2e-4)}
#: Most slip levels the first stage uses.
COARSE_LEVELS = 4


def descriptors(y: np.ndarray, grid: Grid, g: float = 9.81) -> np.ndarray:
    """Phase-insensitive summary of cycles ``y (..., nb)`` [m/s^2] -> ``(..., K)``, each term scaled to ~1.

    Per window of the cycle (:data:`DESCRIPTOR_WINDOWS`): the mean, the RMS
    about it and the RMS of the slope d az/d phi (amplitude times
    frequency); over the stance half: the phases by which 10/25/50/75/90 %
    of the energy about the stick level has accumulated, and the extremes
    above/below the stick level, and the onset (first phase where the
    signal leaves the stick level by :data:`ONSET_G`, interpolated between
    bins). Signals are smoothed over 5 bins first.
    Unlike the waveform itself these change smoothly when an oscillation's
    phase drifts, which makes them a good first-stage objective.
    """
    nb = grid.nb
    dphi = 2 * grid.half / nb
    k = 5
    a = y / g
    pad = np.concatenate([np.repeat(a[..., :1], k // 2, -1), a, np.repeat(a[..., -1:], k // 2, -1)], axis=-1)
    c = np.cumsum(pad, axis=-1)
    c = np.concatenate([np.zeros(c.shape[:-1] + (1,)), c], axis=-1)
    a = (c[..., k:] - c[..., :-k]) / k
    nw = DESCRIPTOR_WINDOWS
    w = a.reshape(a.shape[:-1] + (nw, nb // nw))
    mean = w.mean(-1)
    rms = np.sqrt(np.mean((w - mean[..., None]) ** 2, -1))
    d = np.diff(a, axis=-1, append=a[..., -1:]) / dphi
    rmsd = np.sqrt(np.mean(d.reshape(d.shape[:-1] + (nw, nb // nw)) ** 2, -1))
    st = a[..., nb // 2 :]
    stick = st[..., :5].mean(-1)
    e = np.cumsum((st - stick[..., None]) ** 2, axis=-1)
    e = e / np.maximum(e[..., -1:], 1e-12)
    qs = np.stack([np.sum(e < q, axis=-1) * dphi for q in (0.1, 0.25, 0.5, 0.75, 0.9)], -1)
    ext = np.stack([st.max(-1) - stick, stick - st.min(-1)], -1)
    # onset: first phase where |a - stick| exceeds ONSET_G, interpolated between bins (pi/nL: never)
    dev = np.abs(st - stick[..., None])
    above = dev > ONSET_G
    first = np.where(above.any(-1), np.argmax(above, axis=-1), st.shape[-1])
    j = np.clip(first, 1, st.shape[-1] - 1)
    d1 = np.take_along_axis(dev, j[..., None], -1)[..., 0]
    d0 = np.take_along_axis(dev, (j - 1)[..., None], -1)[..., 0]
    frac = np.clip((ONSET_G - d0) / np.maximum(d1 - d0, 1e-12), 0.0, 1.0)
    onset = np.where(first >= st.shape[-1], grid.half, (j - 1 + frac + 0.5) * dphi)
    s = DESCRIPTOR_SCALES
    return np.concatenate([mean / s[0], rms / s[1], rmsd / s[2], qs / s[3], ext / s[4], onset[..., None] / s[5]], -1)


def _spread_levels(slips: np.ndarray, k: int) -> np.ndarray:
    """Up to ``k`` of the distinct values, spread over their range (ends included)."""
    levels = np.unique(slips)
    if len(levels) <= k:
        return levels
    pick = np.unique(np.round(np.linspace(0, len(levels) - 1, k)).astype(int))
    return levels[pick]


def _debug(*args):
    if os.environ.get("SLIPEST_FIT_DEBUG"):
        print("[fit]", *args, flush=True)


def run_cmas(f: Callable[[np.ndarray], np.ndarray], starts, rng: np.random.Generator, lam: int, max_gen: int,
             dims=None, keep_after: dict | None = None, tol: float = 1e-4,
             progress: Callable[[], None] | None = None) -> list[tuple[np.ndarray, float]]:
    """Step several CMA-ES instances together (one batched call of ``f`` per generation).

    ``f`` maps ``(P, D)`` points of the unit cube to ``(P,)`` values.
    ``starts``: ``(u0, sigma0)`` pairs of full points; each instance searches
    the coordinates ``dims`` (default all) and keeps the others at its
    start's values (e.g. a categorical parameter). ``keep_after``:
    ``{generation: k}`` keeps the ``k`` instances with the best values so far
    (successive halving). Returns ``(best point, best value)`` per surviving
    instance, best first.
    """
    starts = list(starts)
    D = len(starts[0][0])
    dims = np.arange(D) if dims is None else np.asarray(dims, dtype=np.int64)
    runs = [(CMA(np.asarray(u)[dims], s, lam, rng), np.array(u, dtype=float)) for u, s in starts]
    keep_after = keep_after or {}
    for gen in range(1, max_gen + 1):
        active = [(r, t) for r, t in runs if r.spread >= tol]
        if not active:
            break
        blocks = []
        for r, t in active:
            U = np.tile(t, (lam, 1))
            U[:, dims] = r.ask()
            blocks.append(U)
        fx = f(np.vstack(blocks))
        for j, (r, _) in enumerate(active):
            r.tell(fx[j * lam : (j + 1) * lam])
        if gen in keep_after:
            runs = sorted(runs, key=lambda rt: rt[0].best_f)[: keep_after[gen]]
        if progress is not None:
            progress()
    out = []
    for r, t in sorted(runs, key=lambda rt: rt[0].best_f):
        u = t.copy()
        u[dims] = r.best_u
        out.append((u, r.best_f))
    return out


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


def fit(cycles: CycleSet, idx, effect: str | None, geometry: Geometry, *, seed=0, budget: FitBudget = FitBudget(),
        init: list[dict] | None = None, fixed: dict | None = None, bias0: float = 0.0,
        progress: Callable[[], None] | None = None) -> FitResult:
    """Fit soil (+ ``effect``) to the cycles ``idx``; the objective is the mean squared waveform residual.

    1. Differential evolution (scipy, ``vectorized=True``: a whole
       generation is one simulation batch) on the :func:`descriptors` misfit
       (smooth in the parameters: it finds the basin), at ``DT_COARSE``, on
       at most ``COARSE_LEVELS`` slip levels; the initial population is a
       Latin-hypercube sample of the search ranges plus the ``init`` points
       (values dicts; missing effect parameters at their neutral values);
    2. CMA-ES on the waveform residual (all training cycles, ``DT_SEARCH``)
       from the best of the stage-1 result and the ``init`` points (one
       instance per value of a categorical parameter, the worse dropped
       after a third of the generations);
    3. a short small-step CMA-ES at ``DT_FINE``.

    ``fixed``: parameter values held fixed (not searched). ``progress()`` is
    called once per generation.
    """
    idx = np.asarray(idx, dtype=np.int64)
    ev = Evaluator(cycles, idx, effect, geometry, bias0=bias0, solve_linear=True)
    levels = _spread_levels(cycles.slip[idx], COARSE_LEVELS)
    ev1 = Evaluator(cycles, idx[np.isin(cycles.slip[idx], levels)], effect, geometry, bias0=bias0,
                    solve_linear=True)
    rng = np.random.default_rng(seed)
    fixed = dict(fixed or {})
    D = len(ev.params)
    lo = np.array([p.zbounds[0] for p in ev.params])
    hi = np.array([p.zbounds[1] for p in ev.params])
    width = hi - lo
    integer = np.array([p.integer for p in ev.params])
    fixed_j = [j for j, p in enumerate(ev.params) if p.name in fixed or p.linear]
    free = [j for j in range(D) if j not in fixed_j]
    cat = [j for j, p in enumerate(ev.params) if p.categorical and j not in fixed_j]
    cont = [j for j in free if j not in cat]
    grid = cycles.grid
    d_data = descriptors(ev1.g_mean, grid)
    wg = ev1.g_n / ev1.g_n.sum()
    dt_coarse, dt_search = FINE_SEARCH_EFFECTS.get(effect, (DT_COARSE, DT_SEARCH))

    def to_z(U):
        Z = lo + np.clip(U, 0, 1) * width
        Z[:, integer] = np.round(Z[:, integer])
        return Z

    def to_u(z):
        return (np.asarray(z, dtype=float) - lo) / width

    def full_u(vals: dict) -> np.ndarray:
        full = {}
        for p in ev.params:
            v = fixed.get(p.name, vals.get(p.name, neutral_value(effect, p)))
            full[p.name] = float(np.clip(v, p.lo, p.hi))
        return to_u(ev.z_of(full))

    template = full_u({})
    seeds = np.array([full_u(v) for v in (init or [])]).reshape(-1, D)

    def f_desc(U):
        out = np.empty(len(U))
        for i in range(0, len(U), 256):
            pred, ok = ev1.predict(to_z(U[i : i + 256]), dt_coarse)
            dd = descriptors(np.nan_to_num(pred), grid)
            m = np.sum(np.mean((dd - d_data[None]) ** 2, axis=2) * wg[None], axis=1)
            out[i : i + 256] = np.where(ok & np.isfinite(m), m, 1e6)
        return out

    def f_wave(dt):
        def f(U):
            m, _ = ev.mse(to_z(U), dt)
            return np.where(np.isfinite(m), m, 1e6)

        return f

    b = budget
    if free:
        # stage 1: differential evolution over the free coordinates of the unit cube
        n_free = len(free)

        def f_de(x):
            X = np.atleast_2d(x.T) if x.ndim == 2 else x[None, :]
            U = np.tile(template, (X.shape[0], 1))
            U[:, free] = X
            return f_desc(U)

        n_pop = max(b.de_popsize * n_free, 10)
        sob = qmc.LatinHypercube(n_free, seed=rng).random(n_pop)
        if len(seeds):
            sob[: min(len(seeds), n_pop // 4)] = seeds[: n_pop // 4][:, free]
        step = np.zeros(n_free)
        for jj, j in enumerate(free):
            if integer[j]:
                step[jj] = 1.0 / width[j]
        int_free = np.array([integer[j] for j in free])

        def cb(*_a, **_k):
            if progress is not None:
                progress()
            return False

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
            res = differential_evolution(f_int, bounds, init=init_pop, maxiter=b.de_gens, tol=1e-7,
                                         mutation=(0.5, 1.0), recombination=0.9, seed=rng, polish=False,
                                         vectorized=True, updating="deferred", integrality=int_free, callback=cb)
            x_best = (res.x - off) / scale
        else:
            res = differential_evolution(f_de, [(0.0, 1.0)] * n_free, init=sob, maxiter=b.de_gens, tol=1e-7,
                                         mutation=(0.5, 1.0), recombination=0.9, seed=rng, polish=False,
                                         vectorized=True, updating="deferred", callback=cb)
            x_best = res.x
        u1 = template.copy()
        u1[free] = x_best
        cand = np.vstack([u1[None], seeds])
    else:
        cand = seeds if len(seeds) else template[None]
    fc = f_wave(dt_search)(cand)
    _debug("stage1", effect, sorted(fixed), np.round(np.sqrt(fc) / 9.81, 4))
    j = int(np.argmin(fc))
    u2, f2 = cand[j], fc[j]
    if cont:
        starts2 = [(cand[j], 0.02)]
        if cat:
            jc = cat[0]
            for value in np.unique(np.round(np.linspace(0, 1, int(round(width[jc])) + 1), 9)):
                if abs(value - cand[j, jc]) < 1e-9:
                    continue
                start = cand[j].copy()
                start[jc] = value
                starts2.append((start, 0.02))
        u2b, f2b = run_cmas(f_wave(dt_search), starts2, rng, b.lam, b.gen_wave, dims=cont, tol=2e-4,
                            keep_after={max(1, b.gen_wave // 3): 1}, progress=progress)[0]
        if f2b < f2:
            u2, f2 = u2b, f2b
    cand = np.vstack([u2[None], seeds])
    fc = f_wave(DT_FINE)(cand)
    j = int(np.argmin(fc))
    u3, f3 = cand[j], fc[j]
    if cont:
        u3b, f3b = run_cmas(f_wave(DT_FINE), [(cand[j], 0.004)], rng, max(10, b.lam // 2), b.gen_fine, dims=cont,
                            tol=1e-5, progress=progress)[0]
        if f3b < f3:
            u3, f3 = u3b, f3b
    _debug("stage2/3", np.sqrt(min(f2, 1e9)) / 9.81, np.sqrt(f3) / 9.81)
    z = to_z(u3[None])[0]
    mse, bias = ev.mse(z[None], DT_FINE)
    values = ev.values(z)
    for name, v in ev.last_linear.items():  # parameters solved in closed form
        values[name] = float(v[0])
    return FitResult(effect=effect, values=values, bias=float(bias[0]), mse_train=float(mse[0]),
                     n_evals=ev.n_evals + ev1.n_evals, x=ev.z_of(values))


def signature_seeds(cycles: CycleSet, idx, effect: str, geometry: Geometry, nominal: FitResult) -> list[dict]:
    """Effect parameters read off the data directly where an effect leaves a model-free signature.

    * ``speed_ripple``: the encoder's leg speed per phase bin (``cycles.speed``)
      fitted by ``w0 (1 + c sin(nL phi) + s cos(nL phi))`` (linear least
      squares): ``ripple_c = A cos(phase) = c``, ``ripple_s = A sin(phase) = s``;
    * ``touchdown_impact``: the rigid half's residual against the nominal fit
      (the rigid half's kinematics do not depend on the soil beyond the leg
      length), fitted by the transient train on a grid of ``tau`` x ``freq``
      with the amplitude in closed form;
    * ``imu_saturation``: the largest bin average (clipped tops are flat).

    Returns a list of (partial) value dicts, empty for other effects. These
    seed the fit; the fit decides.
    """
    idx = np.asarray(idx, dtype=np.int64)
    grid = cycles.grid
    phi = grid.bin_centres
    if effect == "speed_ripple":
        w = np.nanmean(cycles.speed[idx], axis=0)
        ok = np.isfinite(w)
        if ok.sum() < 10:
            return []
        X = np.stack([np.ones(ok.sum()), np.sin(grid.n_legs * phi[ok]), np.cos(grid.n_legs * phi[ok])], axis=1)
        coef, *_ = np.linalg.lstsq(X, w[ok], rcond=None)
        if not coef[0] > 0:
            return []
        return [{"ripple_c": float(coef[1] / coef[0]), "ripple_s": float(coef[2] / coef[0])}]
    if effect == "touchdown_impact":
        pred = evaluate(cycles, idx, nominal, geometry)["pred"]
        r = np.mean(cycles.y[idx] - pred, axis=0)[: grid.nb_half]
        omega = float(np.mean(cycles.omega[idx]))
        t = (phi[: grid.nb_half] + grid.half) / omega
        period = 2 * grid.half / omega
        best = (0.0, None)
        for tau in np.geomspace(0.02, 2.0, 16):
            for f in np.geomspace(3.0, 60.0, 40):
                n_back = int(math.ceil(14 * tau / period)) + 1
                h = sum(
                    np.where(t + j * period >= 0,
                             np.exp(-(t + j * period) / tau) * np.sin(2 * math.pi * f * (t + j * period)), 0.0)
                    for j in range(n_back + 1)
                )
                hh = float(h @ h)
                if hh <= 0:
                    continue
                gain = float(r @ h) ** 2 / hh  # reduction of the squared residual
                if gain > best[0]:
                    best = (gain, {"amplitude": float(r @ h) / hh, "tau": float(tau), "freq": float(f)})
        return [best[1]] if best[1] else []
    if effect == "imu_saturation":
        return [{"full_scale": float(np.max(cycles.y[idx]))}]
    return []


def fit_effect(cycles: CycleSet, idx, effect: str, geometry: Geometry, nominal: FitResult, *, seed=0,
               budget: FitBudget = FitBudget(), progress: Callable[[], None] | None = None) -> FitResult:
    """Fit soil + ``effect`` to the cycles ``idx`` with a joint :func:`fit`.

    Its first population holds, besides the quasi-random points, the
    nominal soil with the effect off and, for an effect with a model-free
    signature in the data (:func:`signature_seeds`), the soil refitted with
    the effect parameters read off the data held fixed (a 4-D fit at half
    the budget): the nominal fit absorbs part of an effect into a biased
    soil, and a strong effect (a touchdown transient) can dominate the
    joint search's first stage.
    """
    soil = nominal.soil()
    init = [soil]
    for j, v in enumerate(signature_seeds(cycles, idx, effect, geometry, nominal)):
        r = fit(cycles, idx, effect, geometry, seed=seed + 100 + j, budget=budget.scaled(0.5),
                init=[{**soil, **v}], fixed=v, bias0=nominal.bias, progress=progress)
        init.append(r.values)
    return fit(cycles, idx, effect, geometry, seed=seed, budget=budget, init=init, bias0=nominal.bias,
               progress=progress)


def neutral_value(effect: str | None, p: FitParam) -> float:
    """The value of a fitted parameter at which its effect is (nearly) off."""
    neutral = {
        "c_hc": 0.0,
        "n_hc": 1.0,
        "vs": 0.02,  # no value is neutral: mu(0) = muS changes the break-away dynamics even for tiny vs
        "delta": 2.0,
        "viscous": 0.0,
        "amplitude": 0.0,
        "ripple_c": 0.0,
        "ripple_s": 0.0,
        "tau": 0.05,
        "freq": 10.0,
        "cutoff": p.hi,
        "order": 2,
        "full_scale": p.hi,
        "offset": 0.0,
    }
    return float(np.clip(neutral.get(p.name, 0.5 * (p.lo + p.hi)), p.lo, p.hi))


def evaluate(cycles: CycleSet, idx, result: FitResult, geometry: Geometry, dt: float = DT_FINE) -> dict:
    """Residuals of a fitted model on cycles ``idx`` (e.g. held out): per-cycle predictions and errors.

    Returns ``pred (C, nb)`` [m/s^2] including the fitted bias, ``resid (C, nb)`` and ``mse``.
    """
    ev = Evaluator(cycles, idx, result.effect, geometry, bias0=0.0)
    z = ev.z_of(result.values)
    if result.effect == "imu_saturation":
        ev.bias0 = result.bias
        pred, ok = ev.predict(z[None], dt)
        pred = pred[0] + 0.0
    else:
        pred, ok = ev.predict(z[None], dt)
        pred = pred[0]
    pred_c = pred[ev.group_of] + result.bias
    y = cycles.y[ev.idx]
    resid = y - pred_c
    return {"pred": pred_c, "resid": resid, "mse": float(np.mean(resid**2)) if ok[0] else float("inf"), "ok": bool(ok[0])}
