"""The feature surrogate's model: Legendre fit, grid table, file format."""

import json

import numpy as np
import pytest

from slipest.features import FEATURE_NAMES
from slipest.inverse.surrogate import (
    FORMAT_VERSION,
    FeatureSurrogate,
    InverseModelError,
    load_inverse_model,
    save_inverse_model,
)

FEATS = ("delta_a", "onset", "osc_freq")
RANGES = [[0.0, 0.5], [500.0, 1500.0], [0.1, 0.4], [0.0, 0.35]]


def _truth(slip, kS, phiD, dphi):
    """Three smooth 'features' of known form (cubic in the normalised variables)."""
    u = [(slip - 0.25) / 0.25, (kS - 1000) / 500, (phiD - 0.25) / 0.15, (dphi - 0.175) / 0.175]
    return np.column_stack([
        0.2 + 0.1 * u[0] ** 3 - 0.05 * u[1] * u[3],
        0.5 + 0.2 * u[0] * u[2] + 0.03 * u[1] ** 2,
        8.0 + 1.5 * u[1] - 0.4 * u[3] ** 3 + 0.2 * u[0] * u[1] * u[2],
    ])


def _training(n, rng):
    slip, kS, phiD, dphi = (rng.uniform(lo, hi, n) for lo, hi in RANGES)
    rows = np.full((n, len(FEATURE_NAMES)), np.nan)
    y = _truth(slip, kS, phiD, dphi)
    for j, f in enumerate(FEATS):
        rows[:, FEATURE_NAMES.index(f)] = y[:, j] + rng.normal(0, 1e-3, n)
    return rows, slip, kS, phiD + dphi, phiD


@pytest.fixture(scope="module")
def fitted():
    rows, slip, kS, phiS, phiD = _training(3000, np.random.default_rng(3))
    return FeatureSurrogate.fit(rows, slip, kS, phiS, phiD, features=FEATS, degree=4, ranges=RANGES)


def test_fit_recovers_a_known_polynomial_and_the_noise(fitted):
    rng = np.random.default_rng(4)
    slip, kS, phiD, dphi = (rng.uniform(lo, hi, 500) for lo, hi in RANGES)
    err = fitted.mean(slip, kS, phiD + dphi, phiD) - _truth(slip, kS, phiD, dphi)
    # noise 1e-3 on 3000 rows, 70 terms: the mean's error is about 1e-3 * sqrt(70 / 3000) = 1.5e-4 RMS
    assert np.sqrt(np.mean(err**2)) < 3e-4
    assert np.max(np.abs(err)) < 1.5e-3
    assert np.allclose(np.sqrt(np.diag(fitted.R)), 1e-3, rtol=0.1)


def test_grid_table_equals_the_pointwise_mean(fitted):
    nodes, ks, pd, dp = np.array([0.0, 0.2, 0.45]), np.array([600.0, 1400.0]), np.array([0.15, 0.3]), np.array([0.05, 0.3])
    table = fitted.table(nodes, ks, pd, dp, pad_to=1)  # (cells, slip nodes, features), whitened
    k, p, d = np.meshgrid(ks, pd, dp, indexing="ij")
    cells = np.column_stack([k.ravel(), p.ravel(), d.ravel()])
    for c, (kS, phiD, dphi) in enumerate(cells):
        want = fitted.mean(nodes, kS, phiD + dphi, phiD) @ fitted.whitener()
        assert np.allclose(table[c], want, rtol=1e-5, atol=1e-3)


def test_file_round_trip_and_old_format_refused(fitted, tmp_path):
    path = save_inverse_model(fitted, tmp_path / "m.json")
    again = load_inverse_model(path)
    x = (np.array([0.1, 0.4]), 900.0, 0.5, 0.2)
    assert np.array_equal(again.mean(*x), fitted.mean(*x))
    doc = json.loads(path.read_text())
    doc["format_version"] = 1  # monomial basis: the same numbers would mean another function
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    with pytest.raises(InverseModelError, match=rf"format_version 1 is not supported.*reads {FORMAT_VERSION}.*train_inverse"):
        load_inverse_model(old)


def test_shipped_model_is_the_current_format():
    m = load_inverse_model()
    assert m.degree >= 8 and m.terms.max() == m.degree
    assert m.coef.shape == (m.terms.shape[0], len(m.features))


def test_unreadable_or_missing_model_file_is_a_clear_error(tmp_path):
    with pytest.raises(InverseModelError, match=r"inverse model file .*nope\.json not found"):
        load_inverse_model(tmp_path / "nope.json")
    with pytest.raises(InverseModelError, match=r"inverse model file .* cannot be read"):
        load_inverse_model(tmp_path)  # a directory


@pytest.mark.parametrize("field, value, message", [
    ("terms", [[0, 0, 0, 99]], "terms must be"),
    ("halfwidth", [1.0, 0.0, 1.0, 1.0], "halfwidth must be"),
    ("coef", [[1.0, "x"]], "malformed inverse model"),
    ("center", [[0.0], [1.0, 2.0]], "malformed inverse model"),
])
def test_malformed_model_file_names_the_file_and_the_fault(fitted, tmp_path, field, value, message):
    doc = fitted.to_dict()
    doc[field] = value
    path = tmp_path / "broken.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InverseModelError, match=rf"broken\.json: .*{message}"):
        load_inverse_model(path)
