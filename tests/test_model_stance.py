"""The stick-slip stance simulator against the reference values of docs/model.md and physics sanity."""

import math

import numpy as np
import pytest

from slipest.model import kernel as K
from slipest.model.params import StickSlipParams, param_grid, param_matrix
from slipest.model.stance import ModelFailure, simulate_batch, simulate_stance

# docs/model.md section 4: (changes from defaults, Da [g], first break-away [rad]), given to 3 decimals
REFERENCE = [
    (dict(slip=0.5), 1.505, 0.167),
    (dict(slip=0.25), 1.179, 0.273),
    (dict(slip=0.125), 0.684, 0.399),
    (dict(kS=1500.0), 1.567, 0.207),
    (dict(kS=500.0), 0.738, 0.399),
    (dict(phiS=0.70, phiD=0.30), 1.518, 0.392),
    (dict(phiS=0.52, phiD=0.30), 1.109, 0.273),
    (dict(phiS=0.35, phiD=0.30), 0.738, 0.175),
]


@pytest.mark.parametrize("changes, da_ref, breakaway_ref", REFERENCE)
def test_reference_values_within_a_tenth_of_a_percent(changes, da_ref, breakaway_ref):
    # measured: Da within 0.075% (kS = 1.5 kN/m), break-away within 0.0005 rad (the rounding of the table)
    r = simulate_stance(StickSlipParams(**changes))
    assert r.delta_a_g == pytest.approx(da_ref, rel=0.001)
    assert r.breakaway_theta == pytest.approx(breakaway_ref, abs=0.001)


def test_stance_covers_midstance_to_pi_over_nl():
    r = simulate_stance()
    assert r.theta[0] == 0.0
    assert len(r.t) == 12467  # ceil((pi/4) / (0.63 rad/s * 1e-4 s)) steps a stance
    assert r.theta[-1] < math.pi / 4 <= r.theta[-1] + 0.63 * 1e-4 + 1e-12


def test_static_equilibrium_at_midstance():
    p = StickSlipParams()
    r = simulate_stance(p)
    assert r.az[0] == pytest.approx(0.0, abs=1e-9)
    assert r.FS[0] == pytest.approx(p.MH * p.g, rel=1e-9)  # the spring carries the weight
    assert r.FN[0] == pytest.approx(p.MH * p.g, rel=1e-9)
    assert r.FE[0] == pytest.approx(0.0, abs=1e-9)
    assert r.stick[0] and r.contact[0]


def test_no_stick_slip_at_zero_slip():
    r = simulate_stance(StickSlipParams(slip=0.0))
    assert r.delta_a_g < 0.03  # about 0.015 g: rigid-spoke motion (docs/model.md section 3)
    assert r.delta_a_g < simulate_stance(StickSlipParams(slip=0.125)).delta_a_g / 10


def test_vertical_force_balance_while_in_contact():
    r = simulate_stance()
    p = r.params
    # MH zH'' = FN - MH g (Eq. 5.14, z up) wherever the foot is loaded
    np.testing.assert_allclose(p.MH * r.az[r.contact], r.FN[r.contact] - p.MH * p.g, atol=1e-9)


def test_friction_cone_respected_while_sticking():
    p = StickSlipParams()
    r = simulate_stance(p)
    s = r.stick & r.contact
    assert np.all(np.abs(r.FE[s]) <= p.muS * r.FN[s] + 1e-9)


@pytest.mark.parametrize("changes", [dict(), dict(slip=0.0), dict(kS=500.0), dict(phiS=0.7, phiD=0.3)])
def test_literal_model_kappa_zero_is_reported_not_returned(changes):
    with pytest.raises(ModelFailure) as err:
        simulate_stance(StickSlipParams(kappa=0.0, **changes))
    assert "ill-posed" in str(err.value) and "kappa" in str(err.value)
    assert err.value.status == K.STATUS_ILL_POSED


def test_literal_model_failure_in_batch_is_flagged_or_raised():
    ps = [StickSlipParams(), StickSlipParams(kappa=0.0)]
    with pytest.raises(ModelFailure, match="parameter set #1"):
        simulate_batch(ps)
    b = simulate_batch(ps, on_error="flag")
    assert list(b.status) == [K.STATUS_OK, K.STATUS_ILL_POSED]
    assert math.isfinite(b.delta_a_g[0]) and math.isnan(b.delta_a_g[1])


def test_hub_below_ground_is_reported():
    # a soil so soft that the hub's static sinkage nearly reaches the spoke length
    p = StickSlipParams(kS=60.0, MH=1.0, kappa=0.3, slip=0.5)
    with pytest.raises(ModelFailure, match="below the ground|runaway"):
        simulate_stance(p)


def test_batch_equals_single():
    ps = param_grid(slip=[0.0, 0.2, 0.45], kS=[[600.0], [1400.0]], phiS=0.6, phiD=0.3)
    b = simulate_batch(ps, waveforms=True)
    for j, p in enumerate(ps):
        s = simulate_stance(p)
        assert b.delta_a[j] == s.delta_a
        assert (b.breakaway_theta[j] == s.breakaway_theta) or (math.isnan(b.breakaway_theta[j]) and math.isnan(s.breakaway_theta))
        n = b.n_steps[j]
        np.testing.assert_array_equal(b.az[j, :n], s.az)
        assert np.all(np.isnan(b.az[j, n:]))


def test_halving_the_step_changes_da_by_less_than_half_a_percent():
    ps = [StickSlipParams(**c) for c, _, _ in REFERENCE]
    coarse = simulate_batch(ps, dt=1e-4).delta_a
    fine = simulate_batch(ps, dt=5e-5).delta_a
    assert np.max(np.abs(fine / coarse - 1)) < 0.005


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(slip=1.2), "slip"),
        (dict(kS=-1.0), "kS"),
        (dict(phiS=0.3, phiD=0.4), "friction angles"),
        (dict(nL=1), "nL"),
        (dict(kS=50.0), "sinkage"),
    ],
)
def test_invalid_parameters_are_rejected_with_the_reason(changes, message):
    with pytest.raises(ValueError, match=message):
        StickSlipParams(**changes)


def test_batch_pairs_equal_single_stances_to_the_last_bit():
    # integrate_batch runs stances two by two in one loop: every element must equal its own
    # integrate_stance run, whatever its partner (other lengths, extensions on, failures, odd batch)
    rng = np.random.default_rng(11)
    n = 15
    phid = rng.uniform(0.1, 0.4, n)
    mat = param_matrix(param_grid(slip=rng.uniform(0, 0.5, n), kS=rng.uniform(400, 1500, n), phiD=phid,
                                  phiS=phid + rng.uniform(0, 0.35, n), omega=rng.uniform(0.3, 1.2, n),
                                  kappa=rng.choice([0.0, 0.3], n)))
    mat[::3, K.P_BHC], mat[::3, K.P_NHC] = 20.0, 1.2
    mat[1::4, K.P_VS], mat[1::4, K.P_VISC] = 0.01, 0.5
    mat[2::5, K.P_RIPPLE_A], mat[2::5, K.P_RIPPLE_H] = 0.1, 2.0
    max_steps = int(np.ceil(np.max(np.pi / mat[:, K.P_NL] / mat[:, K.P_OMEGA]) / (0.9 * 1e-4))) + 2
    res = K.empty_results(n)
    rec = np.full((n, max_steps, K.N_CHANNELS), np.nan)
    K.integrate_batch(mat, 1e-4, max_steps, res, rec)
    statuses = set()
    for j in range(n):
        r1 = K.empty_results(1)[0]
        w1 = np.full((max_steps, K.N_CHANNELS), np.nan)
        K.integrate_stance(mat[j], 1e-4, max_steps, r1, w1)
        np.testing.assert_array_equal(res[j], r1)
        np.testing.assert_array_equal(rec[j], w1)
        statuses.add(int(r1[K.R_STATUS]))
    assert K.STATUS_OK in statuses and K.STATUS_ILL_POSED in statuses  # both kinds of element were paired
    assert len(set(res[:, K.R_N_STEPS])) > 2  # stances of different lengths were paired
