"""The compiled soil-grid kernels (slipest.inverse.grid_kernels) against plain statements of what they compute."""

import math

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.inverse.grid import QUANTISE_LIMIT, GridTables, SoilGrid, quantise, quantise_product
from slipest.inverse.grid_kernels import _NO_REASSOC, grid_loglik


@numba.njit(fastmath=_NO_REASSOC)
def _distances_one_coordinate_a_pass(tc, tstep, fw, dmat):
    """The squared distances as first written: one pass over the row per coordinate, in order."""
    D, K, S = tc.shape
    for k in range(K):
        for s in range(S):
            dmat[k, s] = np.float32(0.0)
        for j in range(D):
            for s in range(S):
                e = tstep[j] * np.float32(tc[j, k, s]) - fw[j]
                dmat[k, s] += e * e


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 9), st.integers(1, 5), st.integers(1, 70), st.integers(0, 2**32 - 1), st.floats(0.1, 30.0))
def test_grid_loglik_distances_equal_the_one_coordinate_sum(D, K, S, seed, spread):
    """grid_loglik adds four coordinates a pass over the row: the squared distances it returns are bit for bit
    those of one coordinate a pass (the sums keep their order), for any number of coordinates (remainders
    included); the best distance is their minimum; the cell log-likelihoods match the float64 formula."""
    rng = np.random.default_rng(seed)
    tc, tstep = quantise(rng.normal(0.0, spread, (D, K, S)))
    fw = rng.normal(0.0, spread, D).astype(np.float32)
    lp = np.where(np.arange(K) % 3 == 2, -4.0, 0.0).astype(np.float32)
    dmat = np.empty((K, S), dtype=np.float32)
    lc = np.empty(S)
    best, misfit = grid_loglik(tc, tstep, fw, lp, 0.02, 0.4, math.inf, dmat, lc, np.empty((2, S), dtype=np.float32))
    ref = np.empty((K, S), dtype=np.float32)
    _distances_one_coordinate_a_pass(tc, tstep, fw, ref)
    assert best == ref.min() and misfit == 1.0
    d = -0.5 * 0.4 * ref.astype(float) + lp[:, None]  # dmat now holds these (float32)
    np.testing.assert_allclose(dmat, d, rtol=1e-6, atol=1e-5)
    top = d.max(axis=0)
    expect = top + np.log(0.02 * np.exp(d - top).sum(axis=0))
    np.testing.assert_allclose(lc, expect, rtol=0, atol=0.02)  # fexp's error (grid_kernels docstring)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 4), st.integers(1, 40), st.integers(0, 2**32 - 1),
       st.floats(1e-3, 300.0), st.floats(-50.0, 50.0))
def test_a_quantised_table_holds_its_values_within_half_a_step(D, K, S, seed, spread, shift):
    """quantise: int16 counts of one step per coordinate, the largest |value| over 32767, every value within
    half a step (a float32 rounding more); a coordinate of zeros keeps a usable step."""
    rng = np.random.default_rng(seed)
    values = rng.normal(shift, spread, (D, K, S))
    values[0, 0, 0] = 0.0
    counts, step = quantise(values, limit=np.inf)
    assert counts.dtype == np.int16 and step.dtype == np.float32 and counts.flags.c_contiguous
    top = np.abs(values).max(axis=(1, 2))
    np.testing.assert_allclose(step, np.where(top > 0, top / 32767.0, 1.0), rtol=1e-6)
    back = counts * step[:, None, None].astype(float)
    assert np.all(np.abs(back - values) <= step[:, None, None] * (0.5 + 1e-3))
    assert int(np.abs(counts).max()) <= 32767
    zeros, zstep = quantise(np.zeros((2, 1, 3)))
    assert np.all(zeros == 0) and np.all(zstep == 1.0)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 4), st.integers(1, 40), st.integers(0, 2**32 - 1),
       st.floats(1e-3, 600.0), st.booleans())
def test_quantise_equals_its_numpy_statement(D, K, S, seed, spread, cells_outermost):
    """The compiled quantise_into gives exactly the counts and steps of the plain numpy statement (counts of the
    float32 step the kernels multiply by), whatever the memory layout of the values (columnar, or a transposed
    view of a cells-outermost array)."""
    rng = np.random.default_rng(seed)
    values = rng.normal(0.0, spread, (D, K, S))
    if cells_outermost:
        values = np.ascontiguousarray(values.transpose(2, 1, 0)).transpose(2, 1, 0)
    counts, step = quantise(values)
    top = np.minimum(np.abs(values).max(axis=(1, 2)), QUANTISE_LIMIT)
    plain = np.where(top > 0, top / 32767.0, 1.0).astype(np.float32)
    assert np.array_equal(step, plain)
    used = plain.astype(np.float64)[:, None, None]
    assert np.array_equal(counts, np.clip(np.rint(values / used), -32767, 32767).astype(np.int16))


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 5), st.integers(1, 6), st.integers(1, 60), st.integers(0, 2**32 - 1),
       st.floats(1e-3, 600.0))
def test_quantise_product_equals_quantise_of_the_product(A, D, K, G, seed, spread):
    """quantise_product never makes the table, but gives exactly quantise's counts and steps of it when the
    table's sums run in the same order (slip degree by slip degree, float64), on any subset of the grid's
    points, with values beyond the clipping limit too."""
    rng = np.random.default_rng(seed)
    partial = rng.normal(0.0, spread, (A, D, G))
    basis = rng.normal(0.0, 1.0, (K, A))
    cells = np.flatnonzero(rng.random(G) < 0.7)
    if cells.size == 0:
        cells = np.array([G - 1])
    values = np.zeros((D, K, cells.size))
    for a in range(A):  # the order the kernel adds in
        values = values + basis[None, :, a, None] * partial[a][:, None, cells]
    counts, step = quantise_product(partial, basis, cells)
    ref_counts, ref_step = quantise(values)
    assert np.array_equal(step, ref_step) and np.array_equal(counts, ref_counts)


def test_quantise_product_refuses_factors_that_do_not_match():
    with pytest.raises(ValueError, match="partial"):
        quantise_product(np.zeros((3, 2, 5)), np.zeros((4, 2)), np.arange(5))
    with pytest.raises(ValueError, match="index"):
        quantise_product(np.zeros((3, 2, 5)), np.zeros((4, 3)), np.array([0, 5]))


def test_a_table_of_the_shipped_model_is_the_quantised_grid_mean():
    """The estimator's table build (the grid's factors quantised cell by cell) gives the counts and steps of the
    plain statement: the whitened grid mean, its cells gathered, quantised (to the rounding of the sums: not one
    count of the 3.5 million differs at these bins)."""
    from slipest.inverse.surrogate import load_inverse_model

    model = load_inverse_model()
    grid = SoilGrid.default()
    tables = GridTables(model, grid, np.arange(0.0, 0.551, 0.02))
    for omega, noise in ((0.41, 0.0007), (1.1, 0.02)):
        table = tables.get(omega, noise)
        mean = model.mean_on_grid(tables.nodes, grid.kS, grid.phiS, grid.dphi, table.omega, table.noise_smooth,
                                  right=table.whitener)
        counts, step = quantise(mean[grid.mask].transpose(2, 1, 0))
        assert np.array_equal(table.step, step)
        assert np.array_equal(table.columnar, counts)


def test_a_far_cell_is_clipped_and_does_not_coarsen_the_others():
    """One whitened mean 1e5 standard deviations out (a nearly constant feature of a calibrated rover, say):
    clipped to the limit, the other cells keep the limit's fine step, and the cycle's distances to them are
    those of the float64 table."""
    rng = np.random.default_rng(7)
    values = rng.normal(0.0, 20.0, (3, 2, 50))
    values[1, 0, 3] = 1e5
    counts, step = quantise(values)
    assert step[1] == np.float32(QUANTISE_LIMIT / 32767.0)
    back = counts * step[:, None, None].astype(float)
    assert back[1, 0, 3] == pytest.approx(QUANTISE_LIMIT, rel=1e-6)
    near = np.ones_like(values, dtype=bool)
    near[1, 0, 3] = False
    assert np.all(np.abs(back - values)[near] <= step.max() * 0.51)
    fw = rng.normal(0.0, 3.0, 3).astype(np.float32)
    dmat = np.empty((2, 50), dtype=np.float32)
    grid_loglik(counts, step, fw, np.zeros(2, np.float32), 0.02, 1.0, math.inf, dmat, np.empty(50),
                np.empty((2, 50), dtype=np.float32))
    e = values - fw[:, None, None].astype(float)
    exact = (e**2).sum(axis=0)
    half = step[:, None, None].astype(float) / 2  # each value is within half a step: so is each |e|
    bound = (2.0 * np.abs(e) * half + half**2).sum(axis=0) + 1e-6 * exact  # (and float32 sums)
    got = -2.0 * dmat.astype(float)
    keep = near.all(axis=0)
    assert np.all(np.abs(got - exact)[keep] <= bound[keep])
    assert got[0, 3] > 0.99 * (QUANTISE_LIMIT - abs(fw[1])) ** 2  # the clipped cell: still far


def test_a_refined_soil_grid_keeps_its_ranges_and_levels_and_refuses_a_bad_factor():
    import pytest

    from slipest.inverse.grid import SoilGrid

    g = SoilGrid.default()
    r = g.refined(2)
    for a, b in ((g.kS, r.kS), (g.phiS, r.phiS), (g.dphi, r.dphi)):
        assert b.size == 2 * a.size - 1
        assert b[0] == a[0] and b[-1] == a[-1]
        np.testing.assert_allclose(b[::2], a, atol=1e-12)  # the shipped levels are among the refined ones
    np.testing.assert_allclose(r.steps(), g.steps() / 2)
    assert r.phid_min == g.phid_min
    assert 6 * g.size < r.size < 8 * g.size  # about 8x the cells (phiD >= phid_min cuts a corner)
    assert g.refined(1).key() == g.key()
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="integer >= 1"):
            g.refined(bad)


def test_a_coordinate_too_small_for_a_float32_step_quantises_to_zeros_not_a_division_by_zero():
    """A rover file's extra covariance of 1e300 whitened every mean to ~1e-150, whose step underflowed float32 to
    0: a ZeroDivisionError out of a table build. The step is then 1 and the counts 0 (the values are 0 to
    float32's precision), in the plain and the product routine alike."""
    values = np.full((2, 3, 4), 1e-300)
    values[1] = np.arange(12.0).reshape(3, 4)
    counts, step = quantise(values)
    assert step[0] == 1.0 and not counts[0].any() and step[1] == np.float32(11.0 / 32767)
    partial = np.full((1, 2, 4), 1e-300)
    c2, s2 = quantise_product(partial, np.ones((3, 1)), np.arange(4))
    assert (s2 == 1.0).all() and not c2.any()
