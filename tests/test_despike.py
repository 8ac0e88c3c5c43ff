"""Isolated outliers: none found in clean cycles over the envelope, every glitch found, steps kept."""

import math

import numpy as np
import pytest

from slipest.despike import FLOOR, outliers
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.segmentation import CycleSegmenter
from slipest.units import G


def _cycles(rate, noise, omega, seed, slip=(0.05, 0.25, 0.45), soil=(1200.0, 0.7, 0.3)):
    kS, phiS, phiD = soil
    p = StickSlipParams(kS=kS, phiS=phiS, phiD=phiD).with_(omega=omega)
    s = simulate_stream(Scenario.per_cycle(p, dict(noise_g=noise, seed=seed, rate=rate), slip=list(slip)))
    seg = CycleSegmenter(window=(-math.pi / 4, math.pi / 4))
    return seg.push_many(s.t, s.az, s.theta) + seg.finish()


# the corners of the envelope: slow and fast IMUs, no noise and much, slow and fast legs, hard and soft soils
CORNERS = [(200.0, 0.0, 0.3, (500.0, 0.8, 0.1)), (200.0, 0.03, 1.2, (1500.0, 0.8, 0.45)),
           (2000.0, 0.0, 1.2, (1500.0, 0.3, 0.1)), (2000.0, 0.03, 0.3, (500.0, 0.5, 0.3)),
           (1000.0, 0.01, 0.63, (1000.0, 0.52, 0.35))]


@pytest.mark.parametrize("rate, noise, omega, soil", CORNERS)
def test_clean_cycles_have_no_outlier_and_a_glitch_is_found(rate, noise, omega, soil):
    rng = np.random.default_rng(int(rate + 1000 * noise + 10 * omega))
    cycles = _cycles(rate, noise, omega, seed=3, soil=soil)
    assert len(cycles) == 3
    for c in cycles:
        assert not outliers(c.az).any()
        if rate < 1000:
            continue  # (at low rates a spike must be large against the oscillation: module docstring)
        for size in (3.0, 15.0):
            az = c.az.copy()
            j = int(rng.integers(5, az.size - 5))
            az[j] += rng.choice([-1.0, 1.0]) * size * G
            assert np.flatnonzero(outliers(az)).tolist() == [j]
        az = c.az.copy()  # two adjacent glitch samples
        az[100:102] += 5 * G
        assert np.flatnonzero(outliers(az)).tolist() == [100, 101]


def test_a_step_or_a_ramp_is_not_an_outlier_and_the_floor_holds():
    t = np.arange(400) * 1e-3
    step = np.where(t < 0.2, 9.81, 9.81 + 20.0)  # a 2 g step (a break-away is sharper than any real one)
    ramp = 9.81 + 200.0 * t
    assert not outliers(step).any() and not outliers(ramp).any()
    flat = np.full(400, 9.81)
    flat[50] += 0.9 * FLOOR  # below the floor on a noise-free signal: kept
    flat[300] += 1.1 * FLOOR
    assert np.flatnonzero(outliers(flat)).tolist() == [300]
    assert not outliers(np.full(4, 9.81)).any() and outliers(np.array([])).size == 0


def test_the_running_median_of_five_is_numpys():
    from slipest.despike import _median5

    rng = np.random.default_rng(5)
    for n in (3, 4, 5, 6, 9):
        for _ in range(300):
            a = rng.integers(0, 5, n).astype(float)  # ties too
            for i in range(n):
                assert _median5(a, i, n) == np.median(a[max(0, i - 2) : i + 3])


def test_the_two_samples_at_each_end_are_not_judged():
    """A step in a cycle's last sample (the next leg's touchdown, put there by a rounded leg angle) is no
    outlier; a glitch three samples in is found."""
    rng = np.random.default_rng(4)
    az = 14.5 + rng.normal(0.0, 0.01 * G, 400)
    az[-1] = 9.9  # a step of -0.47 g in the last sample
    az[0] = 20.0
    assert not outliers(az).any()
    az[2] += 3.0 * G
    assert np.flatnonzero(outliers(az)).tolist() == [2]


def _plain_outliers(az, k, floor, block):
    """The module docstring's rule in plain numpy (every residual judged against its blocks' scale)."""
    n = az.size
    r = np.array([az[i] - np.median(az[max(0, i - 2):i + 3]) for i in range(n)])
    scale = np.array([np.median(np.abs(r[b:b + block])) for b in range(0, n, block)])
    out = np.zeros(n, dtype=bool)
    for i in range(2, n - 2):
        b = i // block
        s = scale[max(0, b - 1):b + 2].max()
        out[i] = abs(r[i]) > max(k * 1.4826 * s, floor)
    return out


@pytest.mark.parametrize("seed", range(60))
def test_outliers_equal_the_plain_statement_of_the_rule(seed):
    """The compiled rule (which skips the local scales when no residual reaches the floor) flags exactly what
    the plain statement does: noise below and above the floor, glitches on top, blocks cut short at the end."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 300))
    az = 9.81 + np.sin(np.arange(n) * rng.uniform(0.01, 0.5)) * rng.choice([0.0, 0.1, 5.0])
    az += rng.normal(0.0, rng.choice([0.005, 0.05, 0.3, 1.5]) * FLOOR, n)
    for _ in range(int(rng.integers(0, 4))):
        az[int(rng.integers(0, n))] += rng.choice([-1.0, 1.0]) * np.exp(rng.uniform(np.log(0.5), np.log(20.0))) * FLOOR
    k, block = float(rng.choice([3.0, 6.0])), int(rng.choice([8, 32]))
    assert outliers(az, k=k, floor=FLOOR, block=block).tolist() == _plain_outliers(az, k, FLOOR, block).tolist()
