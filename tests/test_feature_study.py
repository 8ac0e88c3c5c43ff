"""The smooth moment features (spec_cent, spec_bw, spec_skew, spec_cent2, e_cent, e_spread): what they mean, the
compiled kernel equal to a plain numpy reference; tools/feature_study.py runs end to end."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slipest.features import FEATURE_NAMES, N_GRID, SPECTRAL_BAND, STICK_FRACTION, cycle_features
from slipest.inverse.simdata import draw_envelope, simulate_features
from slipest.units import G

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import feature_study as FS  # noqa: E402

HALF = math.pi / 4


def reference_moments(features, grids, omega, half):
    """The moments by numpy (FFT) from the smoothed signal, as slipest.features documents them."""
    g = np.asarray(grids, dtype=float)
    n_grid = g.shape[1]
    dphase = half / n_grid
    phase = (np.arange(n_grid) + 0.5) * dphase
    sig = features[:, FEATURE_NAMES.index("noise_smooth")]
    n_stick = max(2, int(round(STICK_FRACTION * n_grid)))
    e = np.maximum((g - g[:, :n_stick].mean(1, keepdims=True)) ** 2 - sig[:, None] ** 2, 0.0)
    et = np.maximum(e.sum(1), 1e-300)
    e_cent = (e * phase).sum(1) / et
    e_spread = np.sqrt((e * (phase - e_cent[:, None]) ** 2).sum(1) / et)

    def spectrum(part):
        m = part.shape[1]
        power = np.abs(np.fft.rfft((part - part.mean(1, keepdims=True)) * np.hanning(m), axis=1)) ** 2
        freq = np.fft.rfftfreq(m, dphase / omega)
        band = (freq >= SPECTRAL_BAND[0]) & (freq <= SPECTRAL_BAND[1])
        return power[:, band], freq[band]

    p, f = spectrum(g)
    cent = (p * f).sum(1) / p.sum(1)
    bw = np.sqrt((p * (f - cent[:, None]) ** 2).sum(1) / p.sum(1))
    skew = np.cbrt((p * (f - cent[:, None]) ** 3).sum(1) / p.sum(1))
    p2, f2 = spectrum(g[:, n_grid // 2:])
    cent2 = (p2 * f2).sum(1) / p2.sum(1)
    return {"e_cent": e_cent, "e_spread": e_spread, "spec_cent": cent, "spec_bw": bw, "spec_skew": skew,
            "spec_cent2": cent2}


def _features_of_grids(grids, omega, noise_smooth=0.0):
    """Feature rows of signals given directly on the phase grid (one sample per grid bin, noise given)."""
    n_grid = grids.shape[1]
    phase = (np.arange(n_grid) + 0.5) * (HALF / n_grid)
    return np.stack([cycle_features(phase, row * G, omega=omega, noise=noise_smooth) for row in grids])


def test_spectral_centroid_of_a_sine_is_its_frequency():
    omega = 0.63
    t = (np.arange(N_GRID) + 0.5) * (HALF / N_GRID) / omega  # seconds
    grids = np.stack([1.0 + 0.3 * np.sin(2 * np.pi * hz * t) for hz in (4.0, 7.0)])
    f = _features_of_grids(grids, omega)
    assert f[:, FEATURE_NAMES.index("spec_cent")] == pytest.approx([4.0, 7.0], abs=0.3)
    assert np.all(f[:, FEATURE_NAMES.index("spec_bw")] < 1.0)
    assert f[:, FEATURE_NAMES.index("spec_cent2")] == pytest.approx([4.0, 7.0], abs=0.5)  # its half: the same sine
    flat = _features_of_grids(np.ones((1, N_GRID)), omega)[0]
    for name in ("spec_cent", "spec_bw", "spec_skew", "spec_cent2"):
        assert flat[FEATURE_NAMES.index(name)] == 0.0, name


def test_spectral_skew_says_which_side_the_power_leans_to_and_the_second_half_centroid_which_half_has_it():
    omega = 0.63
    t = (np.arange(N_GRID) + 0.5) * (HALF / N_GRID) / omega  # seconds
    low, high = np.sin(2 * np.pi * 4.0 * t), np.sin(2 * np.pi * 12.0 * t)
    grids = np.stack([1.0 + 0.3 * low + 0.1 * high,  # most power low, a little high: leans up (positive skew)
                      1.0 + 0.1 * low + 0.3 * high,  # the reverse
                      1.0 + np.where(t > t[-1] / 2, 0.3 * high, 0.3 * low)])  # 4 Hz first half, 12 Hz second half
    f = _features_of_grids(grids, omega)
    skew = f[:, FEATURE_NAMES.index("spec_skew")]
    assert skew[0] > 1.0 and skew[1] < -1.0
    assert f[2, FEATURE_NAMES.index("spec_cent2")] == pytest.approx(12.0, abs=1.0)
    assert f[2, FEATURE_NAMES.index("spec_cent")] < 10.0  # the whole window: both


def test_energy_moments_follow_where_the_energy_is():
    phase = (np.arange(N_GRID) + 0.5) * (HALF / N_GRID)
    g = np.ones((3, N_GRID))
    g[0, (phase > 0.5) & (phase < 0.52)] += 0.5  # a burst at 0.51 rad
    g[1, phase > 0.4] += 0.2 * np.sin(40 * phase[phase > 0.4])  # energy spread over 0.4-0.785 rad
    f = _features_of_grids(g, 0.63, noise_smooth=0.001)
    cent, spread = f[:, FEATURE_NAMES.index("e_cent")], f[:, FEATURE_NAMES.index("e_spread")]
    assert cent[0] == pytest.approx(0.51, abs=0.01)
    assert spread[0] < 0.02
    assert 0.5 < cent[1] < 0.7 and spread[1] > 0.05
    assert cent[2] == 0.0 and spread[2] == 0.0  # nothing above the noise


def test_simulated_grids_are_what_the_features_are_taken_on():
    x = draw_envelope(200, np.random.default_rng(3))
    plain = simulate_features(x, 500.0, 0.01, np.random.default_rng(9))
    feats, grids = simulate_features(x, 500.0, 0.01, np.random.default_rng(9), grids=True)
    np.testing.assert_array_equal(plain, feats)  # asking for the grids changes no feature
    assert grids.shape == (200, N_GRID)
    n_stick = int(round(STICK_FRACTION * N_GRID))
    peak = (grids - grids[:, :n_stick].mean(1, keepdims=True)).max(1)
    ok = np.isfinite(feats[:, 0])
    assert ok.sum() > 150
    np.testing.assert_allclose(peak[ok], feats[ok, FEATURE_NAMES.index("peak_pos")], atol=1e-12)
    assert np.all(np.isnan(grids[~ok]))


@pytest.mark.parametrize("omega, rate", [(0.3, 2000.0), (0.63, 1000.0), (1.2, 200.0)])
def test_compiled_moments_equal_the_numpy_reference(omega, rate):
    x = draw_envelope(150, np.random.default_rng(4))
    x[:, 4] = omega
    feats, grids = simulate_features(x, rate, 0.02, np.random.default_rng(8), grids=True)
    ok = np.isfinite(feats[:, 0])
    ref = reference_moments(feats[ok], grids[ok], omega, HALF)
    for name, v in ref.items():
        np.testing.assert_allclose(feats[ok, FEATURE_NAMES.index(name)], v, rtol=1e-9, atol=1e-12, err_msg=name)


def test_a_small_study_runs_and_prints_every_set(tmp_path):
    out = tmp_path / "fs.json"
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "feature_study.py"), "--train", "3000", "--test", "1000",
                        "--soils", "8", "--slips", "6", "--degree", "4", "--json", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    figures = json.loads(out.read_text())
    assert set(figures) == set(FS.FEATURE_SETS)
    for label, f in figures.items():
        assert label in r.stdout
        assert set(f["rmse"]) == {"0.15", "0.4", "1.0", "known"}
        assert all(0.0 <= v < 0.5 for v in f["rmse"].values())


def test_bad_sizes_are_usage_errors(capsys):
    # refused as the arguments are parsed: the tool's main in this process (no new interpreter's start-up)
    with pytest.raises(SystemExit) as exc:
        FS.main(["--soils", "0"])
    assert exc.value.code == 2 and "--soils must be >= 1" in capsys.readouterr().err
