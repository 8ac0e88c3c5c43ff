"""Tests of slipest.inverse.eq515: thesis Eq. 5.15 exactly as stated, against hand-computed values."""

import math

import numpy as np
import pytest

from slipest.calibration import load_calibration
from slipest.features import FEATURE_NAMES, INDEX
from slipest.inverse.base import Soil
from slipest.inverse.eq515 import Eq515Inverse, Eq515Tracker

# Coefficients chosen for hand computation (not a calibration):
#   aIV = cI + cmu dphi + cK kS,  bIV = amu + bmu dphi,  i = aIV + bIV Da
COEF = dict(amu=1.2, bmu=-3.0, cI=-0.1, cmu=0.05, cK=1e-5, slip_std=0.07)


def row(da):
    f = np.zeros(len(FEATURE_NAMES))
    f[INDEX["delta_a"]] = da
    return f


def test_slip_from_da_hand_computed():
    inv = Eq515Inverse(**COEF)
    # Da = 1.0 g, dphi = 0.2 rad, kS = 1000 N/m:
    # aIV = -0.1 + 0.05*0.2 + 1e-5*1000 = -0.08 ; bIV = 1.2 - 3*0.2 = 0.6 ; i = -0.08 + 0.6*1.0 = 0.52
    assert inv.slip_from_da(1.0, 0.2, 1000.0) == pytest.approx(0.52, abs=1e-12)
    # Da = 0.5 g, dphi = 0, kS = 500 N/m: aIV = -0.1 + 0.005 = -0.095 ; bIV = 1.2 ; i = -0.095 + 0.6 = 0.505
    assert inv.slip_from_da(0.5, 0.0, 500.0) == pytest.approx(0.505, abs=1e-12)
    # broadcasting over Da
    np.testing.assert_allclose(inv.slip_from_da(np.array([1.0, 0.5]), 0.2, 1000.0), [0.52, -0.08 + 0.3], atol=1e-12)


def test_dphi_from_da_hand_computed_and_round_trip():
    inv = Eq515Inverse(**COEF)
    # dphi = (i - cI - cK kS - amu Da) / (cmu + bmu Da) = (0.52 + 0.1 - 0.01 - 1.2) / (0.05 - 3.0) = 0.2
    assert inv.dphi_from_da(1.0, 0.52, 1000.0) == pytest.approx(0.2, abs=1e-12)
    for da, dphi, ks in ((0.3, 0.05, 600.0), (1.7, 0.33, 1400.0)):
        s = inv.slip_from_da(da, dphi, ks)
        assert inv.dphi_from_da(da, s, ks) == pytest.approx(dphi, abs=1e-12)
    # cmu + bmu Da = 0 at Da = 0.05/3: Da says nothing about dphi there
    assert math.isnan(float(inv.dphi_from_da(0.05 / 3.0, 0.2, 1000.0)))
    assert math.isinf(float(inv.dphi_std(0.05 / 3.0)))
    # std propagation: slip_std / |cmu + bmu Da| = 0.07 / 2.95
    assert inv.dphi_std(1.0) == pytest.approx(0.07 / 2.95)


def test_slip_interface_reads_delta_a_and_needs_soil():
    inv = Eq515Inverse(**COEF)
    s, sd = inv.slip(row(1.0), Soil.from_args(kS=1000.0, dphi=0.2))
    assert s == pytest.approx(0.52) and sd == 0.07
    # phiS and phiD give dphi too
    s2, _ = inv.slip(row(1.0), Soil(kS=1000.0, phiS=0.5, phiD=0.3))
    assert s2 == pytest.approx(0.52)
    with pytest.raises(ValueError, match="dphi"):
        inv.slip(row(1.0), Soil(kS=1000.0))
    with pytest.raises(ValueError, match="kS"):
        inv.slip(row(1.0), None)
    assert all(math.isnan(v) for v in inv.slip(row(math.nan), Soil.from_args(kS=1000.0, dphi=0.2)))
    s_b, sd_b = inv.slip_batch(np.stack([row(1.0), row(0.5)]), Soil.from_args(kS=1000.0, dphi=0.2))
    np.testing.assert_allclose(s_b, [0.52, 0.22], atol=1e-12)
    np.testing.assert_allclose(sd_b, [0.07, 0.07])


def test_from_shipped_calibration_uses_its_coefficients():
    cal = load_calibration()
    inv = Eq515Inverse.from_calibration(cal)
    c = cal["eq515"]
    assert inv.coefficients() == {k: c[k] for k in ("amu", "bmu", "cI", "cmu", "cK")}
    assert inv.slip_std == c["rmse_end_to_end"]
    da, dphi, ks = 1.1, 0.17, 900.0
    expect = (c["cI"] + c["cmu"] * dphi + c["cK"] * ks) + (c["amu"] + c["bmu"] * dphi) * da
    assert inv.slip_from_da(da, dphi, ks) == pytest.approx(expect, abs=1e-12)


def test_bad_coefficients_refused():
    with pytest.raises(ValueError):
        Eq515Inverse(**{**COEF, "amu": math.nan})
    with pytest.raises(ValueError):
        Eq515Inverse(**{**COEF, "slip_std": 0.0})


def test_tracker_learns_dphi_from_reference_slips():
    inv = Eq515Inverse(**COEF)
    true_dphi, ks = 0.25, 1000.0
    tr = Eq515Tracker(inv, Soil(kS=ks), use_reference=True, dphi0=0.1, dphi0_std=0.1, q=1e-6)
    rng = np.random.default_rng(0)
    stds = []
    for _ in range(40):
        da = rng.uniform(0.5, 1.8)
        ref = float(inv.slip_from_da(da, true_dphi, ks))
        slip, slip_std, dphi, dstd, used = tr.step(da, ref)
        assert used
        stds.append(dstd)
    assert tr.dphi == pytest.approx(true_dphi, abs=0.01)
    assert stds[-1] < stds[0]
    # the slip of a cycle without a reference now follows Eq. 5.15 at the learnt dphi
    slip, slip_std, _, _, used = tr.step(1.0, None)
    assert not used
    assert slip == pytest.approx(float(inv.slip_from_da(1.0, tr.dphi, ks)))
    assert slip_std >= inv.slip_std


def test_tracker_without_references_keeps_prior_and_grows_uncertain():
    inv = Eq515Inverse(**COEF)
    tr = Eq515Tracker(inv, Soil(kS=1000.0), use_reference=True, dphi0=0.175, dphi0_std=0.05, q=1e-4)
    for _ in range(10):
        tr.step(1.0, None)
    assert tr.dphi == pytest.approx(0.175)
    assert tr.dphi_std == pytest.approx(math.sqrt(0.05**2 + 10 * 1e-4))


def test_tracker_with_known_dphi_ignores_references():
    inv = Eq515Inverse(**COEF)
    tr = Eq515Tracker(inv, Soil.from_args(kS=1000.0, dphi=0.2), use_reference=True)
    slip, slip_std, dphi, dstd, used = tr.step(1.0, 0.9)
    assert not used
    assert (slip, dphi, dstd) == (pytest.approx(0.52), 0.2, 0.0)
    assert slip_std == pytest.approx(0.07)


def test_tracker_is_a_cycle_estimator_on_feature_rows():
    inv = Eq515Inverse(**COEF)
    tr = Eq515Tracker(inv, Soil.from_args(kS=1000.0, phiS=0.5, dphi=0.2))
    row = np.zeros(len(FEATURE_NAMES))
    row[INDEX["delta_a"]] = 1.0
    est = tr.update(row, 0.9)
    assert est.slip == pytest.approx(0.52) and est.dphi == pytest.approx(0.2) and est.dphi_std == 0.0
    assert (est.kS, est.kS_std, est.phiS, est.phiD) == (1000.0, 0.0, 0.5, pytest.approx(0.3))
    assert math.isnan(est.change_prob) and not est.used_reference
    row[INDEX["delta_a"]] = math.nan
    with pytest.raises(ValueError, match="Da"):
        tr.update(row)


def test_tracker_needs_kS_and_dphi_or_references():
    inv = Eq515Inverse(**COEF)
    with pytest.raises(ValueError, match="kS"):
        Eq515Tracker(inv, Soil.from_args(dphi=0.2))
    with pytest.raises(ValueError, match="use_reference"):
        Eq515Tracker(inv, Soil.from_args(kS=1000.0))
