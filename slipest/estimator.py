"""The recursive slip and soil estimator (pure computation): one leg cycle's features at a time.

What is observable from what (this model, IMU noise 0.01 g at 1 kHz)
--------------------------------------------------------------------
* One cycle's features (:mod:`slipest.features`) depend on slip **and**
  soil. The break-away angle (``onset``) is the strongest carrier: it moves
  with slip, ``kS`` and ``phiS`` together; the oscillation frequency
  carries ``kS``; the amplitude and its growth over the stance carry
  ``dphi`` together with slip and ``kS``. With the soil known one cycle
  gives slip to about 0.015-0.02 (held-out RMSE); with the soil unknown
  about 0.06, because a different soil explains the same cycle with another
  slip.
* The soil is shared by the cycles driven on it while slip changes, so the
  soil becomes identifiable **jointly** from several cycles at different
  slips; slip per cycle then gets to about 0.03 after ~10 cycles. It does
  not reach the soil-known figure, and the reason is a ridge: ``onset``
  moves with slip, ``kS`` and ``phiS`` together, so a soil one grid step
  off along that ridge (0.025 rad in ``phiD``) explains the cycles with a
  slip about 0.03 off, and only the noisier amplitude and frequency
  features tell them apart. Measured on development draws: with the soil
  posterior after 25 cycles, slip on its most probable cell is 2-5 times
  worse than on the true soil, while the posterior mean of the soil is
  within one standard deviation of the truth. What helped (each measured
  on two development seeds): every whitened feature direction rather than
  the 8 strongest, a degree-14 surrogate (degree 8 leaves a lack of fit
  of about 0.25 noise standard deviations per feature, degree 12 about
  0.15), a slip tempering of 0.4, and, once the surrogate was that good,
  a finer ``dphi`` axis of the soil grid (31 levels, 0.0117 rad apart,
  instead of 11: slip 0.028 / 0.027 / 0.025 on seeds 11 / 7 / 3 became
  0.025 / 0.023 / 0.025; finer ``kS`` and ``phiD`` axes gained nothing,
  see :meth:`~slipest.inverse.surrogate.SoilGrid.default`). What did not:
  lighter soil tempering, a smaller hazard, a residual covariance that
  varies with slip and soil.
* Not observable: the soil, while the wheel does not stick-slip (slip near
  0 on a soil with ``phiS`` above about 0.5 rad: no break-away, ``Da`` about
  0.015 g, flat features). The surrogate's small errors there would still
  single out a soil, so a cycle with no break-away detected (``onset`` at
  the end of the window) does **not** update the soil: its posterior only
  widens with the change hazard, and ``dphi`` keeps a large standard
  deviation instead of a confident wrong number (tested). Its slip is
  estimated as usual (near 0). With slip held constant the soil and slip
  are confounded (a different soil explains the same cycles with another
  slip): the soil sharpens only when slip varies between cycles, and until
  then the standard deviations stay wide. ``phiD`` alone is weakly
  observable; it is reported through ``dphi`` and ``phiS``.

How (the recursion)
-------------------
The soil ``(kS, phiD, dphi)`` is a slowly varying state on a grid of cells
(:class:`slipest.inverse.surrogate.SoilGrid`, 3410 cells), filtered by a
point-mass (discrete) Bayes filter (the update of
:func:`filterpy.discrete_bayes.update`, written out and compiled with the
rest of the cycle: filterpy's own normalisation sums in Python and alone
cost 0.3 ms a cycle); slip is a new unknown every cycle, marginalised on a
grid of slip nodes. Per cycle (:func:`_cycle_step`, compiled, on the kernels of
:mod:`slipest.inverse.grid_kernels`: about 0.3 ms with its tables in the CPU
caches, 0.4-0.6 ms from memory, hence :meth:`SoilSlipEstimator.prefetch`):

1. *predict*: the soil may have changed: with probability ``hazard`` the
   soil is redrawn from the prior (mixing with it keeps every cell
   reachable, so after a change the filter re-acquires in a few cycles
   instead of staying confidently wrong); ``change_prob`` reports the
   posterior probability that the soil changed at this cycle (a Bayesian
   run-length-1 change detector on the innovation).
2. *slip*: ``p(slip | all cycles) ~ sum_cells w(cell) p(f | slip, cell)``
   with the measurement model ``f ~ N(mu(slip, soil), R / slip_temper)``
   (:class:`~slipest.inverse.surrogate.FeatureSurrogate`), on slip nodes
   0.02 apart (:data:`NODE_STRIDE`) over the cells that hold the mass; the
   estimate is its mean, the standard deviation its spread.
3. *soil update*: ``w(cell) *= p(f | cell)^soil_temper`` (slip
   marginalised), or ``p(f | slip_ref, cell)^soil_temper`` when a reference
   slip is given and ``use_reference`` is on (the thesis's way of learning
   the soil, but from every feature, not ``Da`` alone). The exponent
   ``soil_temper < 1`` accounts for the surrogate's error being the same on
   consecutive cycles of one soil (it is not independent noise); without it
   the soil posterior becomes overconfident (measured in development on
   training draws: 95 % intervals covering about 60 % of ``dphi``).
   Tempering alone still lets the evidence grow without bound, and the
   surrogate's error does not average out over cycles: at constant slip,
   100 cycles walked the soil along the ridge (``phiS`` and ``phiD`` both
   0.05 rad high, to the edge of the grid) and slip 0.066 high, with 95 %
   intervals covering 18 %. So the posterior is also *forgotten*: before
   each update the weights are raised to ``forget`` (0.9), which bounds the
   accumulated evidence at about ``1 / (1 - forget)`` = 10 cycles'
   worth. The same run then gives slip 0.056 high with intervals covering
   100 %, and the accuracy with slip varying is unchanged (development
   seeds 11/7/3, degree-12 surrogate: 0.029/0.028/0.027 from the 10th
   cycle with forgetting, 0.028/0.028/0.026 without). With the current
   surrogate and grid (31 ``dphi`` levels) that run (slip 0.3, 100
   cycles) gives slip 0.026 high with intervals covering 100 %, and 0.041
   high covering 42 % without forgetting.

Why not an EKF/UKF over the soil: ``mu`` is a rough, partly multimodal
function of the soil, and the soil is unknown over its whole range at the
start and after every change. An EKF over (kS, phiD, dphi) with the slip
marginalised the same way (tried on training draws) needed about 20 cycles
to get slip within 0.03 and its 95 % intervals covered 60-80 %; the grid
filter gets there in about 10 with calibrated intervals. ``Eq515Tracker`` (:mod:`slipest.inverse.eq515`), the
thesis's method, is a 1-state filterpy ``KalmanFilter`` on ``dphi``.

Units: slip [-], kS [N/m], phiS, phiD, dphi [rad]; every estimate comes
with its standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from slipest.features import FEATURE_NAMES, INDEX
from slipest.inverse.base import Soil
from slipest.inverse.grid_kernels import (
    grid_loglik,
    marginal_from_rows,
    node_moments,
    select_cells,
    touch,
    weighted_moments,
    whiten_into,
)
from slipest.inverse.surrogate import SLIP_NODES, FeatureSurrogate, SoilGrid, SurrogateInverse, load_inverse_model, slip_prior

#: The recursive estimator marginalises slip over every NODE_STRIDE-th slip node of ``SLIP_NODES``
#: (0.02 apart), for the soil update and the slip estimate alike: a Riemann sum of a Gaussian of
#: standard deviation sigma is exact to ~1 % down to a step of 2 sigma, and a cycle's slip
#: likelihood on one soil is about 0.015 wide (0.024 after the slip tempering). Adding the nodes
#: in between for the slip estimate (0.01 apart) changed slip RMSE by < 0.0003 on development
#: seeds 11 / 7 / 3 and cost up to 0.3 ms a cycle when the soil posterior is broad.
NODE_STRIDE = 2
#: Cells whose joint weight is below the best one's by more than this (log) are left out of the
#: slip estimate (each holds less than exp(-15) = 3e-7 of the best one's mass).
SLIP_CUTOFF = 15.0
_ONSET = INDEX["onset"]

#: Default probability per cycle that the soil changed [-].
DEFAULT_HAZARD = 0.01
#: Default tempering of a cycle's soil likelihood [-] (see module docstring).
DEFAULT_SOIL_TEMPER = 0.3
#: Default forgetting of the soil posterior per update [-] (1: none; see module docstring).
DEFAULT_FORGET = 0.9
#: Default tempering of a cycle's slip likelihood [-] (widens the slip posterior for the surrogate's error).
DEFAULT_SLIP_TEMPER = 0.4


@numba.njit(cache=True, fastmath=True)
def _cycle_step(w, prior, hazard, soil_temper, forget, cutoff, node_width, table, fw, lp, nodes, node_quant,
                ref_k, ref_a, skip, summary_x, summary_q, dmat, f32s, f64s, sel, ps, out):
    """One cycle of the grid filter, in place on the weights ``w`` (the soil posterior over the cells).

    predict (hazard mixing with the prior), cell likelihoods on the slip
    nodes ``nodes`` [-] (``table``: columnar ``(D, K, S)``; ``lp``: their
    log prior; ``node_width``: their spacing [-]), slip marginal on the same
    nodes over the cells that matter,
    run-length-1 change probability, tempered update (by the reference
    slip's likelihood when ``ref_k >= 0``: between nodes ``ref_k`` and
    ``ref_k + 1`` at fraction ``ref_a``; the prior weights raised to
    ``forget`` first), or no update when ``skip``; then the moments.

    Writes ``out``: slip [-], its std [-] (``node_quant``: variance added
    for the nodes' spacing), change probability [-], then mean and std of
    each row of ``summary_x`` under the weights (std with ``summary_q``
    added to the variance). Scratch: ``dmat`` ``(K, S)`` and ``f32s`` ``(3,
    S)`` float32, ``f64s`` ``(2, S)`` float64, ``sel`` ``(S,)`` int64, ``ps``
    ``(K,)`` float64.
    """
    S = w.size
    lc = f64s[0]  # cell log-likelihoods
    lw = f64s[1]  # log weights after predict, then the update's log-likelihoods
    grid_loglik(table, fw, lp, node_width, dmat, lc, f32s[:2])
    top = -np.inf
    for s in range(S):
        if lc[s] > top:
            top = lc[s]
    p_stay = 0.0
    p_new = 0.0
    for s in range(S):
        e = math.exp(lc[s] - top)
        p_stay += w[s] * e
        p_new += prior[s] * e
        v = (1.0 - hazard) * w[s] + hazard * prior[s]
        w[s] = v
        lw[s] = math.log(v) if v > 0.0 else -1e300
    p_stay *= 1.0 - hazard
    p_new *= hazard
    change = p_new / (p_stay + p_new) if (p_stay + p_new) > 0.0 else 1.0
    base = f32s[2]
    n = select_cells(lw, lc, cutoff, sel, base)
    ps[:] = 0.0
    marginal_from_rows(dmat, sel, base, n, ps)
    out[0], out[1] = node_moments(ps, nodes, node_quant)
    out[2] = change
    if not skip:
        ll = lw  # reused: the log weights are not needed any more
        if ref_k >= 0:
            l0 = lp[ref_k]
            l1 = lp[ref_k + 1]
            r0 = dmat[ref_k]
            r1 = dmat[ref_k + 1]
            for s in range(S):
                ll[s] = (1.0 - ref_a) * (r0[s] - l0) + ref_a * (r1[s] - l1)
        else:
            for s in range(S):
                ll[s] = lc[s]
        mx = -np.inf
        for s in range(S):
            if ll[s] > mx:
                mx = ll[s]
        top = -np.inf  # w^forget * L^temper, in logs (the weights span hundreds of decades)
        for s in range(S):
            v = forget * math.log(w[s]) + soil_temper * (ll[s] - mx) if w[s] > 0.0 else -np.inf
            ll[s] = v
            if v > top:
                top = v
        tot = 0.0
        for s in range(S):
            w[s] = math.exp(ll[s] - top)
            tot += w[s]
        for s in range(S):
            w[s] /= tot
    weighted_moments(w, summary_x, summary_q, out[3:])


@dataclass(frozen=True)
class CycleEstimate:
    """The estimator's output for one cycle (SI; ``*_std``: standard deviations).

    slip [-]; kS [N/m]; phiS, phiD, dphi [rad] (the soil posterior after
    this cycle); change_prob: posterior probability that the soil changed
    at this cycle [-]; used_reference: the reference slip updated the soil.
    """

    slip: float
    slip_std: float
    dphi: float
    dphi_std: float
    kS: float
    kS_std: float
    phiS: float
    phiS_std: float
    phiD: float
    phiD_std: float
    change_prob: float
    used_reference: bool

    @classmethod
    def nan(cls) -> "CycleEstimate":
        n = math.nan
        return cls(n, n, n, n, n, n, n, n, n, n, n, False)


#: Fields of :class:`CycleEstimate` that :meth:`SoilSlipEstimator.update_batch` returns as arrays.
BATCH_FIELDS = ("slip", "slip_std", "dphi", "dphi_std", "kS", "kS_std", "phiS", "phiS_std", "phiD", "phiD_std",
                "change_prob", "used_reference")


class SoilSlipEstimator:
    """Slip every cycle and the soil as it goes, from feature rows (see the module docstring).

    model: the feature surrogate (default: the shipped one).
    soil: what is known of the soil (:class:`~slipest.inverse.base.Soil`,
        any parts); complete: slip is inverted on that soil and it is not
        learnt; partial: the known parts restrict the prior.
    use_reference: learn the soil from the reference slips given to
        :meth:`update` (else they are ignored).
    hazard: probability per cycle that the soil changed [-].
    soil_temper, slip_temper: likelihood exponents (see module docstring).
    forget: exponent applied to the soil posterior before each update (1: no forgetting) [-].
    grid: the soil grid (default :meth:`SoilGrid.default`).
    n_legs: legs of the wheel-leg (sets the end of the window, ``pi/nL``,
    where ``onset`` lies when no break-away was detected).
    n_dims: whitened feature directions kept (default: all; see :class:`~slipest.inverse.surrogate.SurrogateInverse`).
    """

    def __init__(
        self,
        model: FeatureSurrogate | None = None,
        soil: Soil | None = None,
        use_reference: bool = False,
        hazard: float = DEFAULT_HAZARD,
        soil_temper: float = DEFAULT_SOIL_TEMPER,
        forget: float = DEFAULT_FORGET,
        slip_temper: float = DEFAULT_SLIP_TEMPER,
        grid: SoilGrid | None = None,
        n_legs: int = 4,
        n_dims: int | None = None,
    ):
        if not 0.0 <= hazard < 1.0:
            raise ValueError(f"hazard={hazard} must be in [0, 1)")
        if not (0.0 < soil_temper <= 1.0 and 0.0 < slip_temper <= 1.0 and 0.0 < forget <= 1.0):
            raise ValueError("soil_temper, slip_temper and forget must be in (0, 1]")
        self.model = model or load_inverse_model()
        self.inverse = SurrogateInverse(self.model, grid, n_dims=n_dims)
        self.grid = self.inverse.grid
        self.soil = soil
        self.use_reference = bool(use_reference)
        self.hazard = float(hazard)
        self.soil_temper = float(soil_temper)
        self.forget = float(forget)
        self.slip_temper = float(slip_temper)
        self._known = soil is not None and soil.complete
        self._cols = self.model.columns
        self._no_onset = math.pi / n_legs - 1e-9  # onset at or past this: no break-away detected
        self._scale = math.sqrt(self.slip_temper)
        if not self._known:
            table = self.inverse.table_t * np.float32(self._scale)  # (S, D, K)
            S, D, K = table.shape
            # the slip nodes (every NODE_STRIDE-th), as a columnar (D, K, S) table
            picked = np.arange(0, K, NODE_STRIDE)
            self._nodes = SLIP_NODES[picked]
            self._node_width = float(self._nodes[1] - self._nodes[0])
            self._table = np.ascontiguousarray(table[:, :, picked].transpose(1, 2, 0))  # (D, K, S)
            self._lp = np.ascontiguousarray(slip_prior(self._nodes).astype(np.float32))
            self._node_quant = self._node_width ** 2 / 12.0  # variance of a uniform within one node
            cells = self.grid.cells()
            prior = np.exp(self.inverse.soil_logprior(soil))
            self._prior = prior / prior.sum()
            q = self.grid.steps() ** 2 / 12.0  # variance of a uniform within one cell
            # dphi, kS, phiS, phiD of every cell, and the within-cell variance added to each
            self._summary_x = np.ascontiguousarray(np.column_stack([cells[:, 1] - cells[:, 2], cells[:, 0], cells[:, 1], cells[:, 2]]).T)
            self._summary_q = np.array([q[2], q[0], q[1] + q[2], q[1]])
            # scratch of the compiled step (no allocation per cycle)
            self._dmat = np.empty((self._nodes.size, S), dtype=np.float32)
            self._f32s = np.empty((3, S), dtype=np.float32)
            self._f64s = np.empty((2, S))
            self._sel = np.empty(S, dtype=np.int64)
            self._ps = np.empty(self._nodes.size)
            self._out = np.empty(3 + 2 * self._summary_x.shape[0])
            # the compiled whitening: modelled columns, log offsets, projection, scale; its output
            self._whiten_args = (np.ascontiguousarray(self._cols, dtype=np.int64), np.asarray(self.model.log_offset, dtype=float),
                                 np.ascontiguousarray(self.inverse.projection), np.float32(self._scale))
            self._fw = np.zeros(D, dtype=np.float32)
            whiten_into(np.zeros(len(FEATURE_NAMES)), *self._whiten_args, self._fw)
            # what a cycle step reads or writes, flat (prefetch)
            self._hot = [a.reshape(-1) for a in (self._table, self._dmat, self._f32s, self._f64s, self._prior,
                                                  self._summary_x, self._sel)]
            for a in self._hot:
                touch(a)
            # run the compiled kernels once now (loading them costs ~15 ms: not on the first cycle's latency)
            self._step(self._prior.copy(), np.zeros(D, np.float32), 0.0, -1, 0.0, False)
        self.reset()

    # ------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything learnt: the soil posterior goes back to the prior."""
        self.n_cycles = 0
        self.n_updates = 0
        self.n_reference = 0
        self.n_no_breakaway = 0
        if not self._known:
            self._w = self._prior.copy()

    @property
    def soil_weights(self) -> np.ndarray | None:
        """Posterior weights over the grid cells (``grid.cells()`` order); None with the soil known."""
        return None if self._known else self._w.copy()

    def prefetch(self) -> None:
        """Bring what the next cycle step reads (about 7 MB: the grid table, the weights, scratch) into the
        CPU caches. Call it shortly before a cycle closes (:class:`~slipest.online.SlipEstimator` does, one
        live sample at a time): the step then waits less on memory. Takes about 0.1-0.2 ms; changes nothing else."""
        if self._known:
            return
        touch(self._w)
        for a in self._hot:
            touch(a)

    def _step(self, w, fw, hazard: float, ref_k: int, ref_a: float, skip: bool) -> np.ndarray:
        """Run the compiled cycle step on the weights ``w`` (in place); returns the ``out`` row of :func:`_cycle_step`."""
        _cycle_step(w, self._prior, hazard, self.soil_temper, self.forget, SLIP_CUTOFF, self._node_width, self._table,
                    fw, self._lp, self._nodes, self._node_quant, ref_k, ref_a, skip, self._summary_x,
                    self._summary_q, self._dmat, self._f32s, self._f64s, self._sel, self._ps, self._out)
        return self._out

    def update(self, features, slip_ref: float | None = None) -> CycleEstimate:
        """One cycle: its full feature row (order of ``FEATURE_NAMES``) and, optionally, a reference slip [-].

        A row with non-finite modelled features raises ``ValueError``
        (the caller must not pass corrupted cycles; :mod:`slipest.online`
        flags them before).
        """
        f = np.asarray(features, dtype=float)
        if f.shape != (len(FEATURE_NAMES),):
            raise ValueError(f"a feature row has {len(FEATURE_NAMES)} values, got shape {f.shape}")
        if self._known:
            finite = np.all(np.isfinite(f[self._cols]))
        else:
            finite = whiten_into(f, *self._whiten_args, self._fw)  # the table coordinates, into self._fw
        if not finite:
            raise ValueError("non-finite features: this cycle cannot be estimated")
        use_ref = self.use_reference and slip_ref is not None and math.isfinite(slip_ref)
        self.n_cycles += 1
        if self._known:
            s = self.soil
            m, sd = self.inverse.slip_known_soil(f, s.kS, s.phiS, s.phiD)
            if self._scale != 1.0:
                sd = sd / self._scale
            return CycleEstimate(m, sd, s.dphi, 0.0, s.kS, 0.0, s.phiS, 0.0, s.phiD, 0.0, 0.0, False)
        if use_ref:
            nodes = self._nodes
            x = (min(max(slip_ref, nodes[0]), nodes[-1]) - nodes[0]) / (nodes[1] - nodes[0])
            ref_k = min(int(x), nodes.size - 2)
            ref_a = x - ref_k
        else:
            ref_k, ref_a = -1, 0.0
        skip = bool(f[_ONSET] >= self._no_onset)  # no break-away: no soil update (module docstring)
        slip, sd, change, dm, ds, km, ks, pm, pss, dm2, ds2 = self._step(self._w, self._fw, self.hazard, ref_k, ref_a,
                                                                          skip).tolist()
        used = use_ref and not skip
        if skip:
            self.n_no_breakaway += 1
        else:
            self.n_updates += 1
        if used:
            self.n_reference += 1
        return CycleEstimate(slip, sd, dm, ds, km, ks, pm, pss, dm2, ds2, change, used)

    def update_batch(self, features_2d, slip_ref=None) -> dict:
        """:meth:`update` over the rows of ``features_2d`` in order (the recursion is sequential).

        ``slip_ref``: None or one reference slip per row (NaN: none for that
        row). Rows with non-finite features give NaN outputs and leave the
        filter untouched. Returns ``{field: array}`` for :data:`BATCH_FIELDS`.
        """
        features_2d = np.atleast_2d(np.asarray(features_2d, dtype=float))
        n = features_2d.shape[0]
        refs = np.full(n, np.nan) if slip_ref is None else np.asarray(slip_ref, dtype=float).reshape(n)
        out = {k: np.full(n, np.nan) for k in BATCH_FIELDS}
        out["used_reference"] = np.zeros(n, dtype=bool)
        for j in range(n):
            row = features_2d[j]
            if not np.all(np.isfinite(row[self._cols])):
                continue
            est = self.update(row, None if math.isnan(refs[j]) else float(refs[j]))
            for k in BATCH_FIELDS:
                out[k][j] = getattr(est, k)
        return out
