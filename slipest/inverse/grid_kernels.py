"""Compiled kernels of the soil-grid inversions (numba, one thread, int16 tables).

The grid inversions (:class:`slipest.inverse.feature_inverse.FeatureInverse`, one
cycle; :class:`slipest.estimator.SoilSlipEstimator`, recursive) compare a
cycle's whitened features ``fw`` with the whitened mean features of every
soil cell ``s`` at every slip node ``k``:

    d(s, k) = -scale |fw - step * table[:, k, s]|^2 / 2 + lp[k]        [nats]

(``lp``: log prior of the slip nodes), then marginalise slip (per cell) or
the soil (per slip node). Tables are **columnar**, ``(D, K, S)``:
coordinate, slip node, soil cell, the cell innermost, so that every inner
loop runs over the cells (about 6000 by default) contiguously and
vectorises; loops over the 28-56 slip nodes of one cell are too short to.
They hold int16 counts of a float32 step per coordinate
(:class:`slipest.inverse.grid.Table`): half the bytes of float32, and
reading the table is what the distances cost.

``exp`` of a log-likelihood difference is :func:`fexp` where the sums are
large (float32, vectorisable, relative error ``d^2 / 2048``: the sums it
enters are dominated by terms near 0 and move by < 0.01 nats) and the
exact ``math.exp`` elsewhere. Units: log-likelihoods in nats; slip [-].
"""

from __future__ import annotations

import math

import numba
import numpy as np


#: fastmath but for reassociation: sums keep the order they are written in (results do not depend on how the
#: compiler groups them), min and max reductions still vectorise.
_NO_REASSOC = {"nnan", "ninf", "nsz", "arcp", "contract", "afn"}


@numba.njit(cache=True, fastmath=True, inline="always")
def fexp(d):
    """``exp(d)`` for ``d <= 0`` as ``(1 + d/1024)^1024`` (float32, vectorisable).

    Relative error about ``d^2 / 2048``: below 1.2 % for ``d > -5``; the
    log-sums it enters are dominated by terms near 0 and move by < 0.01
    (measured 0.002) nats. ``d`` is clamped at -60.
    """
    x = np.float32(1.0) + max(d, np.float32(-60.0)) * np.float32(1.0 / 1024.0)
    for _ in range(10):
        x = x * x
    return x


@numba.njit(cache=True)
def whiten_into(row, cols, whitener, fw):
    """A full feature row in a table's coordinates: ``fw[:n] = float32(row[cols] @ whitener)``.

    ``row``: ``(F,)`` float64 feature row (order of ``FEATURE_NAMES``);
    ``cols``: ``(d,)`` int64 columns of the modelled features; ``whitener``:
    ``(d, n)`` float64. Returns False, ``fw`` untouched, when a modelled
    feature is not finite.
    """
    d, n = whitener.shape
    for i in range(d):
        if not np.isfinite(row[cols[i]]):
            return False
    for j in range(n):
        acc = 0.0
        for i in range(d):
            acc += row[cols[i]] * whitener[i, j]
        fw[j] = np.float32(acc)
    return True


@numba.njit(cache=True, inline="always")
def quantise_step(top, limit):
    """The float32 step of a coordinate whose largest ``|value|`` is ``top``: ``min(top, limit) / 32767``, 1
    for a coordinate of zeros or of values so small the step underflows float32 (their counts are then 0;
    the rule of :func:`slipest.inverse.grid.quantise`)."""
    t = min(top, limit)
    s = np.float32(t / 32767.0 if t > 0.0 else 1.0)
    return s if s > 0.0 else np.float32(1.0)


@numba.njit(cache=True, inline="always")
def quantise_count(v, st):
    """The int16 count of ``v`` for the step ``st`` (the float32 step as float64): ``rint(v / st)`` clipped to
    +-32767, so ``count * step`` is within ``step / 2`` of ``v`` (up to the clipping)."""
    return np.int16(min(max(np.rint(v / st), -32767.0), 32767.0))


@numba.njit(cache=True)
def quantise_into(x, limit, counts, step):
    """The int16 counts of :func:`slipest.inverse.grid.quantise` of ``x`` ``(D, K, S)``: ``counts`` ``(D, K, S)``
    int16 and ``step`` ``(D,)`` float32 (:func:`quantise_step` of the largest ``|x|`` of the coordinate; each
    count :func:`quantise_count`, in float64 with the float32 step the kernels multiply by)."""
    D, K, S = x.shape
    for d in range(D):
        top = 0.0
        for k in range(K):
            for s in range(S):
                v = abs(x[d, k, s])
                if v > top:
                    top = v
        step[d] = quantise_step(top, limit)
        st = np.float64(step[d])
        for k in range(K):
            for s in range(S):
                counts[d, k, s] = quantise_count(x[d, k, s], st)


@numba.njit(cache=True)
def quantise_product_into(partial, basis_t, cells, limit, counts, step, rows):
    """The counts and steps of :func:`quantise_into` of the table ``sum_a basis_t[a, k] * partial[a, d, cells[s]]``,
    computed cell by cell without the table (:func:`slipest.inverse.grid.quantise_product`).

    ``partial``: ``(A, D, G)`` float64; ``basis_t``: ``(A, K)`` float64; ``cells``: ``(S,)`` int64 indices
    into ``G``; ``counts``: ``(D, K, S)`` int16 and ``step`` ``(D,)`` float32, written as :func:`quantise_into`
    writes them; ``rows``: ``(S, K)`` float64 scratch (one coordinate's values). The sum over ``a`` runs in
    order, in float64."""
    A, D, G = partial.shape
    K = basis_t.shape[1]
    S = cells.size
    for d in range(D):
        top = 0.0
        for s in range(S):
            g = cells[s]
            row = rows[s]
            for k in range(K):
                row[k] = 0.0
            for a in range(A):
                c = partial[a, d, g]
                b = basis_t[a]
                for k in range(K):
                    row[k] += c * b[k]
            for k in range(K):
                v = abs(row[k])
                if v > top:
                    top = v
        step[d] = quantise_step(top, limit)
        st = np.float64(step[d])
        out = counts[d]
        for s in range(S):
            row = rows[s]
            for k in range(K):
                out[k, s] = quantise_count(row[k], st)


@numba.njit(cache=True, fastmath=_NO_REASSOC)
def grid_loglik(tc, tstep, fw, lp, node_width, scale, fit_level, dmat, lc, scratch, floor=1.0):
    """Cell log-likelihoods with the slip marginalised over the table's slip nodes.

    ``tc``: ``(D, K, S)`` int16 columnar table of counts of ``tstep``
    (``(D,)`` float32, per coordinate: :class:`slipest.inverse.grid.Table`);
    ``fw``: ``(D,)`` float32 whitened features; ``lp``: ``(K,)`` float32 log prior of the nodes;
    ``node_width``: node spacing [-]; ``scale``: the likelihood's exponent
    (tempering). The smallest squared whitened distance over cells and nodes,
    ``best``, says how well the model explains the cycle: when it exceeds
    ``fit_level`` (inf: never) the cycle's ``misfit`` is ``best / fit_level``
    (else 1). The exponent is divided by ``widen = max(misfit, floor)``
    (``floor`` >= 1: a widening known from elsewhere, e.g. the recent
    cycles'; 1: none). Writes ``dmat[k, s] = d(s, k) = -scale |fw - tc[:, k,
    s] tstep|^2 / (2 widen) + lp[k]`` (``(K, S)`` float32) and ``lc[s] =
    log(node_width * sum_k exp(d(s, k)))`` (``(S,)`` float64), a Riemann sum
    of the likelihood over slip, the exp by :func:`fexp` relative to the
    cell's largest term. ``scratch``: ``(2, S)`` float32 (the largest term,
    the sum). Returns ``(best, misfit)``.
    """
    D, K, S = tc.shape
    mx = scratch[0]
    tot = scratch[1]
    best = np.float32(np.inf)
    for k in range(K):
        row = dmat[k]
        for s in range(S):
            row[s] = np.float32(0.0)
        # the squares added coordinate by coordinate, in order; four coordinates a pass over the row (the row is
        # loaded and stored a quarter as often: the pass is bound by that, not by the table)
        j = 0
        while j + 4 <= D:
            f0, f1, f2, f3 = fw[j], fw[j + 1], fw[j + 2], fw[j + 3]
            a0, a1, a2, a3 = tstep[j], tstep[j + 1], tstep[j + 2], tstep[j + 3]
            t0, t1, t2, t3 = tc[j, k], tc[j + 1, k], tc[j + 2, k], tc[j + 3, k]
            for s in range(S):
                e0 = a0 * np.float32(t0[s]) - f0
                e1 = a1 * np.float32(t1[s]) - f1
                e2 = a2 * np.float32(t2[s]) - f2
                e3 = a3 * np.float32(t3[s]) - f3
                row[s] = (((row[s] + e0 * e0) + e1 * e1) + e2 * e2) + e3 * e3
            j += 4
        for j in range(j, D):
            fj = fw[j]
            aj = tstep[j]
            tj = tc[j, k]
            for s in range(S):
                e = aj * np.float32(tj[s]) - fj
                row[s] += e * e
        if k == 0:  # the smallest distance per cell so far, in tot (free until the sums below)
            for s in range(S):
                tot[s] = row[s]
        else:
            for s in range(S):  # tot = min(tot, row), as an exact blend: a scalar min reduction does not vectorise
                v = row[s]
                c = np.float32(v < tot[s])
                tot[s] = c * v + (np.float32(1.0) - c) * tot[s]
    for s in range(S):
        if tot[s] < best:
            best = tot[s]
    misfit = best / fit_level if best > fit_level else 1.0
    half = np.float32(-0.5 * scale / max(misfit, floor))
    for k in range(K):
        row = dmat[k]
        lk = lp[k]
        for s in range(S):
            row[s] = half * row[s] + lk
        if k == 0:
            for s in range(S):
                mx[s] = row[s]
        else:
            for s in range(S):  # mx = max(mx, row), as an exact blend: a select does not vectorise here
                v = row[s]
                c = np.float32(v > mx[s])
                mx[s] = c * v + (np.float32(1.0) - c) * mx[s]
    for s in range(S):
        tot[s] = np.float32(0.0)
    for k in range(K):
        row = dmat[k]
        for s in range(S):
            tot[s] += fexp(row[s] - mx[s])
    for s in range(S):
        lc[s] = mx[s] + math.log(tot[s] * node_width)
    return best, misfit


@numba.njit(cache=True, fastmath=True)
def select_cells(logw, lc, cutoff, sel, base):
    """The cells that matter to the slip marginal: joint log weight ``logw + lc`` within ``cutoff`` of the largest.

    Writes their indices (ascending) to ``sel`` (``(S,)`` int64) and
    ``base[i] = logw - top`` (float32) of each; returns how many. The cells
    left out hold less than ``exp(-cutoff)`` of the largest one's mass each.
    """
    S = logw.size
    top = -np.inf
    for s in range(S):
        v = logw[s] + lc[s]
        if v > top:
            top = v
    n = 0
    lim = top - cutoff
    for s in range(S):
        if logw[s] + lc[s] >= lim:
            sel[n] = s
            base[n] = np.float32(logw[s] - top)
            n += 1
    return n


@numba.njit(cache=True, fastmath=True)
def marginal_from_rows(dmat, sel, base, n, ps):
    """Add ``sum_i exp(base[i] + dmat[k, sel[i]])`` (by :func:`fexp`) to ``ps[k]`` for every row ``k``.

    ``dmat``: ``(K, S)`` float32 values ``d(s, k)`` already computed (by
    :func:`grid_loglik`); ``sel``, ``base``, ``n``: from :func:`select_cells`.
    """
    for k in range(dmat.shape[0]):
        row = dmat[k]
        acc = 0.0
        for i in range(n):
            acc += fexp(base[i] + row[sel[i]])
        ps[k] += acc


@numba.njit(cache=True, fastmath=True)
def node_moments(ps, x, quant):
    """Mean and standard deviation of the nodes ``x`` under the weights ``ps`` (normalised here).

    ``quant``: variance added to the spread (a node's width squared over
    12: the value is anywhere within its node). NaN when the weights are all 0.
    """
    tot = 0.0
    for k in range(ps.size):
        tot += ps[k]
    if not tot > 0.0:
        return np.nan, np.nan
    m = 0.0
    for k in range(ps.size):
        m += ps[k] * x[k]
    m /= tot
    v = 0.0
    for k in range(ps.size):
        d = x[k] - m
        v += ps[k] * d * d
    sd = math.sqrt(max(v / tot, 0.0))
    return m, math.sqrt(sd * sd + quant)


@numba.njit(cache=True)
def weighted_moments(w, xs, q, out):
    """Means and standard deviations of the rows of ``xs`` under the weights ``w`` (summing to 1).

    ``q``: variance added to each row's spread (a cell's width squared
    over 12). Writes ``out[2 i] = mean_i``, ``out[2 i + 1] = std_i``.
    """
    for i in range(xs.shape[0]):
        acc = 0.0
        for s in range(w.size):
            acc += w[s] * xs[i, s]
        m = acc
        acc = 0.0
        for s in range(w.size):
            d = xs[i, s] - m
            acc += w[s] * d * d
        out[2 * i] = m
        out[2 * i + 1] = math.sqrt(max(acc, 0.0) + q[i])


@numba.njit(cache=True)
def touch(a):
    """Read one value per 64-byte cache line of the 1-D array ``a`` (brings it into the CPU caches); returns their sum."""
    step = max(1, 64 // a.itemsize)
    acc = 0.0
    for i in range(0, a.size, step):
        acc += a[i]
    return acc
