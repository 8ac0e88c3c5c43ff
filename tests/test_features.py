"""Tests of slipest.features: per-cycle features of the hub's vertical acceleration."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.features import (
    FEATURE_NAMES,
    FEATURE_UNITS,
    INDEX,
    N_GRID,
    analysis_grid,
    cycle_features,
    features_batch,
    smoothed_noise,
)
from slipest.model.params import StickSlipParams
from slipest.model.stance import simulate_batch
from slipest.units import G

OMEGA = 0.63
H = math.pi / 4


def window(rate=1000.0, omega=OMEGA, offset=0.0):
    """Phases [rad] and times [s] of 1 kHz samples over the feature window [0, pi/4)."""
    t = np.arange(offset, H / omega, 1.0 / rate)
    return omega * t, t


def burst(ph, onset=0.3, freq_hz=6.0, amp_g=0.5, omega=OMEGA):
    """Specific force [m/s^2]: 1 g at rest, then a sine of amp_g from the onset phase."""
    tau = (ph - onset) / omega
    return G + np.where(ph >= onset, amp_g * G * np.sin(2 * np.pi * freq_hz * tau), 0.0)


@pytest.mark.parametrize("rate", [200.0, 250.0, 1000.0, 2000.0])
@pytest.mark.parametrize("omega", [0.3, 0.63, 1.2])
def test_smoothed_noise_is_what_the_features_measure(rate, omega):
    """smoothed_noise (what the online layer predicts a cycle's noise_smooth from, before the cycle closes) is
    within 1 % of the noise_smooth cycle_features gives for the same sample noise, rate and leg speed."""
    t = np.arange(0.0, (math.pi / 2) / omega, 1.0 / rate)
    phase = -math.pi / 4 + omega * t
    az = G + np.random.default_rng(int(rate)).normal(0.0, 0.01 * G, t.size)
    f = cycle_features(phase, az, t, n_legs=4, noise=0.01)
    assert smoothed_noise(0.01, rate) == pytest.approx(f[INDEX["noise_smooth"]], rel=0.01)
    assert math.isnan(smoothed_noise(math.nan, rate))


def test_names_units_and_shape():
    assert len(FEATURE_NAMES) == len(FEATURE_UNITS) == len(set(FEATURE_NAMES))
    assert FEATURE_NAMES[0] == "delta_a"
    ph, t = window()
    f = cycle_features(ph, burst(ph), t)
    assert f.shape == (len(FEATURE_NAMES),)
    assert np.all(np.isfinite(f))


def test_delta_a_is_max_minus_min_of_raw_samples_in_g():
    ph, t = window()
    rng = np.random.default_rng(1)
    az = G + rng.normal(0, 0.3, ph.size)
    az[100] = G + 7.0
    az[900] = G - 5.0
    f = cycle_features(ph, az, t)
    assert f[INDEX["delta_a"]] == pytest.approx(12.0 / G, rel=1e-12)


def test_synthetic_burst_onset_frequency_and_parts():
    ph, t = window()
    f = cycle_features(ph, burst(ph, onset=0.3, freq_hz=6.0, amp_g=0.5), t)
    # the sine starts at 0 and reaches the threshold within a few ms; the onset is the centre of a bin of the
    # analysis grid (pi/nL / N_GRID wide), so it may sit up to half a bin before the true start
    assert 0.3 - 0.5 * H / N_GRID <= f[INDEX["onset"]] <= 0.3 + 0.01
    assert f[INDEX["delta_a"]] == pytest.approx(1.0, abs=0.01)
    assert f[INDEX["osc_freq"]] == pytest.approx(6.0, rel=0.05)
    assert f[INDEX["rice_freq"]] == pytest.approx(6.0, rel=0.1)
    # nothing happens in the first quarter (0 .. 0.196 rad), a lot in the last (RMS about the
    # window mean, which a sine cut mid-period moves off 0 by a little)
    assert f[INDEX["rms_q1"]] < 0.1 * f[INDEX["rms_q4"]]
    assert f[INDEX["energy_q10"]] > 0.3
    assert f[INDEX["energy_q10"]] < f[INDEX["energy_q50"]] < f[INDEX["energy_q90"]] <= H
    duration = H / OMEGA
    assert f[INDEX["zc_rate"]] == pytest.approx(f[INDEX["n_crossings"]] / duration)
    # ~ (0.785 - 0.3) / 0.63 s * 6 Hz * 2 crossings a period
    assert abs(f[INDEX["n_crossings"]] - 2 * 6.0 * (H - 0.3) / OMEGA) <= 2


def test_no_stick_slip_gives_no_onset_and_no_oscillation():
    ph, t = window()
    az = G + np.random.default_rng(2).normal(0, 0.01 * G, ph.size)
    f = cycle_features(ph, az, t)
    assert f[INDEX["onset"]] == pytest.approx(H)
    assert f[INDEX["osc_freq"]] == 0.0
    assert f[INDEX["rice_freq"]] == 0.0
    assert f[INDEX["noise"]] == pytest.approx(0.01, rel=0.15)


@settings(max_examples=25, deadline=None)
@given(bias=st.floats(-30.0, 30.0))
def test_constant_bias_changes_no_feature(bias):
    ph, t = window()
    az = burst(ph) + np.random.default_rng(3).normal(0, 0.1, ph.size)
    f0 = cycle_features(ph, az, t)
    f1 = cycle_features(ph, az + bias, t)
    np.testing.assert_allclose(f1, f0, rtol=1e-9, atol=1e-9)


def test_uneven_sampling_gives_close_features():
    ph, t = window()
    f_even = cycle_features(ph, burst(ph), t)
    rng = np.random.default_rng(4)
    t_u = np.sort(rng.uniform(0, H / OMEGA, ph.size))
    t_u[0], t_u[-1] = 0.0, H / OMEGA - 1e-4
    ph_u = OMEGA * t_u
    f_uneven = cycle_features(ph_u, burst(ph_u), t_u)
    for name in ("delta_a", "rms", "rms_q4", "peak_pos", "peak_neg"):
        assert f_uneven[INDEX[name]] == pytest.approx(f_even[INDEX[name]], rel=0.05), name
    for name in ("onset", "energy_q50"):
        assert f_uneven[INDEX[name]] == pytest.approx(f_even[INDEX[name]], abs=0.01), name
    assert f_uneven[INDEX["osc_freq"]] == pytest.approx(f_even[INDEX["osc_freq"]], rel=0.05)


def test_batch_equals_single_and_nan_rows():
    ph, t = window()
    rows = np.stack([burst(ph, onset=o, freq_hz=fr) for o, fr in ((0.2, 5.0), (0.4, 8.0), (0.5, 3.0))])
    rows[1, 500] = np.nan
    fb = features_batch(ph, rows, omega=OMEGA)
    np.testing.assert_array_equal(fb[0], cycle_features(ph, rows[0], t))
    np.testing.assert_array_equal(fb[2], cycle_features(ph, rows[2], t))
    assert np.all(np.isnan(fb[1]))
    with pytest.raises(ValueError, match="non-finite"):
        cycle_features(ph, rows[1], t)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda ph, az: (ph[::-1].copy(), az), "non-decreasing"),
        (lambda ph, az: (ph[:10], az[:10]), "at least|fewer than"),
        (lambda ph, az: (ph[ph < 0.5], az[ph < 0.5]), "end is missing"),
        (lambda ph, az: (np.where(np.arange(ph.size) == 7, np.nan, ph), az), "non-finite"),
    ],
)
def test_bad_phase_is_refused(make, match):
    ph, _ = window()
    p, a = make(ph, burst(ph))
    with pytest.raises(ValueError, match=match):
        features_batch(p, a)


def test_analysis_grid():
    g = analysis_grid(4)
    assert g.size == N_GRID and g[0] > 0 and g[-1] < H
    np.testing.assert_allclose(np.diff(g), H / N_GRID)


def test_onset_tracks_the_simulated_break_away():
    params = [StickSlipParams(slip=s, kS=k) for s, k in ((0.1, 800.0), (0.25, 1000.0), (0.45, 1400.0))]
    res = simulate_batch(params, waveforms=True)
    ph, t = window()
    for j in range(len(params)):
        m = res.n_steps[j]
        az = np.interp(ph, res.theta[j, :m], res.az[j, :m]) + G
        f = cycle_features(ph, az, t)
        assert f[INDEX["onset"]] == pytest.approx(res.breakaway_theta[j], abs=0.05)
        assert f[INDEX["delta_a"]] == pytest.approx(res.delta_a_g[j], rel=0.05)
