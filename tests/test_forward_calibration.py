"""Tests of tools/forward_calibration.py: the forward calibration (Da as a function of slip and soil) and its inverse."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from slipest import calibration as C

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import forward_calibration as F  # noqa: E402

from tests.test_calibration import _soils  # noqa: E402


def _forward_table(slips=np.linspace(0.0, 0.5, 6)):
    """Da generated exactly as alpha + beta * i with alpha, beta planes in (dphi, kS)."""
    ks, phis, phid = _soils()
    s = np.repeat(slips, ks.size)
    k, ps, pd = np.tile(ks, slips.size), np.tile(phis, slips.size), np.tile(phid, slips.size)
    d = ps - pd
    alpha = 0.02 + 1.5 * d + 1e-4 * k
    beta = 0.3 + 3.0 * d + 1e-3 * k
    return s, k, ps, pd, alpha + beta * s


def test_forward_planes_recover_coefficients_and_invert():
    slip, ks, phis, phid, da = _forward_table()
    model, info = F.fit_forward_surfaces(slip, ks, phis, phid, da, degree=1, use_phiS=False)
    assert info["alpha_plane"] == pytest.approx({"const": 0.02, "dphi": 1.5, "kS": 1e-4}, rel=1e-8, abs=1e-10)
    assert info["beta_plane"] == pytest.approx({"const": 0.3, "dphi": 3.0, "kS": 1e-3}, rel=1e-8, abs=1e-10)
    assert info["r2_alpha"] == pytest.approx(1.0) and info["r2_beta"] == pytest.approx(1.0)
    assert model.kind == "linear-in-slip"
    assert np.allclose(F.forward_da(model, slip, ks, phis, phid), da)
    assert np.allclose(F.invert_slip(model, da, ks, phis, phid), slip, atol=1e-10)


def test_compare_and_select_prefers_simplest_exact_model():
    slip, ks, phis, phid, da = _forward_table()
    cands = F.compare_forward(slip, ks, phis, phid, da, candidates=F.DEFAULT_CANDIDATES[:4])
    planes = cands[0]
    assert planes.r2_da == pytest.approx(1.0) and planes.rmse_slip < 1e-9 and planes.rmse_slip_cv < 1e-9
    assert planes.monotone_fraction == 1.0 and planes.identifiable
    assert F.select_forward(cands) is planes


def test_select_forward_skips_inadmissible_candidates():
    def cand(n, rmse, ident=True, mono=1.0):
        m = F.ForwardModel(f"m{n}", ((0, 0, 0, 0),) * n, np.zeros(n), np.zeros(4), np.ones(4))
        return F.ForwardCandidate(m, n, ident, mono, 1, 0.1, 1, 0.1, rmse, rmse)

    simple_bad = cand(4, 0.10, mono=0.9)  # best RMSE but not invertible everywhere
    rank_def = cand(6, 0.10, ident=False)
    ok_big = cand(20, 0.11)
    ok_bigger = cand(30, 0.108)
    assert F.select_forward([simple_bad, rank_def, ok_big, ok_bigger]) is ok_big
    with pytest.raises(ValueError, match="admissible"):
        F.select_forward([simple_bad, rank_def])


def test_polynomial_inversion_round_trips_and_clips():
    # Da = 0.1 + 1.0 u + 0.5 u^2 (monotone on [0, 0.55]) + 0.2 * dphi_u
    model = F.ForwardModel(
        "test",
        ((0, 0, 0, 0), (1, 0, 0, 0), (2, 0, 0, 0), (0, 1, 0, 0)),
        np.array([0.1, 1.0, 0.5, 0.2]),
        np.array([0.0, 0.175, 1000.0, 0.5]),
        np.array([1.0, 0.175, 500.0, 0.25]),
    )
    assert model.kind == "polynomial"
    slip = np.linspace(0.0, 0.55, 23)
    ks, phis, phid = 800.0, 0.5, 0.3
    da = F.forward_da(model, slip, ks, phis, phid)
    assert np.allclose(F.invert_slip(model, da, ks, phis, phid), slip, atol=2e-6)
    lo, hi = model.slip_clip
    assert F.invert_slip(model, np.array([-5.0, 50.0]), ks, phis, phid) == pytest.approx([lo, hi])
    assert np.isnan(F.invert_slip(model, np.nan, ks, phis, phid))


def test_linear_inversion_clips_and_vectorises():
    slip, ks, phis, phid, da = _forward_table()
    model, _ = F.fit_forward_surfaces(slip, ks, phis, phid, da)
    out = F.invert_slip(model, np.array([[-1.0], [100.0]]), ks[:3], phis[:3], phid[:3])
    assert out.shape == (2, 3)
    assert np.all(out[0] == model.slip_clip[0]) and np.all(out[1] == model.slip_clip[1])
    raw = F.invert_slip(model, 100.0, ks[0], phis[0], phid[0], clip=False)
    assert raw > model.slip_clip[1]


def test_shipped_forward_model_round_trips_inside_its_box():
    cal = C.load_calibration()
    g = cal["grid"]
    rng = np.random.default_rng(7)
    n = 500
    ks = rng.uniform(min(g["kS"]), max(g["kS"]), n)
    phid = rng.uniform(min(g["phiD"]), max(g["phiD"]), n)
    phis = phid + rng.uniform(min(g["dphi"]), max(g["dphi"]), n)
    slip = rng.uniform(0.0, max(g["slip"]), n)
    assert F.soil_in_range(cal, ks, phis, phid).all()
    assert not F.soil_in_range(cal, 5000.0, 0.5, 0.3)
    da = F.forward_da(cal, slip, ks, phis, phid)
    assert np.all(np.isfinite(da))
    back = F.invert_slip(cal, da, ks, phis, phid)
    assert np.allclose(back, slip, atol=1e-4)



def test_shipped_file_carries_a_consistent_forward_section():
    cal = C.load_calibration()
    F.check_forward_section(cal)
    names = [c["name"] for c in cal["forward"]["candidates"]]
    assert cal["forward"]["name"] in names
    bad = dict(cal, forward=dict(cal["forward"], coef=cal["forward"]["coef"][:-1]))
    with pytest.raises(C.CalibrationError, match="one coefficient"):
        F.check_forward_section(bad)
