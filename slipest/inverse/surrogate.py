"""The feature surrogate: the measurement model of the multi-feature inverse (pure computation + its file).

Fitted offline on simulated cycles over the estimator's envelope
(:mod:`slipest.inverse.simdata`, ``tools/train_inverse.py``), it gives the
distribution of one cycle's modelled features (:data:`MODEL_FEATURES`, from
:mod:`slipest.features`) given the slip, the soil, the leg speed and the
IMU's smoothed noise level::

    f ~ N(mu(slip, kS, phiS, dphi, noise_smooth; omega), R(noise_smooth; omega))

The leg speed changes the stick-slip waveform in ways one polynomial over all
speeds follows poorly, so the model is a set of **speed nodes** ``omega_i``
(geometric spacing): at each, ``mu_i`` is a polynomial per feature in the
normalised ``(slip, kS, phiS, dphi, noise_smooth)`` in the tensor Legendre
basis, total degree :func:`node_terms` (high in the soil and slip, low in
the noise), one polynomial per **slip patch** (``patches``: overlapping slip
ranges, blended smoothly across each overlap by :func:`patch_weights`; the
shipped model has one, docs/estimator.md says why), and ``R_i(s)`` the
covariance of the residuals, piecewise linear in ``s^2`` between **noise
knots** (``cov_knots``, :func:`cov_knot_weights`; each knot's matrix
positive definite, so ``R`` is everywhere; constant beyond the last knot,
the largest smoothed noise trained on; a file of format 4 or before holds
``R_i(s) = A_i + s^2 B_i``)
(what the IMU noise leaves on the features and what a smooth law cannot
follow: the oscillation's phase at the end of the stance jumps about with
small parameter changes, so amplitude features scatter by about 30 % around
any smooth law while the break-away angle is followed to a few percent).
Between nodes, ``mu`` and ``R`` are interpolated linearly in ``log omega``
(:meth:`FeatureSurrogate.node_weights`).

Units: slip [-], kS [N/m], phiS, phiD, dphi [rad], omega [rad/s],
noise_smooth [g]; features in :data:`slipest.features.FEATURE_UNITS`. The
model is valid over ``ranges`` with ``phiS - dphi >= phid_min`` and leg
speeds between the first and last node; ``covered`` says what the estimator
promises (the rest is a margin).

The shipped model is ``slipest/data/inverse_model.npz`` (versioned,
:data:`FORMAT_VERSION`), read by :func:`load_inverse_model`.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from slipest.features import FEATURE_NAMES

#: Version of the inverse model file format (5: the covariance on noise knots; 4: slip patches; 3, one patch, and
#: 4 are still read; 1 and 2 are refused).
FORMAT_VERSION = 5
#: Versions :meth:`FeatureSurrogate.load` reads.
READ_VERSIONS = (3, 4, 5)
#: Noise knots of a fitted covariance (:func:`default_cov_knots`) [-].
N_COV_KNOTS = 5
#: Variables of a node's polynomial, in order (the leg speed selects the nodes).
VARIABLES = ("slip", "kS", "phiS", "dphi", "noise_smooth")
#: The smooth moments of the window (spectral and energy-weighted), integrals where the crossing counts and the
#: energy quantiles step (docs/estimator.md, "four smooth features" and "two more smooth features").
MOMENT_FEATURES = ("spec_cent", "spec_bw", "e_cent", "e_spread", "spec_skew", "spec_cent2")
#: Features the shipped model uses: the smoothed, noise-referred ones (``delta_a``, the raw max - min, grows
#: with the IMU's noise and rate; ``n_crossings`` repeats ``zc_rate``; ``noise``, ``omega``, ``noise_smooth``
#: are inputs; ``stick_mean`` was too noisy to help), then :data:`MOMENT_FEATURES`.
MODEL_FEATURES = ("peak_pos", "peak_neg", "rms", "rms_q1", "rms_q2", "rms_q3", "rms_q4", "onset", "energy_q10",
                  "energy_q50", "energy_q90", "zc_rate", "osc_freq", "rice_freq") + MOMENT_FEATURES

#: Rows per block when building design matrices [-].
_CHUNK = 20000


class InverseModelError(ValueError):
    """The inverse model file is missing, of another format version, or malformed."""


def node_terms(schedule: dict) -> np.ndarray:
    """Tensor Legendre terms ``(T, 5)`` (degrees of the :data:`VARIABLES`) of a term schedule:
    ``{noise degree: total degree in (slip, kS, phiS, dphi)}``."""
    out = []
    for js, d in schedule.items():
        out += [e + (int(js),) for e in itertools.product(range(int(d) + 1), repeat=4) if sum(e) <= d]
    out.sort(key=lambda e: (sum(e), e[4], tuple(-v for v in e)))
    return np.array(out, dtype=np.int64)


def whitener(cov: np.ndarray) -> np.ndarray:
    """``W`` ``(d, d)`` with ``W W^T = cov^-1`` (lower triangular): ``(f - mu) @ W`` has identity covariance when
    ``f - mu`` has ``cov`` (``cov``: symmetric positive definite, e.g. :meth:`FeatureSurrogate.cov`)."""
    return np.linalg.cholesky(np.linalg.inv(cov))


def legendre_design(u: np.ndarray, terms: np.ndarray) -> np.ndarray:
    """Design matrix ``(n, T)`` of the tensor Legendre terms ``(T, V)`` at normalised points ``u`` ``(n, V)``."""
    b = np.polynomial.legendre.legvander(u, int(terms.max()))  # (n, V, degree + 1)
    out = b[:, 0, terms[:, 0]].copy()
    for v in range(1, u.shape[1]):
        out *= b[:, v, terms[:, v]]
    return out



def legendre_factors(terms4: np.ndarray, coef: np.ndarray, center4, halfwidth4,
                     levels) -> tuple[np.ndarray, np.ndarray]:
    """A tensor Legendre polynomial in (slip, kS, phiS, dphi) (terms ``(T, 4)``, coefficients ``(T, d)``,
    normalisation ``u = (x - center4) / halfwidth4``) on the tensor grid of ``levels`` = (slip nodes, kS,
    phiS, dphi levels), as two factors ``(partial, basis)``: ``partial`` ``(A, d, nk, nphiS, ndphi)``
    contracted in kS, phiS and dphi for each slip degree ``a``, and ``basis`` ``(K, A)`` the slip's Legendre
    basis at the nodes, so that the polynomial at node ``k`` is ``sum_a basis[k, a] * partial[a]``
    (:func:`contract_slip`; the estimator's tables contract it cell by cell as they quantise,
    :func:`slipest.inverse.grid.quantise_product`). Repeated terms add up.

    Contracted one variable at a time, each over the terms that exist only (a total-degree basis has a
    sixth of the dense tensor's terms): kS first, for each (slip, phiS, dphi) degree triple; then phiS, for
    each (slip, dphi) pair; then dphi, for each slip degree over the dphi degrees it has."""
    t = np.asarray(terms4, dtype=np.int64)
    coef = np.asarray(coef, dtype=float)
    deg = int(t.max())
    p, d = deg + 1, coef.shape[1]
    levels = [np.asarray(v, dtype=float) for v in levels]
    bases = [np.polynomial.legendre.legvander((lv - center4[j]) / halfwidth4[j], deg) for j, lv in enumerate(levels)]
    nk, nphi = levels[1].size, levels[2].size
    triples, of_term, pairs, of_triple, dphi_degrees = _degree_groups(t)
    # kS, per (slip, phiS, dphi) degree triple: (triples, kS degree, d) -> (triples, d, kS)
    c1 = np.zeros((len(triples), p, d))
    np.add.at(c1, (of_term, t[:, 1]), coef)
    x1 = np.matmul(c1.transpose(0, 2, 1), bases[1].T)
    # phiS, per (slip, dphi) pair: (pairs, phiS degree, d, kS) -> (pairs, d, kS, phiS)
    c2 = np.zeros((len(pairs), p, d, nk))
    c2[of_triple, triples[:, 1]] = x1  # each (pair, phiS degree) once: the triples are unique
    x2 = np.tensordot(c2, bases[2], axes=([1], [1]))
    # dphi, per slip degree over the dphi degrees it has: (A, d, kS, phiS, dphi)
    c3 = np.zeros((p, p) + x2.shape[1:])
    c3[pairs[:, 0], pairs[:, 1]] = x2
    partial = np.empty((p, d, nk, nphi, levels[3].size))
    for a in range(p):
        n = dphi_degrees[a]
        if n:
            partial[a] = np.tensordot(c3[a, :n], bases[3][:, :n], axes=([0], [1]))
        else:
            partial[a] = 0.0
    return partial, bases[0]


_DEGREE_GROUPS: dict = {}


def _degree_groups(terms4: np.ndarray) -> tuple:
    """The grouping of :func:`legendre_factors` for terms ``(T, 4)``: the unique (slip, phiS, dphi) degree
    triples and each term's, the unique (slip, dphi) pairs and each triple's, and for each slip degree the
    number of dphi degrees to sum (its largest plus one; 0 if absent). Cached per terms (a model has a few)."""
    key = (terms4.shape, terms4.tobytes())
    hit = _DEGREE_GROUPS.get(key)
    if hit is None:
        triples, of_term = np.unique(terms4[:, [0, 2, 3]], axis=0, return_inverse=True)
        pairs, of_triple = np.unique(triples[:, [0, 2]], axis=0, return_inverse=True)
        dphi_degrees = np.zeros(int(terms4.max()) + 1, dtype=np.int64)
        np.maximum.at(dphi_degrees, pairs[:, 0], pairs[:, 1] + 1)
        if len(_DEGREE_GROUPS) >= 16:
            _DEGREE_GROUPS.clear()
        hit = _DEGREE_GROUPS[key] = (triples, of_term.reshape(-1), pairs, of_triple.reshape(-1), dphi_degrees)
    return hit


def contract_slip(partial: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """The grid of the factors of :func:`legendre_factors` (``partial`` ``(A, d, nk, nphiS, ndphi)``, ``basis``
    ``(K, A)``): ``(nk, nphiS, ndphi, K, d)``, a transposed view of a contiguous ``(d, nk, nphiS, ndphi, K)``
    (callers gather cells from it: a copy would cost a third of a table build)."""
    return np.tensordot(partial, basis, axes=([0], [1])).transpose(1, 2, 3, 4, 0)


def legendre_on_grid(terms4: np.ndarray, coef: np.ndarray, center4, halfwidth4, levels) -> np.ndarray:
    """The polynomial of :func:`legendre_factors` on its grid, ``(nk, nphiS, ndphi, K, d)`` (a transposed view,
    :func:`contract_slip`)."""
    return contract_slip(*legendre_factors(terms4, coef, center4, halfwidth4, levels))


def check_patches(patches) -> np.ndarray:
    """``patches`` as a ``(P, 2)`` float array of slip ranges ``[lo, hi]`` [-], or ``ValueError``: each range
    non-empty, the ranges increasing, each overlapping the next (``lo[p + 1] < hi[p]``) and no overlap reaching
    into the next one (``hi[p] <= lo[p + 2]``), so that :func:`patch_weights` sum to one."""
    p = np.asarray(patches, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 1 or not np.all(np.isfinite(p)):
        raise ValueError(f"patches must be (P >= 1, 2) finite slip ranges, got {p.tolist()}")
    if not np.all(p[:, 1] > p[:, 0]):
        raise ValueError(f"each slip patch needs lo < hi, got {p.tolist()}")
    if not (np.all(np.diff(p[:, 0]) > 0) and np.all(p[1:, 0] < p[:-1, 1]) and np.all(p[:-2, 1] <= p[2:, 0])):
        raise ValueError(f"slip patches must increase, each overlapping the next and only it, got {p.tolist()}")
    return p


def one_patch(center, halfwidth) -> np.ndarray:
    """The slip patches of a model without any: one, over the normalisation's slip range ``center +- halfwidth``."""
    return check_patches([[center[0] - halfwidth[0], center[0] + halfwidth[0]]])


def patch_weights(slip, patches) -> np.ndarray:
    """Blending weights ``(n, P)`` of the slip patches (``(P, 2)``, :func:`check_patches`) at slips ``(n,)`` [-]:
    1 where only one patch covers the slip (below the first and above the last patch too), a smoothstep
    (``3t^2 - 2t^3``, continuous with its slope) across each overlap; they sum to 1."""
    s = np.asarray(slip, dtype=float).reshape(-1)
    p = np.asarray(patches, dtype=float)
    w = np.ones((s.size, p.shape[0]))
    for j in range(1, p.shape[0]):  # overlap of patches j - 1 and j: [lo_j, hi_(j-1)]
        t = np.clip((s - p[j, 0]) / (p[j - 1, 1] - p[j, 0]), 0.0, 1.0)
        up = t * t * (3.0 - 2.0 * t)
        w[:, j] *= up
        w[:, j - 1] *= 1.0 - up
    return w


def default_cov_knots(center, halfwidth, n: int = N_COV_KNOTS) -> np.ndarray:
    """``n`` noise knots [g] evenly spaced from 0 to the largest smoothed noise of the normalisation
    (``center[4] + halfwidth[4]``)."""
    return np.linspace(0.0, float(center[4] + halfwidth[4]), n)


def check_cov_knots(knots) -> np.ndarray:
    """The noise knots ``(K,)`` [g] as floats, checked: at least two, the first 0, strictly increasing, finite."""
    k = np.asarray(knots, dtype=float)
    if k.ndim != 1 or k.size < 2 or not np.all(np.isfinite(k)) or k[0] != 0.0 or not np.all(np.diff(k) > 0):
        raise ValueError(f"noise knots must be at least two finite values from 0, strictly increasing; "
                         f"got {k.tolist()}")
    return k


def cov_knot_weights(noise_smooth, knots) -> np.ndarray:
    """Weights ``(..., K)`` of the knots' matrices in the covariance at smoothed noise ``noise_smooth`` [g]: the
    hat functions of ``knots**2`` at ``noise_smooth**2`` (linear interpolation in ``s^2``; beyond the last knot,
    its matrix alone). They are >= 0 and sum to 1, so a covariance of positive definite knot matrices is."""
    s2 = np.minimum(np.asarray(noise_smooth, dtype=float) ** 2, knots[-1] ** 2)
    k2 = np.asarray(knots, dtype=float) ** 2
    j = np.clip(np.searchsorted(k2, s2, side="right") - 1, 0, k2.size - 2)
    a = (s2 - k2[j]) / (k2[j + 1] - k2[j])
    out = np.zeros(np.shape(s2) + (k2.size,))
    np.put_along_axis(out, j[..., None], (1.0 - a)[..., None], axis=-1)
    np.put_along_axis(out, (j + 1)[..., None], a[..., None], axis=-1)
    return out


def nearest_positive_definite(m, floor: float = 1e-6) -> np.ndarray:
    """The symmetric part of ``m`` made positive definite in the features' own scales: with ``D`` its diagonal
    (floored at ``floor`` times the largest), the eigenvalues of ``D^-1/2 m D^-1/2`` raised to at least ``floor``
    times the largest. Features in different units (variances from 1e-6 to 10) keep their small but real
    variances, which a floor on the eigenvalues of ``m`` itself would inflate."""
    m = 0.5 * (m + m.T)
    d = np.diag(m).copy()
    d = np.maximum(d, floor * max(float(d.max()), 1e-300))
    s = 1.0 / np.sqrt(d)
    ev, vec = np.linalg.eigh(m * s[:, None] * s[None, :])
    ev = np.maximum(ev, floor * max(float(ev.max()), 1e-300))
    return ((vec * ev) @ vec.T) / s[:, None] / s[None, :]


def patch_norm(center, halfwidth, patch) -> tuple[np.ndarray, np.ndarray]:
    """The normalisation of one slip patch ``[lo, hi]``: ``center``, ``halfwidth`` with the slip's replaced."""
    c = np.array(center, dtype=float)
    h = np.array(halfwidth, dtype=float)
    c[0], h[0] = 0.5 * (patch[0] + patch[1]), 0.5 * (patch[1] - patch[0])
    return c, h


def fit_node(x5, y, terms: np.ndarray, center, halfwidth, patches=None, knots=None,
             progress=None) -> tuple[np.ndarray, np.ndarray]:
    """One speed node's least-squares fit: ``(coef (P, T, d), cov_coef (K, d, d))`` from points ``x5`` ``(n, 5)``
    (order of :data:`VARIABLES`, SI) and modelled features ``y`` ``(n, d)`` (rows with non-finite values are
    dropped). Each slip patch (``patches`` ``(P, 2)``; default :func:`one_patch`) is fitted on the rows it
    weighs (:func:`patch_weights` > 0: within its range, and beyond it for the first and last); the residual
    covariance, of the blended mean, is one matrix per noise knot (``knots`` ``(K,)`` [g]; default
    :func:`default_cov_knots`): least squares of the residuals' outer products on :func:`cov_knot_weights`, kept
    where it is at least a quarter of the knot's kernel average (the outer products averaged with those
    weights, positive semi-definite by construction) in every direction, else that average (few rows near
    the knot); each then made positive definite (:func:`nearest_positive_definite`). Raises ``ValueError``
    when some knot has no rows near it."""
    x5 = np.asarray(x5, dtype=float)
    y = np.asarray(y, dtype=float)
    patches = one_patch(center, halfwidth) if patches is None else check_patches(patches)
    ok = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(x5), axis=1)
    x5, y = x5[ok], y[ok]
    weights = patch_weights(x5[:, 0], patches)
    coef = np.empty((patches.shape[0], len(terms), y.shape[1]))
    fitted = np.zeros_like(y)
    for j, patch in enumerate(patches):
        used = np.flatnonzero(weights[:, j] > 0)
        if used.size < 10 * len(terms):
            raise ValueError(f"too few training rows ({used.size}) for {len(terms)} terms in slip patch "
                             f"{patch.tolist()}")
        c, h = patch_norm(center, halfwidth, patch)
        u = (x5[used] - c) / h
        yp = y[used]
        # normal equations accumulated in blocks; the Legendre basis keeps them well conditioned, a tiny ridge
        # guards the rank
        a = np.zeros((len(terms), len(terms)))
        b = np.zeros((len(terms), y.shape[1]))
        for i in range(0, u.shape[0], _CHUNK):
            dm = legendre_design(u[i : i + _CHUNK], terms)
            a += dm.T @ dm
            b += dm.T @ yp[i : i + _CHUNK]
            if progress:
                progress(dm.shape[0])
        coef[j] = np.linalg.solve(a + 1e-8 * np.trace(a) / len(terms) * np.eye(len(terms)), b)
        for i in range(0, used.size, _CHUNK):
            rows = used[i : i + _CHUNK]
            fitted[rows] += weights[rows, j, None] * (legendre_design(u[i : i + _CHUNK], terms) @ coef[j])
    resid = y - fitted
    knots = default_cov_knots(center, halfwidth) if knots is None else check_cov_knots(knots)
    basis = cov_knot_weights(x5[:, 4], knots)
    outer = np.einsum("nb,ni,nj->bij", basis, resid, resid)
    gram = basis.T @ basis
    if np.linalg.matrix_rank(gram) < knots.size:
        raise ValueError(f"too few training rows near some noise knot of {knots.tolist()} to fit the covariance")
    fitted_cov = np.linalg.solve(gram, outer.reshape(knots.size, -1)).reshape(outer.shape)
    cov_coef = []
    for ls, avg in zip(fitted_cov, outer / basis.sum(axis=0)[:, None, None]):
        w = whitener(nearest_positive_definite(avg))  # ls >= avg / 4 in every direction: eig(W^T ls W) >= 1/4
        ok = np.linalg.eigvalsh(w.T @ (0.5 * (ls + ls.T)) @ w).min() >= 0.25
        cov_coef.append(nearest_positive_definite(ls if ok else avg))
    return coef, np.stack(cov_coef)


def _check_numbers(meta: dict) -> None:
    """The numbers the estimator reads from a model's ``meta`` (``fit_level``, ``fit_level_quantiles``, the
    settings in ``estimator``) are finite numbers, else :class:`InverseModelError` naming the one that is not."""
    found = [("meta['fit_level']", meta["fit_level"])] if "fit_level" in meta else []
    for section in ("fit_level_quantiles", "estimator"):
        part = meta.get(section, {})
        if not isinstance(part, dict):
            raise InverseModelError(f"inverse model meta[{section!r}] must be a mapping, got {part!r}")
        found += [(f"meta[{section!r}][{key!r}]", value) for key, value in part.items()]
    for where, value in found:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InverseModelError(f"inverse model {where} must be a finite number, got {value!r}")


@dataclass(frozen=True)
class FeatureSurrogate:
    """``mu`` and ``R`` of the module docstring.

    features: names of the modelled features (subset of ``FEATURE_NAMES``).
    node_omegas: ``(M,)`` leg speeds of the nodes [rad/s], increasing.
    center, halfwidth: ``(5,)`` normalisation ``u = (x - center) / halfwidth``
    of a node's variables (SI). ranges: ``(6, 2)`` [lo, hi] of the training
    draw (the :data:`VARIABLES`, then omega); phid_min [rad]: its smallest
    ``phiS - dphi``. terms: ``(T, 5)`` Legendre degrees per variable;
    coef: ``(M, P, T, d)``, one polynomial per node and slip patch, each
    patch normalising the slip over its own range (:func:`patch_norm`);
    cov_coef: ``(M, K, d, d)``, the covariance at each noise knot (feature
    units squared); with ``cov_knots`` None, ``(M, 2, d, d)``: ``A_i``,
    ``B_i`` of ``A_i + s^2 B_i`` (format 4 and before). covered: what the
    estimator promises, ``{name: [lo, hi]}`` for slip, kS, phiS, dphi,
    omega, and ``"phid_min"``. meta: provenance (free-form). patches:
    ``(P, 2)`` slip ranges of the patches (:func:`check_patches`); None: one,
    the normalisation's slip range. cov_knots: ``(K,)`` smoothed noises [g]
    of the covariance's knots (:func:`check_cov_knots`).
    """

    features: tuple
    node_omegas: np.ndarray
    center: np.ndarray
    halfwidth: np.ndarray
    ranges: np.ndarray
    phid_min: float
    terms: np.ndarray
    coef: np.ndarray
    cov_coef: np.ndarray
    covered: dict
    meta: dict
    patches: np.ndarray | None = None
    cov_knots: np.ndarray | None = None
    #: Factor on the standard deviations the estimator reports with this model (1: its own posterior's; a
    #: calibrated rover model's is learnt from held-out testbed logs, :class:`slipest.rover.RoverSurrogate`).
    interval_scale: ClassVar[float] = 1.0

    def __post_init__(self):
        try:
            patches = one_patch(self.center, self.halfwidth) if self.patches is None else check_patches(self.patches)
        except (ValueError, IndexError, TypeError) as exc:
            raise InverseModelError(f"inverse model slip patches: {exc}") from None
        object.__setattr__(self, "patches", patches)
        if self.cov_knots is not None:
            try:
                object.__setattr__(self, "cov_knots", check_cov_knots(self.cov_knots))
            except ValueError as exc:
                raise InverseModelError(f"inverse model covariance knots: {exc}") from None
        k = 2 if self.cov_knots is None else self.cov_knots.size
        d = len(self.features)
        m = self.node_omegas.size
        unknown = [f for f in self.features if f not in FEATURE_NAMES]
        if unknown:
            raise InverseModelError(f"inverse model uses unknown feature(s) {unknown}")
        if m < 1 or not np.all(np.diff(self.node_omegas) > 0) or not np.all(self.node_omegas > 0):
            raise InverseModelError("inverse model node_omegas must be positive and increasing")
        t = self.terms
        if t.ndim != 2 or t.shape[1] != len(VARIABLES) or (t < 0).any():
            raise InverseModelError(f"inverse model terms must be (T, {len(VARIABLES)}) degrees >= 0")
        shape_ok = (self.center.shape == self.halfwidth.shape == (len(VARIABLES),)
                    and self.ranges.shape == (len(VARIABLES) + 1, 2))
        if not shape_ok or not np.all(np.isfinite(self.center)) or not np.all(np.isfinite(self.halfwidth) & (self.halfwidth > 0)):
            raise InverseModelError(f"inverse model center and halfwidth must be {len(VARIABLES)} finite values "
                                    f"(halfwidth > 0), ranges {len(VARIABLES) + 1} pairs")
        p = patches.shape[0]
        if self.coef.shape != (m, p, self.terms.shape[0], d) or self.cov_coef.shape != (m, k, d, d):
            raise InverseModelError(
                f"inverse model shapes do not agree: {m} nodes, {p} slip patches, {self.terms.shape[0]} terms, "
                f"coef {self.coef.shape}, cov_coef {self.cov_coef.shape}, {d} features"
            )
        if not (np.all(np.isfinite(self.coef)) and np.all(np.isfinite(self.cov_coef))):
            raise InverseModelError("inverse model has non-finite coefficients")
        for name in self.covered:
            if name not in ("phid_min", "omega") and name not in VARIABLES:
                raise InverseModelError(f"inverse model 'covered' names an unknown variable {name!r}")
        _check_numbers(self.meta)

    # ------------------------------------------------------------------ what it is for
    @property
    def n_legs(self) -> int:
        """Legs of the wheel-leg the model was trained for [-]."""
        return int(self.meta.get("training", {}).get("n_legs", 4))

    def covered_range(self, name: str) -> tuple[float, float]:
        """``(lo, hi)`` of a variable the estimator promises (the training range when ``covered`` omits it)."""
        if name in self.covered:
            lo, hi = self.covered[name]
            return float(lo), float(hi)
        j = (VARIABLES + ("omega",)).index(name)
        return float(self.ranges[j, 0]), float(self.ranges[j, 1])

    @property
    def omega(self) -> float:
        """Middle of the covered leg-speed range [rad/s] (what a single-speed caller should drive at)."""
        lo, hi = self.covered_range("omega")
        return 0.5 * (lo + hi)

    @property
    def columns(self) -> np.ndarray:
        """Column of each modelled feature in a full feature row."""
        return np.array([FEATURE_NAMES.index(f) for f in self.features])

    def observe(self, rows) -> np.ndarray:
        """The modelled features ``(..., d)`` of full feature rows ``(..., len(FEATURE_NAMES))``."""
        return np.asarray(rows, dtype=float)[..., self.columns]

    def node_weights(self, omega: float) -> list[tuple[int, float]]:
        """``[(node, weight), ...]`` interpolating linearly in ``log omega`` between the two nodes around
        ``omega`` [rad/s] (one node, weight 1, at or beyond the first or last)."""
        w = self.node_omegas
        if omega <= w[0]:
            return [(0, 1.0)]
        if omega >= w[-1]:
            return [(w.size - 1, 1.0)]
        i = int(np.searchsorted(w, omega)) - 1
        a = math.log(omega / w[i]) / math.log(w[i + 1] / w[i])
        return [(i, 1.0 - a), (i + 1, a)]

    # ------------------------------------------------------------------ evaluation
    def mean(self, x) -> np.ndarray:
        """Modelled mean features ``(..., d)`` at points ``x`` ``(..., 6)``: slip [-], kS [N/m], phiS, dphi [rad],
        omega [rad/s], noise_smooth [g]."""
        x = np.asarray(x, dtype=float)
        flat = x.reshape(-1, 6)
        d = self.coef.shape[3]
        out = np.zeros((flat.shape[0], d))
        weights = patch_weights(flat[:, 0], self.patches)
        for om in np.unique(flat[:, 4]):
            nodes = self.node_weights(om)
            for j, patch in enumerate(self.patches):
                rows = np.flatnonzero((flat[:, 4] == om) & (weights[:, j] > 0))
                c, h = patch_norm(self.center, self.halfwidth, patch)
                u = (flat[rows][:, [0, 1, 2, 3, 5]] - c) / h
                for i in range(0, rows.size, _CHUNK):
                    dm = legendre_design(u[i : i + _CHUNK], self.terms)
                    r = rows[i : i + _CHUNK]
                    out[r] += weights[r, j, None] * sum(w * (dm @ self.coef[k, j]) for k, w in nodes)
        return out.reshape(x.shape[:-1] + (d,))

    def cov(self, omega: float, noise_smooth: float) -> np.ndarray:
        """``R`` ``(d, d)`` at leg speed ``omega`` [rad/s] and smoothed noise ``noise_smooth`` [g] (beyond the
        last noise knot, the last knot's; made positive definite in the features' scales,
        :func:`nearest_positive_definite`)."""
        if self.cov_knots is None:
            s2 = float(noise_smooth) ** 2
            r = sum(w * (self.cov_coef[k, 0] + s2 * self.cov_coef[k, 1]) for k, w in self.node_weights(omega))
        else:
            h = cov_knot_weights(float(noise_smooth), self.cov_knots)
            r = sum(w * np.tensordot(h, self.cov_coef[k], axes=1) for k, w in self.node_weights(omega))
        return nearest_positive_definite(r)

    def grid_factors(self, slip_nodes, kS_levels, phiS_levels, dphi_levels, omega: float, noise_smooth: float,
                     right: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mean features on a tensor grid at one leg speed [rad/s] and smoothed noise [g], as the two factors of
        :func:`legendre_factors`: ``partial`` ``(A, d, nk, nphiS, ndphi)`` and ``basis`` ``(K, A)`` (the slip
        patches' factors stacked along ``A``, each patch's basis rows weighted by its blend,
        :func:`patch_weights`); :func:`contract_slip` makes the grid (:meth:`mean_on_grid`). ``right``: a
        ``(d, m)`` matrix (the estimator's whitener) the mean features are multiplied by (``partial`` then
        ``(A, m, ...)``): applied to the coefficients, the same (to rounding) as multiplying the grid, and
        cheaper."""
        us = (float(noise_smooth) - self.center[4]) / self.halfwidth[4]
        ps = np.polynomial.legendre.legvander(np.array([us]), int(self.terms[:, 4].max()))[0][self.terms[:, 4]]
        slip_nodes = np.asarray(slip_nodes, dtype=float)
        weights = patch_weights(slip_nodes, self.patches)
        parts, bases = [], []
        for j, patch in enumerate(self.patches):
            if not np.any(weights[:, j] > 0):
                continue
            coef = sum(w * self.coef[k, j] for k, w in self.node_weights(omega)) * ps[:, None]
            if right is not None:
                coef = coef @ right
            c, h = patch_norm(self.center, self.halfwidth, patch)
            partial, basis = legendre_factors(self.terms[:, :4], coef, c[:4], h[:4],
                                              (slip_nodes, kS_levels, phiS_levels, dphi_levels))
            if np.all(weights[:, j] == 1.0):
                return partial, basis  # one patch holds every node (the weights sum to one: the others were skipped)
            parts.append(partial)
            bases.append(basis * weights[:, j, None])  # 0 on the nodes outside the patch
        return np.concatenate(parts), np.concatenate(bases, axis=1)

    def mean_on_grid(self, slip_nodes, kS_levels, phiS_levels, dphi_levels, omega: float, noise_smooth: float,
                     right: np.ndarray | None = None) -> np.ndarray:
        """Mean features on a tensor grid at one leg speed [rad/s] and smoothed noise [g]: ``(nk, nphiS, ndphi,
        K, d)`` (a transposed view, :func:`contract_slip` of :meth:`grid_factors`); ``right`` as there
        (``(nk, nphiS, ndphi, K, m)``)."""
        return contract_slip(*self.grid_factors(slip_nodes, kS_levels, phiS_levels, dphi_levels, omega,
                                                noise_smooth, right))

    # ------------------------------------------------------------------ file
    def save(self, path) -> Path:
        """Write the model as a compressed ``.npz`` (parent directories created)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            np.savez_compressed(
                fh, format_version=np.array(FORMAT_VERSION), variables=np.array(VARIABLES), features=np.array(self.features),
                node_omegas=self.node_omegas, center=self.center, halfwidth=self.halfwidth, ranges=self.ranges,
                phid_min=np.array(self.phid_min), terms=self.terms, coef=self.coef, cov_coef=self.cov_coef,
                patches=self.patches, cov_knots=np.zeros(0) if self.cov_knots is None else self.cov_knots,
                covered=np.array(json.dumps(self.covered)), meta=np.array(json.dumps(self.meta, allow_nan=False)))
        return path

    @classmethod
    def load(cls, source, name: str) -> "FeatureSurrogate":
        """Read a model from a path or binary file object; ``name`` is what errors call it."""
        try:
            with np.load(source, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError) as exc:
            raise InverseModelError(f"{name}: not an inverse model file ({exc})") from None
        version = int(d["format_version"]) if "format_version" in d else None
        if version not in READ_VERSIONS:
            raise InverseModelError(f"{name}: format_version {version!r} is not supported (this slipest reads "
                                    f"{', '.join(map(str, READ_VERSIONS))}); regenerate it with tools/train_inverse.py")
        keys = ("variables", "features", "node_omegas", "center", "halfwidth", "ranges", "phid_min", "terms", "coef",
                "cov_coef", "covered", "meta") + (("patches",) if version >= 4 else ()) \
            + (("cov_knots",) if version >= 5 else ())
        missing = [k for k in keys if k not in d]
        if missing:
            raise InverseModelError(f"{name}: missing key(s) {missing}")
        if list(d["variables"]) != list(VARIABLES):
            raise InverseModelError(f"{name}: variables {list(d['variables'])} are not {list(VARIABLES)}")
        coef = d["coef"].astype(float)
        if version == 3:  # one patch: (M, T, d) -> (M, 1, T, d)
            coef = coef[:, None]
        try:
            return cls(tuple(str(f) for f in d["features"]), d["node_omegas"].astype(float), d["center"].astype(float),
                       d["halfwidth"].astype(float), d["ranges"].astype(float), float(d["phid_min"]),
                       d["terms"].astype(np.int64), coef, d["cov_coef"].astype(float),
                       json.loads(str(d["covered"])), json.loads(str(d["meta"])),
                       d["patches"].astype(float) if version >= 4 else None,
                       d["cov_knots"].astype(float) if version >= 5 and d["cov_knots"].size else None)
        except InverseModelError as exc:
            raise InverseModelError(f"{name}: {exc}") from None
        except (ValueError, TypeError) as exc:
            raise InverseModelError(f"{name}: malformed inverse model ({exc})") from None


_CACHE: dict = {}


def load_inverse_model(path=None) -> FeatureSurrogate:
    """Load the inverse model (default: the shipped ``slipest/data/inverse_model.npz``; cached per file and
    its modification time and size, so a file written again is read again).

    Raises :class:`InverseModelError` naming the file when it is missing, unreadable, of another format
    version or malformed.
    """
    key = None
    if path is not None:
        try:
            st = Path(path).stat()
            key = (str(Path(path).resolve()), st.st_mtime_ns, st.st_size)
        except OSError:
            key = str(path)  # missing or unreadable: not cached, the load below says which
    if key in _CACHE:
        return _CACHE[key]
    if path is None:
        from importlib import resources

        name = "shipped inverse model slipest/data/inverse_model.npz"
        try:
            data = resources.files("slipest").joinpath("data/inverse_model.npz").read_bytes()
        except FileNotFoundError:
            raise InverseModelError(f"{name} is missing: run tools/train_inverse.py") from None
        import io

        model = FeatureSurrogate.load(io.BytesIO(data), name)
    else:
        name = f"inverse model file {path}"
        if not Path(path).is_file():
            raise InverseModelError(f"{name} not found" if not Path(path).exists() else f"{name} cannot be read "
                                    "(not a file)")
        model = FeatureSurrogate.load(path, name)
    _CACHE[key] = model
    return model


def save_inverse_model(model: FeatureSurrogate, path) -> Path:
    """Write the model (see :meth:`FeatureSurrogate.save`)."""
    return model.save(path)


__all__ = ["FORMAT_VERSION", "READ_VERSIONS", "VARIABLES", "MODEL_FEATURES", "MOMENT_FEATURES", "InverseModelError",
           "node_terms",
           "check_patches", "one_patch", "patch_weights", "patch_norm", "N_COV_KNOTS", "default_cov_knots",
           "check_cov_knots", "cov_knot_weights", "nearest_positive_definite", "fit_node",
           "legendre_design", "legendre_factors", "contract_slip", "legendre_on_grid", "whitener",
           "FeatureSurrogate", "load_inverse_model", "save_inverse_model"]
