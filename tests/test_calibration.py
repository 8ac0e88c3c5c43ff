"""Tests of slipest.calibration: Eq. 5.15 fitting and the calibration file."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from slipest import calibration as C

# Known Eq. 5.15 coefficients (Da in g, dphi in rad, kS in N/m)
EQ = dict(amu=0.9, bmu=-1.7, cI=-0.05, cmu=0.12, cK=-2e-5)


def _soils():
    ks, phid, dphi = (a.ravel() for a in np.meshgrid([500.0, 1000.0, 1500.0], [0.2, 0.3], [0.0, 0.1, 0.2, 0.3], indexing="ij"))
    return ks, phid + dphi, phid


def _eq515_table():
    """Sweep table generated exactly from Eq. 5.15 (slip as a function of Da)."""
    ks, phis, phid = _soils()
    da_levels = np.linspace(0.1, 1.5, 7)
    rows = []
    for k, ps, pd in zip(ks, phis, phid):
        d = ps - pd
        a_iv = EQ["cI"] + EQ["cmu"] * d + EQ["cK"] * k
        b_iv = EQ["amu"] + EQ["bmu"] * d
        for da in da_levels:
            rows.append((a_iv + b_iv * da, k, ps, pd, da))
    return tuple(np.array(c) for c in zip(*rows))


def test_fit_eq515_recovers_known_coefficients():
    slip, ks, phis, phid, da = _eq515_table()
    fit = C.fit_eq515(slip, ks, phis, phid, da)
    for name, value in EQ.items():
        assert getattr(fit, name) == pytest.approx(value, rel=1e-9, abs=1e-12), name
    assert fit.soils.shape == (24, 3)
    assert np.allclose(fit.r2, 1.0)
    assert fit.r2_slope_law == pytest.approx(1.0)
    assert fit.r2_intercept_plane == pytest.approx(1.0)
    assert fit.r2_end_to_end == pytest.approx(1.0)
    assert fit.rmse_end_to_end < 1e-12
    # aIV is the intercept and bIV the slope of i(Da) (the equation, not the thesis's swapped wording)
    d = fit.soils[:, 1] - fit.soils[:, 2]
    assert np.allclose(fit.aIV, EQ["cI"] + EQ["cmu"] * d + EQ["cK"] * fit.soils[:, 0])
    assert np.allclose(fit.bIV, EQ["amu"] + EQ["bmu"] * d)
    assert np.allclose(C.eq515_slip(fit, da, phis - phid, ks), slip)


def test_fit_eq515_reports_bad_fits_honestly():
    slip, ks, phis, phid, da = _eq515_table()
    rng = np.random.default_rng(3)
    noisy = da + rng.normal(0.0, 0.3, da.size)  # Da barely related to slip
    fit = C.fit_eq515(slip, ks, phis, phid, noisy)
    assert np.nanmean(fit.r2) < 0.9
    assert fit.r2_end_to_end < 0.9
    d = fit.to_dict()
    assert d["r2_lines_mean"] == pytest.approx(float(np.mean(fit.r2)))
    assert len(d["per_soil"]["aIV"]) == 24


def test_fit_rejects_non_finite_rows():
    slip, ks, phis, phid, da = _eq515_table()
    da = da.copy()
    da[3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        C.fit_eq515(slip, ks, phis, phid, da)


# --------------------------------------------------------------------------- the shipped file


def test_shipped_calibration_loads_with_every_documented_key():
    cal = C.load_calibration()
    assert cal["format_version"] == C.FORMAT_VERSION == 1
    for section, keys in C.REQUIRED_KEYS.items():
        node = cal if section is None else cal[section]
        for key in keys:
            assert key in node, f"{section}.{key}"
    assert isinstance(cal["created_by"], str) and "calibrate.py" in cal["created_by"]
    assert cal["model"]["dt"] > 0 and cal["model"]["kappa"] == cal["model"]["params"]["kappa"]
    assert cal["grid"]["n_used"] == cal["grid"]["n_stances"] - cal["grid"]["n_failed"]
    assert len(cal["eq515"]["per_soil"]["aIV"]) == cal["grid"]["n_soils"]


def test_save_load_round_trip(tmp_path):
    cal = C.load_calibration()
    path = C.save_calibration(cal, tmp_path / "sub" / "cal.json")
    again = C.load_calibration(path)
    assert again == json.loads(json.dumps(cal))


def test_bad_version_raises_clear_error(tmp_path):
    cal = C.load_calibration()
    cal["format_version"] = 99
    path = tmp_path / "v99.json"
    path.write_text(json.dumps(cal))
    with pytest.raises(C.CalibrationError, match=r"format_version 99 is not supported.*format_version 1"):
        C.load_calibration(path)
    del cal["format_version"]
    path.write_text(json.dumps(cal))
    with pytest.raises(C.CalibrationError, match="no 'format_version'"):
        C.load_calibration(path)


def test_missing_key_and_bad_json_raise_clear_errors(tmp_path):
    cal = C.load_calibration()
    del cal["eq515"]["cK"]
    del cal["grid"]
    path = tmp_path / "missing.json"
    path.write_text(json.dumps(cal))
    with pytest.raises(C.CalibrationError, match=r"missing key\(s\): grid, eq515.cK"):
        C.load_calibration(path)
    path.write_text("{not json")
    with pytest.raises(C.CalibrationError, match="not valid JSON"):
        C.load_calibration(path)
    with pytest.raises(C.CalibrationError, match="not found"):
        C.load_calibration(tmp_path / "nope.json")


def test_statistics_helpers():
    y = np.array([1.0, 2.0, 3.0, 4.0])
    assert C.r2_score(y, y) == 1.0
    assert C.r2_score(y, np.full(4, y.mean())) == pytest.approx(0.0)
    assert C.r2_score(y, y[::-1]) < 0.0
    assert math.isnan(C.r2_score(np.ones(3), np.ones(3)))
    assert C.rmse(y, y + 2.0) == pytest.approx(2.0)
