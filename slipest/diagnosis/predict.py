"""The model's prediction of logged leg cycles on a phase grid, for many candidates at once.

A logged cycle is the leg phase ``phi`` in ``[-pi/nL, pi/nL)`` (the stream
convention of :mod:`slipest.model.stream`): the rigid half (``phi < 0``,
the hub riding a planted spoke) then the stick-slip stance (``phi >= 0``).
The model's cycle is deterministic given the slip and the soil, so the
prediction for every cycle at one slip is one stance simulation.

Pipeline, mirroring the simulated stream (SI units; ``az`` is the specific
force with gravity, z up); arrays are ``(P candidates, G groups, ...)``;
:class:`Evaluator` runs it for candidate parameter sets (soil + at most one
catalog effect, :mod:`slipest.model.effects`) on a set of logged cycles:

1. kernel rows: the soil, the slips, and the effect's kernel columns
   (:meth:`~slipest.model.effects.base.Effect.kernel_columns`);
   :func:`stance_fine` integrates many stances in one compiled parallel loop
   (the project's kernel, :func:`slipest.model.kernel.integrate_stance`)
   and averages each stance's ``zH''`` over ``m`` uniform bins of leg angle
   ``[0, pi/nL)`` (the *fine grid*), so only ``(B, m)`` numbers leave the
   loop;
2. a cycle is laid out on an *extended* fine grid of true phase ``psi`` in
   ``[-2 pi/nL, pi/nL + margin)`` (:class:`Grid`): the previous cycle's
   stance (the source of the filter memory and of a positive encoder
   offset), the rigid half (:func:`rigid_batch`: kinematic
   ``-l w^2 cos phi``, ``l = lS - MH g/kS``, or the effect's
   :meth:`~slipest.model.effects.base.Effect.rigid`), the stance, and the
   start of the next rigid half;
3. the effect's sensor part acts on it and averages it over the *analysis
   bins* of the logged phase
   (:meth:`~slipest.model.effects.base.Effect.sense`, by default plain
   :func:`bin_average_batch`);
4. :meth:`Evaluator.mse`: the residual against the logged bin means after
   the best constant bias (with ``common``: after the best waveform common
   to every cycle, a phase-locked disturbance profiled out).

Everything is pure numpy/numba; nothing here knows about files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np

from slipest.features import bin_mean_fill
from slipest.model import kernel as K
from slipest.model.effects import EFFECTS, Effect, FitParam
from slipest.model.params import StickSlipParams

if TYPE_CHECKING:
    from slipest.diagnosis.cycles import CycleSet

#: Fine-grid bins per half cycle (``pi/nL`` of leg angle) [-].
FINE_PER_HALF = 500
#: Integration step of the refinement and of every reported gap [s] (the project's default).
DT_FINE = 1e-4

#: Soil (and leg) parameters of the nominal model: stiffness, static friction
#: angle, friction angle drop ``phiS - phiD``, lateral leg stiffness ratio.
SOIL_PARAMS = (
    FitParam("kS", "N/m", 400.0, 2200.0, log=True),
    FitParam("phiS", "rad", 0.25, 0.85),
    FitParam("dphi", "rad", 0.0, 0.40),
    FitParam("kappa", "-", 0.12, 0.7),
)
SOIL_NAMES = tuple(p.name for p in SOIL_PARAMS)

#: The nominal model: no effect (every hook at its default).
NO_EFFECT = Effect()


def effect_model(effect: str | None) -> Effect:
    """The catalog effect of a name (None: :data:`NO_EFFECT`); ValueError naming the known ones."""
    if effect is None:
        return NO_EFFECT
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; known: {', '.join(EFFECTS)}")
    return EFFECTS[effect]


def space(effect: str | None) -> tuple[FitParam, ...]:
    """The fitted parameters of the nominal model (``None``) or of nominal + ``effect``."""
    return SOIL_PARAMS + effect_model(effect).fit_params


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


@numba.njit(cache=True, parallel=True)
def _stance_fine_kernel(params, dt, max_steps, m, out, status):
    n_b = params.shape[0]
    for b in numba.prange(n_b):
        rec = np.empty((max_steps, 2))
        res = np.empty(K.N_RESULTS)
        K.integrate_stance(params[b], dt, max_steps, res, rec)
        status[b] = res[K.R_STATUS]
        n = int(res[K.R_N_STEPS])
        half = math.pi / params[b, K.P_NL]
        scale = m / half
        acc = np.zeros(m)
        cnt = np.zeros(m)
        for i in range(min(n, max_steps)):
            j = int(rec[i, 0] * scale)
            if j >= m:
                j = m - 1
            acc[j] += rec[i, 1]
            cnt[j] += 1.0
        bin_mean_fill(acc, cnt)
        for j in range(m):
            out[b, j] = acc[j]


def stance_fine(params: np.ndarray, dt: float = 1e-4, m: int = FINE_PER_HALF) -> tuple[np.ndarray, np.ndarray]:
    """Stance ``zH''`` [m/s^2] (gravity-free) averaged over ``m`` uniform leg-angle bins of ``[0, pi/nL)``.

    ``params``: kernel parameter matrix ``(B, N_PARAMS)``. Returns
    ``(az_fine (B, m), status (B,))``; rows whose status is not OK are NaN.
    """
    params = np.ascontiguousarray(params, dtype=np.float64)
    if params.ndim != 2 or params.shape[1] != K.N_PARAMS:
        raise ValueError(f"parameter matrix must have shape (B, {K.N_PARAMS})")
    out = np.empty((params.shape[0], m))
    status = np.empty(params.shape[0])
    if params.shape[0]:
        angle = float(np.max(np.pi / params[:, K.P_NL]))
        omega = float(np.min(params[:, K.P_OMEGA] * (1.0 - params[:, K.P_RIPPLE_A])))
        max_steps = int(math.ceil(angle / (omega * dt))) + 2
        _stance_fine_kernel(params, float(dt), max_steps, int(m), out, status)
    status = status.astype(np.int64)
    out[status != K.STATUS_OK] = np.nan
    return out, status


@dataclass(frozen=True)
class Grid:
    """The extended fine grid of one cycle and the analysis bins.

    n_legs [-]; m: fine bins per half cycle; nb_half: analysis bins per
    half cycle (``m`` a multiple of it); margin_halves: how much of the next
    cycle the grid covers, in half cycles. ``psi``: fine-bin centres [rad]
    of true phase relative to the cycle's midstance, from ``-2 pi/nL``
    (previous stance) to ``pi/nL + margin``.
    """

    n_legs: int
    m: int = FINE_PER_HALF
    nb_half: int = 125
    margin_halves: float = 0.3

    def __post_init__(self):
        if self.m % self.nb_half:
            raise ValueError("the fine bins per half cycle must be a multiple of the analysis bins")

    @property
    def half(self) -> float:
        return math.pi / self.n_legs

    @property
    def dpsi(self) -> float:
        return self.half / self.m

    @property
    def n_margin(self) -> int:
        return int(round(self.margin_halves * self.m))

    @property
    def n_ext(self) -> int:
        return 3 * self.m + self.n_margin

    @property
    def psi(self) -> np.ndarray:
        return -2 * self.half + (np.arange(self.n_ext) + 0.5) * self.dpsi

    @property
    def nb(self) -> int:
        """Analysis bins per cycle."""
        return 2 * self.nb_half

    @property
    def bin_edges(self) -> np.ndarray:
        """Edges [rad] of the analysis bins of logged phase over ``[-pi/nL, pi/nL)``."""
        return np.linspace(-self.half, self.half, self.nb + 1)

    @property
    def bin_centres(self) -> np.ndarray:
        e = self.bin_edges
        return 0.5 * (e[1:] + e[:-1])

    @property
    def rigid_psi(self) -> np.ndarray:
        """Fine-bin centres [rad] of the rigid half ``[-pi/nL, 0)``."""
        return -self.half + (np.arange(self.m) + 0.5) * self.dpsi

    def time(self, omega: float) -> np.ndarray:
        """Time [s] of the extended grid's centres since the cycle's start (phase ``-pi/nL``), constant speed [rad/s]."""
        return (self.psi + self.half) / omega


def rigid_batch(grid: Grid, leg: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Rigid-half ``zH''`` [m/s^2] at constant leg speed, candidates ``leg (P,)`` [m], groups ``omega (G,)`` [rad/s].

    ``-l w^2 cos(phi)`` on the rigid half's fine bins. Returns ``(P, G, m)``.
    """
    phi = grid.rigid_psi
    leg = np.asarray(leg, dtype=float)[:, None, None]
    w0 = np.asarray(omega, dtype=float)
    w0 = np.broadcast_to(w0, (leg.shape[0],) + w0.shape[-1:])[:, :, None]
    return -leg * np.cos(phi)[None, None, :] * w0**2


def bin_average_batch(grid: Grid, x: np.ndarray, offset=None) -> np.ndarray:
    """Averages of ``x (P, G, n_ext)`` over the analysis bins ``(P, G, nb)``, the encoder reading ``offset`` [rad] ahead.

    offset: none, one per candidate ``(P,)``, or one per candidate and bin
    edge ``(P, nb + 1)`` (a warped encoder: the bin edge at logged phase
    ``e`` sits at true phase ``e - offset``; increasing in ``e``).
    """
    P, G, n = x.shape
    if offset is None:
        r = grid.m // grid.nb_half
        return x[:, :, grid.m : 3 * grid.m].reshape(P, G, grid.nb, r).mean(axis=3)
    offset = np.asarray(offset, dtype=float)
    if offset.ndim == 1:
        offset = offset[:, None]
    pos = (grid.bin_edges[None, :] - offset + 2 * grid.half) / grid.dpsi  # (P, nb+1)
    pos = np.clip(pos, 0.0, n - 1e-9)
    i = np.floor(pos).astype(np.int64)
    frac = pos - i
    csum = np.concatenate([np.zeros((P, G, 1)), np.cumsum(x, axis=2)], axis=2)
    idx = np.broadcast_to(i[:, None, :], (P, G, i.shape[1]))
    c_at = np.take_along_axis(csum, idx, axis=2) + frac[:, None, :] * np.take_along_axis(x, idx, axis=2)
    return np.diff(c_at, axis=2) / np.diff(pos, axis=1)[:, None, :]


class Evaluator:
    """Prediction and objective of candidates on a fixed set of cycles (see the module docstring).

    cycles: the :class:`~slipest.diagnosis.cycles.CycleSet`; idx: the
    cycles used; effect: catalog name or None; geometry: the known hardware;
    bias0 [m/s^2]: bias assumed before the sampled stages (clipping), the
    rest is fitted in closed form; solve_linear: the effect's ``linear`` fit
    parameters are solved in closed form (their values, per candidate, in
    :attr:`last_linear` after each prediction) instead of taken from the
    candidates; common: the residual is taken after the best waveform common
    to every cycle (:meth:`common_waveform`, one value per bin: a disturbance
    locked to the leg phase that the soil and ``kappa`` must not absorb)
    instead of the best constant bias; only for the nominal model (``effect``
    None).

    Cycles with the same leg speed and slip (and, for effects with memory
    across the cycle boundary, the same previous slip and previous leg
    speed: the previous stance is simulated at its own speed; for effects
    with a history since the log's start, the same count of touchdowns when
    that is within the effect's ``history_s``) share one prediction
    (a *group*), so the objective only needs the groups' means and one
    stance simulation per distinct slip. The evaluator is the
    :class:`~slipest.model.effects.base.PredictionContext` of the effect's
    sensor part.
    """

    def __init__(self, cycles: CycleSet, idx, effect: str | None, geometry: Geometry, bias0: float = 0.0,
                 solve_linear: bool = False, common: bool = False):
        if common and effect is not None:
            raise ValueError("a common waveform is profiled out of the nominal model's fit only (effect None)")
        self.cycles = cycles
        self.solve_linear = solve_linear
        self.common = bool(common)
        self.last_linear: dict = {}
        self.noise_sigma = float(np.sqrt(np.mean(cycles.noise**2))) if np.all(np.isfinite(cycles.noise)) else 0.0
        self.idx = np.asarray(idx, dtype=np.int64)
        if self.idx.size == 0:
            raise ValueError("no cycles to fit")
        self.effect = effect
        self.model = effect_model(effect)
        self.geometry = geometry
        self.grid: Grid = cycles.grid
        self.params = space(effect)
        self.names = tuple(p.name for p in self.params)
        self._col = {n: j for j, n in enumerate(self.names)}
        self.bias0 = float(bias0)
        sl = cycles.slip[self.idx]
        pv = cycles.prev_slip[self.idx] if self.model.memory else sl
        om = np.round(cycles.omega[self.idx], 9)
        pom = np.round(cycles.prev_omega[self.idx], 9) if self.model.memory else om
        touch = np.full(len(self.idx), np.inf)
        if self.model.history_s is not None:
            # cycles whose history since the log's start matters: grouped by their count of touchdowns
            n = cycles.touchdowns[self.idx]
            touch = np.where(n * (2 * self.grid.half / cycles.omega[self.idx]) < self.model.history_s, n, np.inf)
        keys = np.stack([om, pom, pv, sl, touch], axis=1)
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        inv = inv.ravel()
        self.n_groups = len(uniq)
        self.group_of = inv
        self.g_omega = uniq[:, 0]
        self.g_prev_omega = uniq[:, 1]
        self.g_prev = uniq[:, 2]
        self.g_slip = uniq[:, 3]
        self.g_touchdowns = uniq[:, 4]
        y = cycles.y[self.idx]
        self.g_n = np.bincount(inv, minlength=self.n_groups).astype(float)
        self.g_mean = np.stack([y[inv == g].mean(axis=0) for g in range(self.n_groups)])
        self.within = float(np.sum((y - self.g_mean[inv]) ** 2))
        self.n_values = y.size
        sims = np.unique(np.concatenate([np.stack([self.g_omega, self.g_slip], 1),
                                         np.stack([self.g_prev_omega, self.g_prev], 1)]), axis=0)
        self.sim_omega = sims[:, 0]
        self.sim_slip = sims[:, 1]
        lookup = {(o, s): j for j, (o, s) in enumerate(map(tuple, sims))}
        self.g_sim = np.array([lookup[(o, s)] for o, s in zip(self.g_omega, self.g_slip)])
        self.g_sim_prev = np.array([lookup[(o, s)] for o, s in zip(self.g_prev_omega, self.g_prev)])
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

    def _catalog(self, V: np.ndarray, shape=None) -> dict:
        """The effect's catalog values for candidate values ``V (P, D)`` (columns reshaped by ``shape``)."""
        cols = {n: (V[:, j] if shape is None else shape(V[:, j])) for j, n in enumerate(self.names)}
        fitted = {p.name: cols[p.name] for p in self.model.fit_params}
        soil = {n: cols[n] for n in SOIL_NAMES}
        return self.model.catalog_values(fitted, soil, self.geometry)

    def _rows(self, V: np.ndarray) -> np.ndarray:
        """Kernel rows ``(P * S, N_PARAMS)`` for candidate values ``V (P, D)`` and the distinct slips."""
        P, S = V.shape[0], len(self.sim_slip)
        col = self._col
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
        cat = self._catalog(V, lambda v: v[:, None])
        for column, value in self.model.kernel_columns(cat).items():
            rows[:, :, column] = value
        rows[:, :, K.P_OMEGA] = self.model.drive_speed(omega0, cat)
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
        geo, grid = self.geometry, self.grid
        leg = geo.lS - geo.MH * geo.g / V[:, self._col["kS"]]
        cat = self._catalog(V)
        rig = self.model.rigid(grid, leg, self.g_omega, cat)
        if rig is None:
            rig = rigid_batch(grid, leg, self.g_omega)
        x = np.concatenate([fine[:, self.g_sim_prev], rig, fine[:, self.g_sim], rig[:, :, : grid.n_margin]], axis=2)
        x += geo.g
        out = self.model.sense(x, cat, self)
        out[~ok] = np.nan
        return out, ok

    def mse(self, Z: np.ndarray, dt: float = DT_FINE) -> tuple[np.ndarray, np.ndarray]:
        """``(mse (P,), bias (P,))``: mean squared residual [(m/s^2)^2] after the best constant bias [m/s^2].

        The bias is the whole accelerometer bias: the prediction adds it to
        :meth:`predict` (which, for an effect with ``bias_inside``, already
        applied ``bias0`` before the effect and took it out again).
        """
        pred, ok = self.predict(Z, dt)
        r = self.g_mean[None] - pred  # (P, G, nb)
        w = self.g_n[None, :, None]
        if self.common:
            wave = self.common_waveform(pred)
            bias = np.mean(wave, axis=1)
            sse = np.sum(w * (r - wave[:, None, :]) ** 2, axis=(1, 2)) + self.within
        else:
            bias = np.sum(w * r, axis=(1, 2)) / (self.grid.nb * self.g_n.sum())
            sse = np.sum(w * (r - bias[:, None, None]) ** 2, axis=(1, 2)) + self.within
        mse = sse / self.n_values
        mse = np.where(ok & np.isfinite(mse), mse, np.inf)
        return mse, bias

    def common_waveform(self, pred: np.ndarray) -> np.ndarray:
        """The waveform ``(P, nb)`` [m/s^2] common to every cycle that best explains what the predictions
        ``pred (P, G, nb)`` leave of the logged bin means: their residuals' mean over the cycles (bias
        included)."""
        w = self.g_n[None, :, None]
        return np.sum(w * (self.g_mean[None] - pred), axis=1) / self.g_n.sum()

    # --- the effect's prediction context (slipest.model.effects.base.PredictionContext) -----------------
    def speed_groups(self, previous: bool = False):
        """``(omega, mask (G,))`` per distinct leg speed of the groups; ``previous``: ``(omega, prev_omega, mask)``
        per distinct pair of the cycles' and their previous cycles' speeds."""
        if not previous:
            for om in np.unique(self.g_omega):
                yield om, self.g_omega == om
            return
        for om, pom in np.unique(np.stack([self.g_omega, self.g_prev_omega], axis=1), axis=0):
            yield om, pom, (self.g_omega == om) & (self.g_prev_omega == pom)

    def bin_average(self, x: np.ndarray, offset=None) -> np.ndarray:
        """:func:`bin_average_batch` on this evaluator's grid."""
        return bin_average_batch(self.grid, x, offset)

    def solve_amplitude(self, param: FitParam, m0: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Least-squares ``A (P,)`` of ``group means ~ b + m0 + A h`` (weights: cycles per group), in ``param``'s range.

        Recorded in :attr:`last_linear` under ``param.name``.
        """
        return self.solve_amplitudes((param,), m0, (h,))[0]

    def solve_amplitudes(self, params, m0: np.ndarray, hs) -> list[np.ndarray]:
        """Least-squares ``A_k (P,)`` of ``group means ~ b + m0 + sum_k A_k h_k`` (weights: cycles per group).

        ``params``: one :class:`FitParam` per column ``hs[k] (P, G, nb)``;
        each amplitude is clipped to its parameter's range (after the joint
        solve) and recorded in :attr:`last_linear` under its name. A column
        the data cannot tell from the others gets a minimum-norm share (a
        tiny ridge).
        """
        w = self.g_n[None, :, None]
        r = self.g_mean[None] - m0
        # normal equations of r ~ b + sum_k A_k h_k, weights n_g, summed over groups and bins
        cols = [np.ones_like(m0)] + list(hs)
        k = len(cols)
        M = np.empty((m0.shape[0], k, k))
        v = np.empty((m0.shape[0], k))
        for i in range(k):
            v[:, i] = np.sum(w * cols[i] * r, axis=(1, 2))
            for j in range(i, k):
                M[:, i, j] = M[:, j, i] = np.sum(w * cols[i] * cols[j], axis=(1, 2))
        diag = np.einsum("pii->pi", M)
        M = M + (1e-10 * diag.max(axis=1) + 1e-300)[:, None, None] * np.eye(k)
        coef = np.linalg.solve(M, v[..., None])[..., 0]
        out = []
        for i, param in enumerate(params):
            amp = np.clip(np.where(np.isfinite(coef[:, i + 1]), coef[:, i + 1], 0.0), param.lo, param.hi)
            self.last_linear[param.name] = amp
            out.append(amp)
        return out
