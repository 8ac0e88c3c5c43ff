"""The feature surrogate's model: per-node Legendre fit, speed interpolation, grid evaluation, file format."""

import json
import math

import numpy as np
import pytest

from slipest.inverse.surrogate import (
    FORMAT_VERSION,
    FeatureSurrogate,
    InverseModelError,
    check_patches,
    cov_knot_weights,
    default_cov_knots,
    fit_node,
    load_inverse_model,
    nearest_positive_definite,
    node_terms,
    patch_weights,
    save_inverse_model,
    whitener,
)

FEATS = ("rms", "onset", "osc_freq")
LO = np.array([0.0, 500.0, 0.1, 0.0, 0.0])
HI = np.array([0.5, 1500.0, 0.8, 0.35, 0.02])
CENTER, HALF = (LO + HI) / 2, (HI - LO) / 2
NODES = np.array([0.4, 0.6, 0.9])
SCHEDULE = {0: 4, 1: 2}


def _truth(x5, node):
    """Three smooth 'features' of known form (within the schedule: cubic in slip/soil, linear in the noise)."""
    u = (x5 - CENTER) / HALF
    s = 1.0 + 0.5 * node
    return np.column_stack([
        s * (0.2 + 0.1 * u[:, 0] ** 3 - 0.05 * u[:, 1] * u[:, 3]) + 0.04 * u[:, 4],
        0.5 + 0.2 * s * u[:, 0] * u[:, 2] + 0.03 * u[:, 1] ** 2,
        8.0 + 1.5 * u[:, 1] - 0.4 * s * u[:, 3] ** 3 + 0.2 * u[:, 0] * u[:, 1] * u[:, 2] + 0.3 * u[:, 4] * u[:, 0],
    ])


def _draw(n, rng):
    return rng.uniform(LO, HI, (n, 5))


#: Two slip patches overlapping over 0.2-0.3.
PATCHES = np.array([[0.0, 0.3], [0.2, 0.5]])


def _fit(patches, n=4000):
    rng = np.random.default_rng(3)
    terms = node_terms(SCHEDULE)
    coef, cov = [], []
    for node in range(NODES.size):
        x5 = _draw(n, rng)
        # residual noise with a standard deviation growing with the noise input: 1e-3 * sqrt(1 + (s / 0.01)^2)
        sd = 1e-3 * np.sqrt(1.0 + (x5[:, 4] / 0.01) ** 2)
        y = _truth(x5, node) + rng.normal(0, 1, (n, 3)) * sd[:, None]
        c, r = fit_node(x5, y, terms, CENTER, HALF, patches)
        coef.append(c)
        cov.append(r)
    ranges = np.vstack([np.column_stack([LO, HI]), [NODES[0], NODES[-1]]])
    return FeatureSurrogate(FEATS, NODES, CENTER, HALF, ranges, 0.1, terms, np.stack(coef), np.stack(cov),
                            {"omega": [0.45, 0.85]}, {"training": {"n_legs": 4}}, patches,
                            default_cov_knots(CENTER, HALF))


@pytest.fixture(scope="module")
def fitted():
    return _fit(None)


@pytest.fixture(scope="module")
def patched():
    return _fit(PATCHES, n=8000)


def _x6(x5, omega):
    return np.column_stack([x5[:, :4], np.full(len(x5), omega), x5[:, 4]])


def test_a_node_recovers_a_known_polynomial_and_its_noise(fitted):
    x5 = _draw(500, np.random.default_rng(4))
    for node, omega in enumerate(NODES):
        err = fitted.mean(_x6(x5, omega)) - _truth(x5, node)
        # noise ~1.5e-3 on 4000 rows, 45 terms: the mean's error is about 1.5e-3 * sqrt(45 / 4000) = 1.6e-4 RMS
        assert np.sqrt(np.mean(err**2)) < 4e-4
    # the residual covariance on noise knots follows a variance 1e-6 * (1 + (s / 0.01)^2) on the diagonal
    for s in (0.0, 0.01, 0.02):
        assert np.allclose(np.diag(fitted.cov(0.6, s)), 1e-6 * (1 + (s / 0.01) ** 2), rtol=0.15)


def test_between_nodes_linear_in_log_speed(fitted):
    assert fitted.node_weights(0.3) == [(0, 1.0)] and fitted.node_weights(2.0) == [(2, 1.0)]
    omega = 0.6 * (0.9 / 0.6) ** 0.25
    (i, wi), (j, wj) = fitted.node_weights(omega)
    assert (i, j) == (1, 2) and np.isclose(wj, 0.25) and np.isclose(wi + wj, 1.0)
    x5 = _draw(50, np.random.default_rng(5))
    want = 0.75 * fitted.mean(_x6(x5, 0.6)) + 0.25 * fitted.mean(_x6(x5, 0.9))
    assert np.allclose(fitted.mean(_x6(x5, omega)), want, rtol=1e-10, atol=1e-12)
    assert np.allclose(fitted.cov(omega, 0.01), 0.75 * fitted.cov(0.6, 0.01) + 0.25 * fitted.cov(0.9, 0.01), rtol=1e-6)
    assert fitted.covered_range("omega") == (0.45, 0.85) and fitted.covered_range("kS") == (500.0, 1500.0)


@pytest.mark.parametrize("which", ["fitted", "patched"])
def test_grid_evaluation_equals_the_pointwise_mean(which, request):
    """The grid path (one variable at a time, per patch) and the pointwise mean are one model: equal everywhere,
    on slips inside one patch, in the overlap and beyond the last."""
    model = request.getfixturevalue(which)
    nodes = np.array([0.0, 0.2, 0.25, 0.29, 0.45, 0.52])
    ks, ps, dp = np.array([600.0, 1400.0]), np.array([0.3, 0.6]), np.array([0.05, 0.3])
    omega, s = 0.7, 0.013
    grid = model.mean_on_grid(nodes, ks, ps, dp, omega, s)  # (kS, phiS, dphi, slip, features)
    assert grid.shape == (2, 2, 2, nodes.size, 3)
    for a, kS in enumerate(ks):
        for b, phiS in enumerate(ps):
            for c, dphi in enumerate(dp):
                x = np.column_stack([nodes] + [np.full(nodes.size, v) for v in (kS, phiS, dphi, omega, s)])
                assert np.allclose(grid[a, b, c], model.mean(x), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("which", ["fitted", "patched"])
def test_a_matrix_on_the_right_of_the_grid_mean_is_the_grid_mean_times_it(which, request):
    """The estimator's tables multiply the mean by the whitener through the coefficients (cheaper): the same
    numbers as multiplying the grid, for a square and a non-square matrix."""
    model = request.getfixturevalue(which)
    nodes = np.array([0.0, 0.2, 0.25, 0.29, 0.45, 0.52])
    levels = (nodes, np.array([600.0, 900.0, 1400.0]), np.array([0.3, 0.6]), np.array([0.05, 0.2, 0.3]))
    grid = model.mean_on_grid(*levels, 0.7, 0.013)
    rng = np.random.default_rng(3)
    for right in (rng.normal(size=(3, 3)), rng.normal(size=(3, 2))):
        np.testing.assert_allclose(model.mean_on_grid(*levels, 0.7, 0.013, right=right), grid @ right,
                                   rtol=1e-9, atol=1e-9 * np.abs(grid).max())


def test_patch_weights_sum_to_one_and_blend_smoothly_across_each_overlap():
    p = np.array([[0.0, 0.3], [0.2, 0.4], [0.35, 0.55]])
    s = np.linspace(-0.1, 0.7, 801)
    w = patch_weights(s, p)
    assert w.shape == (s.size, 3) and np.allclose(w.sum(axis=1), 1.0) and (w >= 0).all()
    assert np.array_equal(w[s < 0.2], np.tile([1.0, 0.0, 0.0], ((s < 0.2).sum(), 1)))  # below: the first alone
    assert np.all(w[s > 0.4 + 1e-12, 2] == 1.0)  # beyond the last overlap: the last alone
    mid = np.argmin(np.abs(s - 0.25))
    assert np.allclose(w[mid], [0.5, 0.5, 0.0])  # halfway across an overlap
    # no jump anywhere: at most the smoothstep's steepest slope, 1.5 / (the narrowest overlap, 0.05), times 0.001
    assert np.abs(np.diff(w, axis=0)).max() <= 1.5 / 0.05 * 0.001 + 1e-12


@pytest.mark.parametrize("patches, message", [
    ([[0.0, 0.3], [0.3, 0.5]], "each overlapping the next"),  # touching, no overlap
    ([[0.2, 0.5], [0.0, 0.3]], "must increase"),
    ([[0.0, 0.4], [0.1, 0.45], [0.3, 0.5]], "only it"),  # the first overlap reaches into the second
    ([[0.3, 0.1]], "lo < hi"),
    ([0.0, 0.5], "finite slip ranges"),
])
def test_bad_slip_patches_are_refused_by_name(patches, message):
    with pytest.raises(ValueError, match=message):
        check_patches(patches)


def test_patched_fit_recovers_a_known_polynomial_on_each_side_and_across_the_overlap(patched):
    """A polynomial within the schedule is one in each patch's own slip normalisation too: the patched fit
    recovers it everywhere, blend included."""
    x5 = _draw(2000, np.random.default_rng(8))
    for node, omega in enumerate(NODES):
        err = patched.mean(_x6(x5, omega)) - _truth(x5, node)
        assert np.sqrt(np.mean(err**2)) < 4e-4
        band = (x5[:, 0] > 0.2) & (x5[:, 0] < 0.3)
        assert band.sum() > 200 and np.sqrt(np.mean(err[band] ** 2)) < 4e-4


def test_patched_fit_follows_a_kink_in_slip_that_one_polynomial_smooths():
    """Where the features change their law with slip (a kink at 0.25, inside the overlap: a linear feature
    that turns), two patches of low degree follow each side better than one polynomial of the same degree."""
    rng = np.random.default_rng(9)
    x5 = _draw(20000, rng)
    y = np.column_stack([np.abs(x5[:, 0] - 0.25) + 0.01 * x5[:, 2], x5[:, 1] / 1000, x5[:, 3]])
    terms = node_terms({0: 3})
    test = _draw(3000, np.random.default_rng(10))
    truth = np.column_stack([np.abs(test[:, 0] - 0.25) + 0.01 * test[:, 2], test[:, 1] / 1000, test[:, 3]])
    errs = {}
    for name, patches in (("one", None), ("two", PATCHES)):
        coef, _ = fit_node(x5, y, terms, CENTER, HALF, patches)
        m = FeatureSurrogate(FEATS, NODES[:1], CENTER, HALF, np.vstack([np.column_stack([LO, HI]), [0.4, 0.4]]), 0.1,
                             terms, coef[None], np.zeros((1, 2, 3, 3)) + np.eye(3), {}, {}, patches)
        errs[name] = np.sqrt(np.mean((m.mean(_x6(test, 0.4))[:, 0] - truth[:, 0]) ** 2))
    assert errs["two"] < 0.6 * errs["one"], errs


def test_a_format_3_file_is_read_as_one_patch(fitted, tmp_path):
    path = save_inverse_model(fitted, tmp_path / "m.npz")
    with np.load(path) as z:
        doc = {k: z[k] for k in z.files if k not in ("patches", "cov_knots")}
    doc["format_version"] = np.array(3)
    doc["coef"] = doc["coef"][:, 0]  # (M, T, d): one polynomial per node
    doc["cov_coef"] = doc["cov_coef"][:, :2]  # (A, B) of A + s^2 B, as format 3 holds it
    np.savez(tmp_path / "v3.npz", **doc)
    old = load_inverse_model(tmp_path / "v3.npz")
    x = _x6(_draw(20, np.random.default_rng(11)), 0.66)
    assert old.patches.shape == (1, 2) and np.array_equal(old.mean(x), fitted.mean(x))


@pytest.mark.parametrize("which", ["fitted", "patched"])
def test_file_round_trip_and_other_versions_refused(which, request, tmp_path):
    fitted = request.getfixturevalue(which)
    path = save_inverse_model(fitted, tmp_path / "m.npz")
    again = load_inverse_model(path)
    x = _x6(_draw(50, np.random.default_rng(6)), 0.77)
    assert np.array_equal(again.mean(x), fitted.mean(x)) and np.array_equal(again.patches, fitted.patches)
    assert again.covered == fitted.covered and again.meta == fitted.meta
    with np.load(path) as z:
        doc = {k: z[k] for k in z.files}
    doc["format_version"] = np.array(2)
    old = tmp_path / "old.npz"
    np.savez(old, **doc)
    with pytest.raises(InverseModelError, match=rf"old\.npz: format_version 2 is not supported.*reads 3, 4, {FORMAT_VERSION}.*train_inverse"):
        load_inverse_model(old)


@pytest.mark.parametrize("meta, message", [
    ({"estimator": {"slip_temper": "0.3x"}}, r"meta\['estimator'\]\['slip_temper'\] must be a finite number, got '0.3x'"),
    ({"estimator": {"gross_misfit": float("nan")}}, r"meta\['estimator'\]\['gross_misfit'\] must be a finite number"),
    ({"estimator": [0.3]}, r"meta\['estimator'\] must be a mapping"),
    ({"fit_level": None}, r"meta\['fit_level'\] must be a finite number, got None"),
    ({"fit_level_quantiles": {"q50": True}}, r"meta\['fit_level_quantiles'\]\['q50'\] must be a finite number"),
])
def test_a_model_file_whose_estimator_numbers_are_not_numbers_is_refused_naming_the_file_and_the_number(
        fitted, tmp_path, meta, message):
    """The numbers the estimator reads from a model file's meta: an error at load naming the file and the entry,
    not Python's own conversion error at the estimator's start."""
    from dataclasses import replace

    path = tmp_path / "m.npz"
    good = dict(fitted.meta, fit_level=80.0, fit_level_quantiles={"q50": 20.0},
                estimator={"slip_temper": 0.3, "gross_misfit": 6.0})
    save_inverse_model(replace(fitted, meta=good), path)
    assert load_inverse_model(path).meta["estimator"]["slip_temper"] == 0.3
    bad = fitted.meta | good | meta
    with pytest.raises(InverseModelError, match=message):
        replace(fitted, meta=bad)
    with np.load(path) as z:
        doc = {k: z[k] for k in z.files}
    doc["meta"] = np.array(json.dumps(bad))
    np.savez(path, **doc)
    with pytest.raises(InverseModelError, match=rf"inverse model file .*m\.npz: inverse model {message}"):
        load_inverse_model(path)


def test_unreadable_or_missing_model_file_is_a_clear_error(tmp_path):
    with pytest.raises(InverseModelError, match=r"inverse model file .*nope\.npz not found"):
        load_inverse_model(tmp_path / "nope.npz")
    with pytest.raises(InverseModelError, match=r"inverse model file .* cannot be read"):
        load_inverse_model(tmp_path)  # a directory
    old_json = tmp_path / "inverse_model.json"  # the format before the speed nodes
    old_json.write_text(json.dumps({"format_version": 2}))
    with pytest.raises(InverseModelError, match=r"inverse_model\.json: not an inverse model file"):
        load_inverse_model(old_json)


@pytest.mark.parametrize("field, value, message", [
    ("terms", np.array([[0, 0, 0, 99]]), "terms must be"),
    ("halfwidth", np.array([1.0, 0.0, 1.0, 1.0, 1.0]), "halfwidth must be"),
    ("node_omegas", np.array([0.9, 0.6, 0.4]), "node_omegas must be positive and increasing"),
    ("coef", np.zeros((3, 1, 2, 3)), "shapes do not agree"),
    ("patches", np.array([[0.0, 0.3], [0.35, 0.5]]), "slip patches: .*each overlapping the next"),
    ("features", np.array(["rms", "no_such_feature", "onset"]), "unknown feature"),
    ("meta", np.array("{not json"), "malformed inverse model"),
])
def test_malformed_model_file_names_the_file_and_the_fault(fitted, tmp_path, field, value, message):
    fitted.save(tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as z:
        doc = {k: z[k] for k in z.files}
    doc[field] = value
    path = tmp_path / "broken.npz"
    np.savez(path, **doc)
    with pytest.raises(InverseModelError, match=rf"broken\.npz: .*{message}"):
        load_inverse_model(path)


def test_shipped_model_is_the_current_format_and_covers_the_envelope():
    m = load_inverse_model()
    lo, hi = m.covered_range("omega")
    assert m.node_omegas[0] <= lo and hi <= m.node_omegas[-1] and lo <= 0.3 and hi >= 1.2
    assert m.coef.shape == (m.node_omegas.size, m.patches.shape[0], m.terms.shape[0], len(m.features))
    assert m.n_legs == 4 and np.isfinite(m.meta["fit_level"]) and m.meta["fit_level"] > 0


def test_whitener_whitens_the_model_covariance():
    """``whitener(R)``: ``W W^T = R^-1``, lower triangular, and residuals drawn with ``R`` come out with identity
    covariance (the shipped model's ``R``, which the grid tables, the calibration and the tools whiten with)."""
    r = load_inverse_model().cov(0.63, 0.002)
    w = whitener(r)
    np.testing.assert_allclose(w @ w.T, np.linalg.inv(r), rtol=1e-9, atol=1e-9 * np.abs(np.linalg.inv(r)).max())
    np.testing.assert_array_equal(w, np.tril(w))
    z = np.random.default_rng(0).multivariate_normal(np.zeros(len(r)), r, size=200_000) @ w
    np.testing.assert_allclose(np.cov(z.T), np.eye(len(r)), atol=0.02)


def test_cov_knot_weights_interpolate_in_s2_and_hold_beyond_the_last_knot():
    knots = np.array([0.0, 0.005, 0.01, 0.02])
    s = np.array([0.0, 0.005, 0.0075, 0.02, 0.05])
    h = cov_knot_weights(s, knots)
    assert h.shape == (5, 4) and np.all(h >= 0) and np.allclose(h.sum(axis=1), 1.0)
    assert np.allclose(h[0], [1, 0, 0, 0]) and np.allclose(h[1], [0, 1, 0, 0])
    a = (0.0075**2 - 0.005**2) / (0.01**2 - 0.005**2)  # linear in s^2 between the knots around it
    assert np.allclose(h[2], [0, 1 - a, a, 0])
    assert np.allclose(h[3], [0, 0, 0, 1]) and np.allclose(h[4], [0, 0, 0, 1])  # the last knot's beyond it
    assert np.allclose(cov_knot_weights(0.0075, knots), h[2])


def test_a_variance_that_rises_then_falls_with_noise_is_followed_and_stays_positive():
    """A feature whose scatter first grows with the noise, then shrinks (a thresholded one saturating), with few
    rows at the largest noises as in training: the knots follow it where rows are, and stay positive definite
    and never overconfident where they are few."""
    rng = np.random.default_rng(12)
    n = 40000
    x5 = _draw(n, rng)
    x5[:, 4] = 0.02 * rng.beta(1.0, 4.0, n)  # most rows at low noise
    var = 1e-6 * (1.0 + 3.0 * (x5[:, 4] / 0.02) - 3.9 * (x5[:, 4] / 0.02) ** 2)  # 1 at 0, 0.1 at s = 0.02
    y = _truth(x5, 0) + rng.normal(0, 1, (n, 3)) * np.sqrt(var)[:, None]
    coef, cov = fit_node(x5, y, node_terms(SCHEDULE), CENTER, HALF)
    m = FeatureSurrogate(FEATS, NODES[:1], CENTER, HALF, np.vstack([np.column_stack([LO, HI]), [0.6, 0.6]]), 0.1,
                         node_terms(SCHEDULE), coef[None], cov[None], {}, {}, None, default_cov_knots(CENTER, HALF))
    for s in (0.0, 0.01, 0.02):
        want = 1e-6 * (1.0 + 3.0 * (s / 0.02) - 3.9 * (s / 0.02) ** 2)
        got = np.diag(m.cov(0.6, s))
        assert np.linalg.eigvalsh(m.cov(0.6, s)).min() > 0.01 * want
        if s < 0.02:  # where rows are plenty: the variance itself
            assert np.allclose(got, want, rtol=0.35), (s, got, want)
        else:  # at the last knot, ~160 rows: never below it by half (not overconfident); at worst the average
            # of its knot's neighbourhood, where the variance is up to ten times larger
            assert np.all((got > 0.5 * want) & (got < 10 * want)), (s, got, want)
    assert np.allclose(m.cov(0.6, 0.05), m.cov(0.6, 0.02))  # beyond the last knot: the last knot's


def test_bad_noise_knots_are_refused_by_name(fitted):
    from dataclasses import replace
    for bad in ([0.0], [0.001, 0.01], [0.0, 0.01, 0.005], [0.0, np.nan]):
        with pytest.raises(InverseModelError, match="covariance knots"):
            replace(fitted, cov_knots=np.array(bad))
    with pytest.raises(InverseModelError, match="shapes do not agree"):
        replace(fitted, cov_knots=np.array([0.0, 0.01, 0.02]))  # three knots for five matrices


def test_a_format_4_file_keeps_its_straight_line_in_s2(fitted, tmp_path):
    path = save_inverse_model(fitted, tmp_path / "m.npz")
    with np.load(path) as z:
        doc = {k: z[k] for k in z.files if k != "cov_knots"}
    d = len(FEATS)
    a, b = 1e-6 * np.eye(d), 1e-2 * np.eye(d)
    doc["format_version"] = np.array(4)
    doc["cov_coef"] = np.stack([np.stack([a, b])] * len(NODES))
    np.savez(tmp_path / "v4.npz", **doc)
    old = load_inverse_model(tmp_path / "v4.npz")
    assert old.cov_knots is None
    np.testing.assert_allclose(old.cov(0.6, 0.01), a + 0.01**2 * b, rtol=1e-12)


def test_the_shipped_covariance_is_positive_definite_at_every_speed_and_trained_noise():
    """No eigenvalue needs the floor of ``cov`` (taken in the features' own scales, on the correlation matrix):
    the knots' matrices are positive definite and their weights non-negative (the format-4 line in s^2 went
    indefinite above 0.011 g of smoothed noise)."""
    m = load_inverse_model()
    assert m.cov_knots is not None and m.cov_knots[-1] == pytest.approx(m.center[4] + m.halfwidth[4])
    for omega in np.geomspace(m.node_omegas[0], m.node_omegas[-1], 9):
        for s in np.linspace(0.0, m.cov_knots[-1], 8):
            h = cov_knot_weights(s, m.cov_knots)
            raw = sum(w * np.tensordot(h, m.cov_coef[k], axes=1) for k, w in m.node_weights(omega))
            raw = 0.5 * (raw + raw.T)
            d = np.sqrt(np.diag(raw))
            ev = np.linalg.eigvalsh(raw / np.outer(d, d))
            assert ev.min() > 1e-6 * ev.max(), (omega, s)
            np.testing.assert_allclose(m.cov(omega, s), raw, rtol=1e-9, atol=0)  # the floor left it as it is


@pytest.mark.parametrize("rate, noise", [(1000.0, 0.01), (200.0, 0.03)])
def test_held_out_stances_whiten_to_the_number_of_features_even_at_the_noisiest_imu(rate, noise):
    """Simulated stances over the covered domain at 0.6-0.66 rad/s: the mean squared whitened residual from
    the shipped model is about the number of modelled features (20), at an ordinary IMU and at the corner of
    the envelope (200 Hz, 0.03 g: about 2e6 with the format-4 covariance)."""
    from slipest.features import INDEX
    from slipest.inverse.simdata import draw_envelope, simulate_features
    m = load_inverse_model()
    env = {"slip": (0.0, 0.5), "kS": (500.0, 1500.0), "phiS": (0.1, 0.8), "dphi": (0.0, 0.35), "omega": (0.6, 0.66)}
    x = draw_envelope(1500, np.random.default_rng(21), env, phid_min=0.1)
    rows = simulate_features(x, rate, noise, np.random.default_rng(22))
    f = m.observe(rows)
    ok = np.all(np.isfinite(f), axis=1)
    ns = rows[ok, INDEX["noise_smooth"]]
    r = f[ok] - m.mean(np.column_stack([x[ok], ns]))
    w = whitener(m.cov(0.63, float(np.median(ns))))
    d2 = np.sum((r @ w) ** 2, axis=1)
    assert 0.6 * len(m.features) < d2.mean() < 1.4 * len(m.features), d2.mean()


def test_the_positive_definite_floor_keeps_small_variances_of_features_in_other_units():
    """Features whose variances differ by 1e7 (rad^2 against Hz^2): a positive definite matrix comes back as it is,
    and an indefinite one is mended in the features' own scales, every variance kept to within the floor."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    scale = np.diag([1e-4, 1e-3, 1.0, 10.0, 1e-2, 3.0])
    m = scale @ (a @ a.T) @ scale
    np.testing.assert_allclose(nearest_positive_definite(m), m, rtol=1e-9, atol=0)
    bad = m.copy()
    bad[0, 1] = bad[1, 0] = 2.0 * math.sqrt(m[0, 0] * m[1, 1])  # correlation 2: indefinite
    fixed = nearest_positive_definite(bad)
    d = np.sqrt(np.diag(fixed))
    assert np.linalg.eigvalsh(fixed / np.outer(d, d)).min() > 0.0
    np.testing.assert_allclose(np.diag(fixed)[2:], np.diag(m)[2:], rtol=0.5)
    assert fixed[0, 0] < 1e-6  # the rad^2-sized variance is not raised to a floor set by the Hz^2 one
