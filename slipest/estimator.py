"""The recursive slip and soil estimator of the default method (pure computation).

:class:`SoilSlipEstimator` takes one leg cycle's feature row at a time
(:mod:`slipest.features`) and returns slip with its standard deviation and
the soil ``(kS, phiS, phiD, dphi)`` learnt so far, with theirs
(:class:`~slipest.cycle_estimator.CycleEstimate`). The soil is a state on a
grid of cells (:class:`~slipest.inverse.surrogate.SoilGrid`) filtered by a
point-mass Bayes filter; slip is a new unknown every cycle, marginalised on
slip nodes; the measurement model is the feature surrogate
(:class:`~slipest.inverse.surrogate.FeatureSurrogate`). Per cycle:

1. predict: with probability ``hazard`` the soil changed (mixed with the
   prior); ``change_prob`` is the posterior probability that it did;
2. slip: posterior over slip nodes 0.02 apart, marginalised over the cells
   that hold the mass; likelihood ``N(f; mu(slip, soil), R / slip_temper)``;
   its mean (and the soil's reported) taken under the soil posterior raised
   to ``soil_sharpen`` once the recent slips have varied, its spread not
   narrowed;
3. soil update: the weights raised to ``forget``, times the cycle's soil
   likelihood (slip marginalised, or at the reference slip when one is given
   and ``use_reference`` is on) raised to ``soil_temper``, or, without a
   reference, to ``soil_temper * repeat_temper`` while the slip has not
   varied over the recent cycles (slip and soil are then confounded and the
   surrogate's error repeats, so repeated cycles add little new evidence); a
   cycle with no break-away detected
   (``onset`` at the end of the window) carries no soil information and does
   not update the soil.

Honesty when the model does not fit: a cycle's best candidate (smallest
squared whitened distance over cells and slip nodes) is compared with what
clean simulated cycles give. Above ``fit_level`` the cycle is not explained
(``misfit`` = the excess factor); the recent cycles' best distances, their
geometric mean over about ``1 / (1 - DISCREPANCY_MEMORY)`` cycles relative
to their typical clean value ``fit_typical``, give ``discrepancy``, a
persistent model error. The likelihood's variance is widened by the larger
of the two, so data the model does not explain get wide intervals.

Limits: the model's geometry and covered leg speeds (``model_legs``,
``omega_range``); slip 0-0.5 and the soil grid (:meth:`SoilGrid.default`). One cycle step takes about 0.7 ms
(compiled; :meth:`SoilSlipEstimator.prefetch` warms its 6 MB table first).
Why it is built this way, and what was tried: ``docs/estimator.md``.

Units: slip [-], kS [N/m], phiS, phiD, dphi [rad].
"""

from __future__ import annotations

import math

import numba
import numpy as np

from slipest.cycle_estimator import CycleEstimate, CycleEstimator
from slipest.features import FEATURE_NAMES, INDEX
from slipest.inverse.base import Soil
from slipest.inverse.feature_inverse import FeatureInverse
from slipest.inverse.grid import NOISE_STEP, SLIP_NODES, SoilGrid, grid_tables, slip_prior
from slipest.inverse.grid_kernels import (
    grid_loglik,
    marginal_from_rows,
    node_moments,
    select_cells,
    touch,
    weighted_moments,
    whiten_into,
)
from slipest.inverse.surrogate import FeatureSurrogate, load_inverse_model

#: Slip is marginalised on every NODE_STRIDE-th node of ``SLIP_NODES`` (0.02 apart), for the soil
#: update and the slip estimate alike (docs/estimator.md: why this spacing suffices).
NODE_STRIDE = 2
#: Cells whose joint log weight is below the best one's by more than this [nats] are left out of the
#: slip estimate (each holds less than exp(-15) = 3e-7 of the best one's mass).
SLIP_CUTOFF = 15.0
_ONSET = INDEX["onset"]
_OMEGA = INDEX["omega"]
_NOISE_SMOOTH = INDEX["noise_smooth"]

#: Default probability per cycle that the soil changed [-].
DEFAULT_HAZARD = 0.01
#: Default tempering of a cycle's soil likelihood [-] (docs/estimator.md).
DEFAULT_SOIL_TEMPER = 0.15
#: Default forgetting of the soil posterior per update [-] (1: none; see module docstring).
DEFAULT_FORGET = 0.9
#: Tempering of a cycle's slip likelihood [-] (widens the slip posterior for the surrogate's error), when the
#: model file does not say (:data:`MODEL_SETTINGS`; the 18-feature model's).
DEFAULT_SLIP_TEMPER = 0.4
#: Default exponent on the soil posterior where it weighs the cells for the slip estimate and the soil reported [-]
#: (the posterior kept stays tempered and forgotten; docs/estimator.md, "Sharpened for the estimate").
DEFAULT_SOIL_SHARPEN = 2.0
#: Squared whitened distance of a cycle's best candidate above which it is not explained by the model, when
#: the model file does not say (the 99th percentile of a chi-square with 14 degrees of freedom).
DEFAULT_FIT_LEVEL = 29.1
#: Typical (median) squared whitened distance of a clean cycle's best candidate, when the model file does not
#: say (the shipped model's, measured on held-out simulated cycles).
DEFAULT_FIT_TYPICAL = 5.4
#: Memory of the running discrepancy: weight of the previous cycles in its log average per cycle [-].
DISCREPANCY_MEMORY = 0.9
#: A cycle's best distance enters the running discrepancy as at least this fraction of ``fit_typical`` (one
#: cycle fitted unusually well does not hide a discrepancy of the next ones).
FIT_RATIO_MIN = 0.1
#: Squared whitened distance of a cycle's best candidate from which it is not estimated, where widening cannot
#: make an estimate honest. An effect's distance grows less with the number of features than the clean
#: cycles' percentile does, so the threshold keeps one distance: the 14-feature model's misfit 10, the
#: 18-feature one's 6.8, the 20-feature one's 5.6 (docs/estimator.md, "four smooth features").
GROSS_DISTANCE = 512.0
#: Misfit from which a cycle is not estimated, when the model file does not say (:data:`MODEL_SETTINGS`):
#: the 18-feature model's (:data:`GROSS_DISTANCE` over its ``fit_level`` 75.7).
DEFAULT_GROSS_MISFIT = 6.8
#: Settings a model file states for the estimator in its ``meta["estimator"]`` (they are tuned with the model:
#: ``tools/train_inverse.py`` writes them), used where the caller does not give them.
MODEL_SETTINGS = ("slip_temper", "gross_misfit")
#: Default share of ``soil_temper`` a cycle's soil update gets while the slip has not varied [-].
DEFAULT_REPEAT_TEMPER = 0.3
#: Spread (standard deviation) of the recent cycles' slips [-] from which they count as varied.
SLIP_SPREAD = 0.05
#: Memory of the recent slips' spread: weight of the previous cycles in its running moments per cycle [-].
SLIP_SPREAD_MEMORY = 0.8


@numba.njit(cache=True)
def slips_varied(moments):
    """How far the recent slips have varied, 0 (not at all, or none yet) to 1 (their spread has reached
    :data:`SLIP_SPREAD`): ``min(1, var / SLIP_SPREAD^2)`` of the running ``moments`` (see
    :func:`slip_spread_weight`) [-]."""
    if moments[0] <= 0.0:
        return 0.0
    var = max(moments[2] - moments[1] * moments[1], 0.0)
    return min(1.0, var / (SLIP_SPREAD * SLIP_SPREAD))


@numba.njit(cache=True)
def slip_spread_weight(moments, slip, repeat_temper):
    """The share of the soil tempering a cycle gets: ``repeat_temper`` while the recent slips have not varied,
    rising to 1 as their spread reaches :data:`SLIP_SPREAD`.

    ``moments``: ``(3,)``, the number of slips folded in (0: none yet), then
    the running mean of the recent slips and of their squares (weights
    ``SLIP_SPREAD_MEMORY**age``), updated in place with this cycle's
    ``slip`` [-] first. (No NaN sentinel: the kernel calling it is compiled
    with fastmath, which assumes no NaN.)
    """
    if moments[0] > 0.0:
        a = SLIP_SPREAD_MEMORY
        moments[1] = a * moments[1] + (1.0 - a) * slip
        moments[2] = a * moments[2] + (1.0 - a) * slip * slip
    else:
        moments[1] = slip
        moments[2] = slip * slip
    moments[0] += 1.0
    return repeat_temper + (1.0 - repeat_temper) * slips_varied(moments)


@numba.njit(cache=True, fastmath=True)
def _cycle_step(w, prior, hazard, soil_temper, repeat_temper, moments, forget, cutoff, sharpen, node_width, scale,
                fit_level, floor, gross, table, tstep, fw, lp, nodes, node_quant, ref_k, ref_a, skip, summary_x,
                summary_q, dmat, f32s, f64s, sel, ps, out):
    """One cycle of the grid filter, in place on the weights ``w`` (the soil posterior over the cells).

    predict (hazard mixing with the prior), cell likelihoods on the slip
    nodes ``nodes`` [-] (``table``, ``tstep``: columnar ``(D, K, S)`` counts and their step,
    :class:`~slipest.inverse.grid.Table`; ``lp``: their
    log prior; ``node_width``: their spacing [-]; ``scale``: the slip
    tempering; ``fit_level``, ``floor``: the misfit level and the widening
    floor of :func:`grid_loglik`), slip
    marginal on the same nodes over the cells that matter (its mean under
    their weights raised to ``1 + (sharpen - 1) v``, ``v`` =
    :func:`slips_varied` of ``moments`` before this cycle; its spread not
    narrowed), run-length-1
    change probability, tempered update (by the reference slip's likelihood
    when ``ref_k >= 0``: between nodes ``ref_k`` and ``ref_k + 1`` at
    fraction ``ref_a``; the prior weights raised to ``forget`` first; the
    likelihood raised to ``soil_temper``, times ``repeat_temper`` while the
    recent slips have not varied and no reference is given: see
    :func:`slip_spread_weight`, on the running moments ``moments``, updated
    in place with this cycle's slip),
    or no update when ``skip`` or when the cycle's misfit reaches ``gross``
    (the model does not explain it at all: neither the soil nor the slip
    moments learn from it); then the moments.

    Writes ``out``: slip [-], its std [-] (``node_quant``: variance added
    for the nodes' spacing), change probability [-], misfit [-] (1: the
    model explains the cycle), the best candidate's squared whitened
    distance [-], then mean and std of each row of
    ``summary_x`` under the updated weights (the means under the weights
    sharpened as for slip; std with ``summary_q`` added to the variance and
    widened by how far the mean moved). Scratch: ``dmat`` ``(K, S)`` and
    ``f32s`` ``(3, S)`` float32, ``f64s`` ``(2, S)`` float64, ``sel``
    ``(S,)`` int64, ``ps`` ``(K,)`` float64.
    """
    S = w.size
    lc = f64s[0]  # cell log-likelihoods, then the update's
    lw = f64s[1]  # log weights after predict
    best, misfit = grid_loglik(table, tstep, fw, lp, node_width, scale, fit_level, dmat, lc, f32s[:2], floor)
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
    sharpen = 1.0 + (sharpen - 1.0) * slips_varied(moments)  # none while slip and soil are confounded
    base = f32s[2]
    n = select_cells(lw, lc, cutoff, sel, base)
    ps[:] = 0.0
    marginal_from_rows(dmat, sel, base, n, ps)
    out[0], out[1] = node_moments(ps, nodes, node_quant)
    if sharpen != 1.0 and n > 0:  # the mean under the sharpened weights; the spread not narrowed (docstring)
        top = -np.inf
        for i in range(n):
            v = sharpen * lw[sel[i]] + lc[sel[i]]
            if v > top:
                top = v
        kept = 0  # the selected cells that still matter once sharpened (fewer: the mass gathers)
        for i in range(n):
            c = sel[i]
            if sharpen * lw[c] + lc[c] >= top - cutoff:
                sel[kept] = c
                base[kept] = np.float32(sharpen * lw[c] - top)
                kept += 1
        ps[:] = 0.0
        marginal_from_rows(dmat, sel, base, kept, ps)
        m, _ = node_moments(ps, nodes, node_quant)
        out[1] = math.sqrt(out[1] * out[1] + (out[0] - m) ** 2)
        out[0] = m
    out[2] = change
    out[3] = misfit
    out[4] = best
    temper = 0.0
    if misfit >= gross:
        skip = True
    else:
        temper = soil_temper * slip_spread_weight(moments, out[0], repeat_temper)
        if ref_k >= 0:  # the slip is given: nothing for repeated slips to confound
            temper = soil_temper
    if not skip:
        ll = lc  # the update's log-likelihoods (the cell log-likelihoods are not needed any more)
        if ref_k >= 0:
            l0 = lp[ref_k]
            l1 = lp[ref_k + 1]
            r0 = dmat[ref_k]
            r1 = dmat[ref_k + 1]
            for s in range(S):
                ll[s] = (1.0 - ref_a) * (r0[s] - l0) + ref_a * (r1[s] - l1)
        mx = -np.inf
        for s in range(S):
            if ll[s] > mx:
                mx = ll[s]
        top = -np.inf  # w^forget * L^temper, in logs (the weights span hundreds of decades)
        for s in range(S):  # lw[s] = log(w[s]) when w[s] > 0 (the predict step's)
            v = forget * lw[s] + temper * (ll[s] - mx) if w[s] > 0.0 else -np.inf
            ll[s] = v
            if v > top:
                top = v
        tot = 0.0
        for s in range(S):
            w[s] = math.exp(ll[s] - top)
            tot += w[s]
        for s in range(S):
            w[s] /= tot
    weighted_moments(w, summary_x, summary_q, out[5:])
    if sharpen != 1.0:  # the means under the weights raised to sharpen (lw is free now); the spreads not narrowed
        ws = f64s[1]
        tot = 0.0
        if sharpen == 2.0:  # the default: a product, not a power (about 100 us less a cycle)
            for s in range(S):
                ws[s] = w[s] * w[s]
                tot += ws[s]
        else:
            for s in range(S):
                ws[s] = w[s] ** sharpen  # w sums to 1: its largest is >= 1/S, no underflow of the sum
                tot += ws[s]
        for s in range(S):
            ws[s] /= tot
        sharp = np.empty(2 * summary_x.shape[0])
        weighted_moments(ws, summary_x, summary_q, sharp)
        for i in range(summary_x.shape[0]):
            d = out[5 + 2 * i] - sharp[2 * i]
            out[5 + 2 * i + 1] = math.sqrt(out[5 + 2 * i + 1] ** 2 + d * d)
            out[5 + 2 * i] = sharp[2 * i]


#: Fields of :class:`CycleEstimate` that :meth:`SoilSlipEstimator.update_batch` returns as arrays.
BATCH_FIELDS = ("slip", "slip_std", "dphi", "dphi_std", "kS", "kS_std", "phiS", "phiS_std", "phiD", "phiD_std",
                "change_prob", "used_reference", "misfit", "discrepancy")


class SoilSlipEstimator(CycleEstimator):
    """Slip every cycle and the soil as it goes, from feature rows (see the module docstring).

    model: the feature surrogate (default: the shipped one); the standard
        deviations reported are multiplied by its ``interval_scale`` (1 but
        for a calibrated rover model).
    soil: what is known of the soil (:class:`~slipest.inverse.base.Soil`,
        any parts); complete: slip is inverted on that soil and it is not
        learnt, with the cycle's misfit tests (``fit_level``, the running
        discrepancy, ``gross_misfit``) on that soil; partial: the known parts
        restrict the prior. ValueError when a part lies outside ``grid``.
    use_reference: learn the soil from the reference slips given to
        :meth:`update` (else they are ignored).
    hazard: probability per cycle that the soil changed [-].
    soil_temper, slip_temper: likelihood exponents (docs/estimator.md).
    forget: exponent applied to the soil posterior before each update (1: no forgetting) [-].
    soil_sharpen: exponent on the soil posterior (>= 1) where it weighs the
        cells for the means of the slip estimate and of the soil reported,
        once the recent slips have varied (:func:`slips_varied`; none at a
        constant slip); the standard deviations are not narrowed, and the
        posterior carried to the next cycle is not sharpened (1: none) [-].
    grid: the soil grid (default :meth:`SoilGrid.default`).
    n_legs: legs of the wheel-leg (sets the end of the window, ``pi/nL``,
        where ``onset`` lies when no break-away was detected).
    fit_level: squared whitened distance of the best candidate above which a
        cycle counts as not explained by the model and its likelihood is
        widened by the excess (``misfit``; default: the model's, measured on
        clean simulated cycles; inf: never).
    fit_typical: the best candidate's typical squared whitened distance on
        clean cycles, the reference of ``discrepancy`` (default: the
        model's median on clean simulated cycles; inf: never widen for a
        persistent discrepancy).
    repeat_temper: share of ``soil_temper`` a cycle's soil update gets while
        the recent cycles' slips have not varied (1: as any cycle; not applied
        to updates by a reference slip) [-].
    gross_misfit: misfit from which a cycle is not estimated: its estimate
        has every value NaN but ``misfit`` and ``discrepancy``, and it
        updates nothing but the running discrepancy (inf: never) [-].

    ``slip_temper`` and ``gross_misfit`` default (None) to the model file's
    ``meta["estimator"]`` (:data:`MODEL_SETTINGS`), else to
    :data:`DEFAULT_SLIP_TEMPER` and :data:`DEFAULT_GROSS_MISFIT`.
    """

    def __init__(
        self,
        model: FeatureSurrogate | None = None,
        soil: Soil | None = None,
        use_reference: bool = False,
        hazard: float = DEFAULT_HAZARD,
        soil_temper: float = DEFAULT_SOIL_TEMPER,
        forget: float = DEFAULT_FORGET,
        slip_temper: float | None = None,
        grid: SoilGrid | None = None,
        n_legs: int = 4,
        fit_level: float | None = None,
        fit_typical: float | None = None,
        repeat_temper: float = DEFAULT_REPEAT_TEMPER,
        gross_misfit: float | None = None,
        soil_sharpen: float = DEFAULT_SOIL_SHARPEN,
    ):
        self.model = model or load_inverse_model()
        stated = self.model.meta.get("estimator", {})
        unknown = sorted(set(stated) - set(MODEL_SETTINGS))
        if unknown:  # a setting the model was tuned with that this estimator would silently not apply
            raise ValueError(f"the inverse model's meta['estimator'] states {unknown}, which this slipest does not "
                             f"know (it knows {list(MODEL_SETTINGS)})")
        slip_temper = float(stated.get("slip_temper", DEFAULT_SLIP_TEMPER) if slip_temper is None else slip_temper)
        gross_misfit = float(stated.get("gross_misfit", DEFAULT_GROSS_MISFIT) if gross_misfit is None else gross_misfit)
        if not 0.0 <= hazard < 1.0:
            raise ValueError(f"hazard={hazard} must be in [0, 1)")
        if not (0.0 < soil_temper <= 1.0 and 0.0 < slip_temper <= 1.0 and 0.0 < forget <= 1.0
                and 0.0 < repeat_temper <= 1.0):
            raise ValueError("soil_temper, slip_temper, forget and repeat_temper must be in (0, 1]")
        self.model_legs = self.model.n_legs
        self.interval_scale = float(self.model.interval_scale)
        self.omega_range = self.model.covered_range("omega")
        self.inverse = FeatureInverse(self.model, grid)
        self.grid = self.inverse.grid
        self.soil = soil
        self.use_reference = bool(use_reference)
        self.hazard = float(hazard)
        self.soil_temper = float(soil_temper)
        self.forget = float(forget)
        self.slip_temper = float(slip_temper)
        if not 1.0 <= soil_sharpen <= 10.0:
            raise ValueError(f"soil_sharpen={soil_sharpen} must be in [1, 10]")
        self.soil_sharpen = float(soil_sharpen)
        level = self.model.meta.get("fit_level", DEFAULT_FIT_LEVEL) if fit_level is None else fit_level
        self.fit_level = float(level)
        if fit_typical is None:
            fit_typical = self.model.meta.get("fit_level_quantiles", {}).get("q50", DEFAULT_FIT_TYPICAL)
        if not fit_typical > 0:
            raise ValueError(f"fit_typical={fit_typical} must be > 0")
        self.fit_typical = float(fit_typical)
        self.repeat_temper = float(repeat_temper)
        if not gross_misfit > 1.0:
            raise ValueError(f"gross_misfit={gross_misfit} must be > 1")
        self.gross_misfit = float(gross_misfit)
        if soil is not None:
            what = self.grid.outside(soil.kS, soil.phiS, soil.phiD, soil.dphi)
            if what is not None:  # the surrogate would extrapolate, or the prior pin the soil to the edge
                raise ValueError(f"the known soil {what} lies outside the soils the model covers")
        self._known = soil is not None and soil.complete
        self._cols = np.ascontiguousarray(self.model.columns, dtype=np.int64)
        self._no_onset = math.pi / n_legs - 1e-9  # onset at or past this: no break-away detected
        if not self._known:
            self._nodes = SLIP_NODES[::NODE_STRIDE]
            self._node_width = float(self._nodes[1] - self._nodes[0])
            self.tables = grid_tables(self.model, self.grid, self._nodes)
            self._lp = np.ascontiguousarray(slip_prior(self._nodes).astype(np.float32))
            self._node_quant = self._node_width ** 2 / 12.0  # variance of a uniform within one node
            cells = self.grid.cells()
            prior = np.exp(self.inverse.soil_logprior(soil))
            self._prior = prior / prior.sum()
            S = cells.shape[0]
            q = self.grid.steps() ** 2 / 12.0  # variance of a uniform within one cell
            # dphi, kS, phiS, phiD of every cell, and the within-cell variance added to each
            self._summary_x = np.ascontiguousarray(np.column_stack([cells[:, 1] - cells[:, 2], cells[:, 0], cells[:, 1],
                                                                    cells[:, 2]]).T)
            self._summary_q = np.array([q[2], q[0], q[1], q[1] + q[2]])
            # scratch of the compiled step (no allocation per cycle)
            self._dmat = np.empty((self._nodes.size, S), dtype=np.float32)
            self._f32s = np.empty((3, S), dtype=np.float32)
            self._f64s = np.empty((2, S))
            self._sel = np.empty(S, dtype=np.int64)
            self._ps = np.empty(self._nodes.size)
            self._out = np.empty(5 + 2 * self._summary_x.shape[0])
            # build the table of the middle of the covered speeds and run the compiled kernels once now
            # (not on the first cycle's latency)
            table = self.tables.get(self.model.omega, 0.002)
            self._fw = np.zeros(table.columnar.shape[0], dtype=np.float32)
            self._table = table
            self._step(self._prior.copy(), np.zeros(3), 0.0, -1, 0.0, False, 1.0)
        self.reset()

    # ------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything learnt: the soil posterior goes back to the prior."""
        self.n_cycles = 0
        self.n_updates = 0
        self.n_reference = 0
        self.n_no_breakaway = 0
        self.n_misfit = 0
        self.n_gross = 0
        self._log_fit = 0.0  # running log average of best / fit_typical (0: as on clean cycles)
        self._moments = np.zeros(3)  # running moments of the recent slips (slip_spread_weight)
        if not self._known:
            self._w = self._prior.copy()

    @property
    def soil_weights(self) -> np.ndarray | None:
        """Posterior weights over the grid cells (``grid.cells()`` order); None with the soil known."""
        return None if self._known else self._w.copy()

    def prefetch(self, omega: float | None = None, noise_smooth: float | None = None) -> None:
        """Get ready for the next cycle: build its table if its leg speed [rad/s] and smoothed noise [g] (when
        both are known: finite, the speed > 0) fall in a new bin (about 40 ms a table), and those of a noise one bin
        higher and lower, then bring what the cycle step reads (the table, the weights,
        scratch: about 7 MB) into the CPU caches. Call it before a cycle closes
        (:class:`~slipest.online.SlipEstimator` does): the step then waits less on memory. Changes nothing else."""
        if self._known:
            return
        if (omega is not None and noise_smooth is not None and math.isfinite(omega) and omega > 0
                and math.isfinite(noise_smooth) and noise_smooth >= 0):
            self._table = self.tables.get(omega, noise_smooth)
            # the smoothed noise moves by up to 5 % from one cycle to the next (its estimate, and how many samples
            # the smoothing averages at each speed): the bins of a noise one bin higher and lower are built now
            # too, not on the closing sample
            for factor in (1.0 / (1.0 + NOISE_STEP), 1.0 + NOISE_STEP):
                self.tables.get(omega, noise_smooth * factor)
        for a in (self._table.columnar, self._w, self._dmat, self._f32s, self._f64s, self._prior, self._summary_x,
                  self._sel):
            touch(a.reshape(-1))

    def _step(self, w, moments, hazard: float, ref_k: int, ref_a: float, skip: bool, floor: float) -> np.ndarray:
        """Run the compiled cycle step on the weights ``w`` and the slip moments (in place) with the current table
        and ``self._fw``; returns the ``out`` row of :func:`_cycle_step`."""
        _cycle_step(w, self._prior, hazard, self.soil_temper, self.repeat_temper, moments, self.forget, SLIP_CUTOFF,
                    self.soil_sharpen, self._node_width, self.slip_temper, self.fit_level, floor, self.gross_misfit,
                    self._table.columnar, self._table.step, self._fw, self._lp, self._nodes, self._node_quant, ref_k,
                    ref_a, skip, self._summary_x, self._summary_q, self._dmat, self._f32s, self._f64s, self._sel,
                    self._ps, self._out)
        return self._out

    @property
    def discrepancy(self) -> float:
        """The persistent discrepancy the next cycle's likelihood is widened by [-]: the geometric mean of the
        recent cycles' best squared whitened distances over ``fit_typical`` (weights ``DISCREPANCY_MEMORY**age``,
        starting from the clean value), at least 1; 1 with ``fit_typical`` inf."""
        return math.exp(self._log_fit) if self._log_fit > 0.0 else 1.0

    def _learn_fit(self, best: float) -> None:
        """The running discrepancy (module docstring) learns a cycle's best squared whitened distance."""
        if math.isfinite(self.fit_typical) and best >= 0.0:
            x = math.log(max(best / self.fit_typical, FIT_RATIO_MIN))
            self._log_fit = DISCREPANCY_MEMORY * self._log_fit + (1.0 - DISCREPANCY_MEMORY) * x

    def update(self, features, slip_ref: float | None = None, widen: float = 1.0) -> CycleEstimate:
        """One cycle: its full feature row (order of ``FEATURE_NAMES``; its ``omega`` and ``noise_smooth``
        say what the cycle was measured at) and, optionally, a reference slip [-]. The likelihood is
        widened by the larger of the running ``discrepancy`` and ``widen`` (>= 1; the caller's reason,
        :class:`slipest.cycle_estimator.CycleEstimator`); ``discrepancy`` in the estimate is that factor.

        A row with non-finite modelled features raises ``ValueError``
        (the caller must not pass corrupted cycles; :mod:`slipest.online`
        flags them before). A cycle whose misfit reaches ``gross_misfit`` gives
        an estimate whose values are all NaN but ``misfit`` and ``discrepancy``.
        """
        f = np.asarray(features, dtype=float)
        if f.shape != (len(FEATURE_NAMES),):
            raise ValueError(f"a feature row has {len(FEATURE_NAMES)} values, got shape {f.shape}")
        omega, sig = float(f[_OMEGA]), float(f[_NOISE_SMOOTH])
        if not (math.isfinite(omega) and omega > 0 and math.isfinite(sig) and sig >= 0):
            raise ValueError("the feature row's omega and noise_smooth must be finite (omega > 0)")
        if self._known:
            finite = bool(np.all(np.isfinite(f[self._cols])))
        else:
            self._table = self.tables.get(omega, sig)
            finite = whiten_into(f, self._cols, self._table.whitener, self._fw)  # the table coordinates
        if not finite:
            raise ValueError("non-finite features: this cycle cannot be estimated")
        use_ref = self.use_reference and slip_ref is not None and math.isfinite(slip_ref)
        self.n_cycles += 1
        floor = max(self.discrepancy, float(widen))
        if self._known:  # slip on the soil given, with the same misfit tests as the grid's
            s = self.soil
            m, sd, best, misfit = self.inverse.known_soil_posterior(f, s.kS, s.phiS, s.phiD, self.slip_temper,
                                                                    self.fit_level, floor)
            self._learn_fit(best)
            if misfit >= self.gross_misfit:
                self.n_misfit += 1
                self.n_gross += 1
                n = math.nan
                return CycleEstimate(n, n, n, n, n, n, n, n, n, n, n, False, misfit, floor)
            self.n_misfit += misfit > 1.0
            return CycleEstimate(m, sd, s.dphi, 0.0, s.kS, 0.0, s.phiS, 0.0, s.phiD, 0.0, 0.0, False, misfit, floor)
        if use_ref:
            nodes = self._nodes
            x = (min(max(slip_ref, nodes[0]), nodes[-1]) - nodes[0]) / (nodes[1] - nodes[0])
            ref_k = min(int(x), nodes.size - 2)
            ref_a = x - ref_k
        else:
            ref_k, ref_a = -1, 0.0
        skip = bool(f[_ONSET] >= self._no_onset)  # no break-away: no soil update (module docstring)
        slip, sd, change, misfit, best, dm, ds, km, ks, pm, pss, dm2, ds2 = self._step(
            self._w, self._moments, self.hazard, ref_k, ref_a, skip, floor).tolist()
        self._learn_fit(best)
        if misfit >= self.gross_misfit:  # not explained at all: no estimate (the step learnt nothing from it)
            self.n_misfit += 1
            self.n_gross += 1
            n = math.nan
            return CycleEstimate(n, n, n, n, n, n, n, n, n, n, n, False, misfit, floor)
        used = use_ref and not skip
        if skip:
            self.n_no_breakaway += 1
        else:
            self.n_updates += 1
        if used:
            self.n_reference += 1
        if misfit > 1.0:
            self.n_misfit += 1
        k = self.interval_scale  # the model's (a calibrated rover's held-out check)
        return CycleEstimate(slip, sd * k, dm, ds * k, km, ks * k, pm, pss * k, dm2, ds2 * k, change, used, misfit,
                             floor)

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
