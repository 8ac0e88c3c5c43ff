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
  not reach the soil-known figure: the surrogate's error is systematic for
  a given soil, so the soil estimate keeps a bias (kS within ~60 N/m,
  phiS within ~0.02 rad) that more cycles do not remove.
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
(:class:`slipest.inverse.surrogate.SoilGrid`, 2145 cells), filtered by a
point-mass (discrete) Bayes filter (the update of
:func:`filterpy.discrete_bayes.update`, written out and compiled with the
rest of the cycle: filterpy's own normalisation sums in Python and alone
cost 0.3 ms a cycle); slip is a new unknown every cycle, marginalised on a
grid of slip nodes. Per cycle (:func:`_cycle_step`, about 0.4-0.6 ms):

1. *predict*: the soil may have changed: with probability ``hazard`` the
   soil is redrawn from the prior (mixing with it keeps every cell
   reachable, so after a change the filter re-acquires in a few cycles
   instead of staying confidently wrong); ``change_prob`` reports the
   posterior probability that the soil changed at this cycle (a Bayesian
   run-length-1 change detector on the innovation).
2. *slip*: ``p(slip | all cycles) ~ sum_cells w(cell) p(f | slip, cell)``
   with the measurement model ``f ~ N(mu(slip, soil), R / slip_temper)``
   (:class:`~slipest.inverse.surrogate.FeatureSurrogate`); the estimate is
   its mean, the standard deviation its spread.
3. *soil update*: ``w(cell) *= p(f | cell)^soil_temper`` (slip
   marginalised), or ``p(f | slip_ref, cell)^soil_temper`` when a reference
   slip is given and ``use_reference`` is on (the thesis's way of learning
   the soil, but from every feature, not ``Da`` alone). The exponent
   ``soil_temper < 1`` accounts for the surrogate's error being the same on
   consecutive cycles of one soil (it is not independent noise); without it
   the soil posterior becomes overconfident (measured in development on
   training draws: 95 % intervals covering about 60 % of ``dphi``).

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
from slipest.inverse.surrogate import (
    SLIP_NODES,
    FeatureSurrogate,
    SoilGrid,
    SurrogateInverse,
    grid_loglik,
    load_inverse_model,
    moments,
    slip_marginal,
    slip_prior,
)

#: The soil update sums the slip likelihood over every SOIL_STRIDE-th slip node (0.03 apart: a
#: Riemann sum of a Gaussian of standard deviation sigma is exact to ~1 % down to a step of 2 sigma,
#: and a cycle's slip likelihood on one soil is about 0.015 wide); the slip estimate uses every
#: node (0.01 apart) on the cells that matter.
SOIL_STRIDE = 2
#: Cells whose joint weight is below the best one's by more than this (log) are left out of the
#: slip estimate (each holds less than exp(-15) = 3e-7 of the best one's mass).
SLIP_CUTOFF = 15.0
_ONSET = INDEX["onset"]

#: Default probability per cycle that the soil changed [-].
DEFAULT_HAZARD = 0.01
#: Default tempering of a cycle's soil likelihood [-] (see module docstring).
DEFAULT_SOIL_TEMPER = 0.3
#: Default tempering of a cycle's slip likelihood [-] (widens the slip posterior for the surrogate's error).
DEFAULT_SLIP_TEMPER = 0.6


@numba.njit(cache=True)
def _weighted_moments(w, xs):
    """Means and variances of the rows of ``xs`` under the weights ``w`` (summing to 1)."""
    n = xs.shape[0]
    m = np.zeros(n)
    v = np.zeros(n)
    for i in range(n):
        acc = 0.0
        for s in range(w.size):
            acc += w[s] * xs[i, s]
        m[i] = acc
        acc = 0.0
        for s in range(w.size):
            d = xs[i, s] - m[i]
            acc += w[s] * d * d
        v[i] = acc
    return m, v


@numba.njit(cache=True, fastmath=True)
def _cycle_step(w, prior, hazard, coarse, table, fw, lp_coarse, lp_slip, node_width, soil_temper, cutoff,
                ref_k, ref_a, skip, dmat, lc):
    """One cycle of the grid filter, in place on the weights ``w``; returns (slip weights, change_prob).

    predict (hazard mixing with the prior), cell likelihoods on the coarse
    slip nodes, slip marginal on every node, run-length-1 change
    probability, tempered update (by the reference slip's likelihood when
    ``ref_k >= 0``: between coarse nodes ``ref_k`` and ``ref_k + 1`` at
    fraction ``ref_a``), or no update when ``skip``.
    """
    S = w.size
    old = w.copy()
    for s in range(S):
        w[s] = (1.0 - hazard) * w[s] + hazard * prior[s]
    grid_loglik(coarse, fw, lp_coarse, dmat, lc, node_width)
    logw = np.empty(S)
    for s in range(S):
        logw[s] = math.log(w[s]) if w[s] > 0.0 else -np.inf
    ps = slip_marginal(logw, table, fw, lp_slip, lc, cutoff)
    top = -np.inf
    for s in range(S):
        if lc[s] > top:
            top = lc[s]
    p_stay = 0.0
    p_new = 0.0
    for s in range(S):
        e = math.exp(lc[s] - top)
        p_stay += old[s] * e
        p_new += prior[s] * e
    p_stay *= 1.0 - hazard
    p_new *= hazard
    change = p_new / (p_stay + p_new) if (p_stay + p_new) > 0.0 else 1.0
    if skip:
        return ps, change
    ll = np.empty(S)
    if ref_k >= 0:
        for s in range(S):
            ll[s] = (1.0 - ref_a) * (dmat[s, ref_k] - lp_coarse[ref_k]) + ref_a * (dmat[s, ref_k + 1] - lp_coarse[ref_k + 1])
    else:
        for s in range(S):
            ll[s] = lc[s]
    mx = -np.inf
    for s in range(S):
        if ll[s] > mx:
            mx = ll[s]
    tot = 0.0
    for s in range(S):
        w[s] *= math.exp(soil_temper * (ll[s] - mx))
        tot += w[s]
    for s in range(S):
        w[s] /= tot
    return ps, change


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
    grid: the soil grid (default :meth:`SoilGrid.default`).
    n_legs: legs of the wheel-leg (sets the end of the window, ``pi/nL``,
    where ``onset`` lies when no break-away was detected).
    n_dims: whitened feature directions kept (see :class:`~slipest.inverse.surrogate.SurrogateInverse`).
    """

    def __init__(
        self,
        model: FeatureSurrogate | None = None,
        soil: Soil | None = None,
        use_reference: bool = False,
        hazard: float = DEFAULT_HAZARD,
        soil_temper: float = DEFAULT_SOIL_TEMPER,
        slip_temper: float = DEFAULT_SLIP_TEMPER,
        grid: SoilGrid | None = None,
        n_legs: int = 4,
        n_dims: int = 8,
    ):
        if not 0.0 <= hazard < 1.0:
            raise ValueError(f"hazard={hazard} must be in [0, 1)")
        if not (0.0 < soil_temper <= 1.0 and 0.0 < slip_temper <= 1.0):
            raise ValueError("soil_temper and slip_temper must be in (0, 1]")
        self.model = model or load_inverse_model()
        self.inverse = SurrogateInverse(self.model, grid, n_dims=n_dims)
        self.grid = self.inverse.grid
        self.soil = soil
        self.use_reference = bool(use_reference)
        self.hazard = float(hazard)
        self.soil_temper = float(soil_temper)
        self.slip_temper = float(slip_temper)
        self._known = soil is not None and soil.complete
        self._cols = self.model.columns
        self._no_onset = math.pi / n_legs - 1e-9  # onset at or past this: no break-away detected
        self._scale = math.sqrt(self.slip_temper)
        if not self._known:
            self._table = np.ascontiguousarray(self.inverse.table_t * np.float32(self._scale))  # (S, D, K)
            self._coarse = np.ascontiguousarray(self._table[:, :, ::SOIL_STRIDE])
            self._coarse_nodes = SLIP_NODES[::SOIL_STRIDE]
            S, _, K = self._coarse.shape
            self._dmat = np.empty((S, K), dtype=np.float32)
            self._lc = np.empty(S)
            self._lp_slip = slip_prior(SLIP_NODES).astype(np.float32)
            self._lp_coarse = np.ascontiguousarray(self._lp_slip[::SOIL_STRIDE])
            cells = self.grid.cells()
            self._cells = cells
            self._dphi_cells = cells[:, 1] - cells[:, 2]
            prior = np.exp(self.inverse.soil_logprior(soil))
            self._prior = prior / prior.sum()
            self._quant = self.grid.steps() ** 2 / 12.0  # variance of a uniform within one cell
            # dphi, kS, phiS, phiD of every cell, and the within-cell variance added to each
            self._summary_x = np.ascontiguousarray(np.column_stack([self._dphi_cells, cells[:, 0], cells[:, 1], cells[:, 2]]).T)
            q = self._quant
            self._summary_q = np.array([q[2], q[0], q[1] + q[2], q[1]])
            # run the compiled kernels once now (loading them costs ~15 ms: not on the first cycle's latency)
            w0 = self._prior.copy()
            _cycle_step(w0, self._prior, 0.0, self._coarse, self._table, np.zeros(self._table.shape[1], np.float32),
                        self._lp_coarse, self._lp_slip, float(SOIL_STRIDE), self.soil_temper, SLIP_CUTOFF, -1, 0.0,
                        False, self._dmat, self._lc)
            _weighted_moments(w0, self._summary_x)
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

    def _soil_summary(self):
        m, v = _weighted_moments(self._w, self._summary_x)
        sd = np.sqrt(np.maximum(v, 0.0) + self._summary_q)
        return [m[0], sd[0], m[1], sd[1], m[2], sd[2], m[3], sd[3]]

    def update(self, features, slip_ref: float | None = None) -> CycleEstimate:
        """One cycle: its full feature row (order of ``FEATURE_NAMES``) and, optionally, a reference slip [-].

        A row with non-finite modelled features raises ``ValueError``
        (the caller must not pass corrupted cycles; :mod:`slipest.online`
        flags them before).
        """
        f = np.asarray(features, dtype=float)
        if f.shape != (len(FEATURE_NAMES),):
            raise ValueError(f"a feature row has {len(FEATURE_NAMES)} values, got shape {f.shape}")
        if not np.all(np.isfinite(f[self._cols])):
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
            nodes = self._coarse_nodes
            x = (min(max(slip_ref, nodes[0]), nodes[-1]) - nodes[0]) / (nodes[1] - nodes[0])
            ref_k = min(int(x), nodes.size - 2)
            ref_a = x - ref_k
        else:
            ref_k, ref_a = -1, 0.0
        skip = bool(f[_ONSET] >= self._no_onset)  # no break-away: no soil update (module docstring)
        fw = self.inverse.whiten(f) * np.float32(self._scale)
        ps, change = _cycle_step(self._w, self._prior, self.hazard, self._coarse, self._table, fw, self._lp_coarse,
                                 self._lp_slip, float(SOIL_STRIDE), self.soil_temper, SLIP_CUTOFF, ref_k, ref_a, skip,
                                 self._dmat, self._lc)
        slip, sd = moments(ps, SLIP_NODES)
        sd = math.sqrt(sd * sd + (SLIP_NODES[1] - SLIP_NODES[0]) ** 2 / 12.0)
        used = use_ref and not skip
        if skip:
            self.n_no_breakaway += 1
        else:
            self.n_updates += 1
        if used:
            self.n_reference += 1
        dm, ds, km, ks, pm, pss, dm2, ds2 = self._soil_summary()
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
