"""tools/feature_study.py: the candidate features mean what its docstring says, and a small study runs end to end."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slipest.features import FEATURE_NAMES, N_GRID, STICK_FRACTION
from slipest.inverse.simdata import draw_envelope, simulate_features

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import feature_study as FS  # noqa: E402

HALF = math.pi / 4


def _rows(n, noise_smooth=0.0):
    f = np.zeros((n, len(FEATURE_NAMES)))
    f[:, FEATURE_NAMES.index("noise_smooth")] = noise_smooth
    return f


def test_spectral_centroid_of_a_sine_is_its_frequency():
    omega = 0.63
    t = (np.arange(N_GRID) + 0.5) * (HALF / N_GRID) / omega  # seconds
    grids = np.stack([1.0 + 0.3 * np.sin(2 * np.pi * hz * t) for hz in (4.0, 7.0)])
    c = FS.candidate_features(_rows(2), grids, omega, HALF)
    assert c["spec_cent"] == pytest.approx([4.0, 7.0], abs=0.3)
    assert np.all(c["spec_bw"] < 1.0)


def test_energy_moments_follow_where_the_energy_is():
    phase = (np.arange(N_GRID) + 0.5) * (HALF / N_GRID)
    g = np.ones((3, N_GRID))
    g[0, (phase > 0.5) & (phase < 0.52)] += 0.5  # a burst at 0.51 rad
    g[1, phase > 0.4] += 0.2 * np.sin(40 * phase[phase > 0.4])  # energy spread over 0.4-0.785 rad
    c = FS.candidate_features(_rows(3, noise_smooth=0.01), g, 0.63, HALF)
    assert c["e_cent"][0] == pytest.approx(0.51, abs=0.01)
    assert c["e_spread"][0] < 0.02
    assert 0.5 < c["e_cent"][1] < 0.7 and c["e_spread"][1] > 0.05
    assert c["e_cent"][2] == 0.0 and c["e_spread"][2] == 0.0  # nothing above the noise


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


def test_bad_sizes_are_usage_errors():
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "feature_study.py"), "--soils", "0"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--soils must be >= 1" in r.stderr
