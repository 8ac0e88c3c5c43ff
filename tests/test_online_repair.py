"""A glitch sample or a few lost ones do not move an estimate, nor cost the cycle (issue 13.1-13.2)."""

import math

import numpy as np
import pytest

from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.online import SlipEstimator

H = math.pi / 4


@pytest.fixture(scope="module")
def drive():
    p = StickSlipParams(kS=900.0, phiS=0.55, phiD=0.3)
    sc = Scenario.per_cycle(p, dict(noise_g=0.01, seed=21), slip=[0.3] * 10)
    s = simulate_stream(sc)
    clean, _ = _run(s.t, s.az, s.theta)
    assert len(clean) == 10 and all(e.quality == "ok" for e in clean)
    return s, clean


def _row(s, cycle, phase):
    """Index of the first sample of ``cycle`` at or past ``phase`` [rad] from its midstance."""
    return int(np.flatnonzero(s.theta >= 2 * H * cycle + phase)[0])


def _run(t, az, theta):
    est = SlipEstimator()
    return list(est.iter_estimates([(t, az, theta)])), est


@pytest.mark.parametrize("spike", [30.0, 98.0, 150.0, -50.0])
def test_one_spike_does_not_move_the_estimate(drive, spike):
    s, clean = drive
    az = s.az.copy()
    j = _row(s, 5, 0.4)  # in the stance, where the features are
    az[j] = spike  # the glitches [m/s^2]
    got, est = _run(s.t, az, s.theta)
    assert [e.cycle for e in got] == [e.cycle for e in clean] and all(e.ok for e in got)
    assert got[5].quality == "repaired" and got[5].n_repaired == 1 and est.counters["spikes"] == 1
    for a, b in zip(got, clean):
        assert abs(a.slip - b.slip) <= 0.2 * b.slip_std and abs(a.dphi - b.dphi) <= 0.2 * b.dphi_std
        assert a.slip_std == pytest.approx(b.slip_std, rel=0.2)
        if a.cycle != 5:
            assert a.quality == "ok" and a.n_repaired == 0


@pytest.mark.parametrize("how, n", [("missing rows", 1), ("missing rows", 3), ("nan az", 2), ("nan az", 4)])
def test_a_few_lost_samples_are_bridged(drive, how, n):
    s, clean = drive
    j = _row(s, 6, 0.3)
    t, az, theta = s.t.copy(), s.az.copy(), s.theta.copy()
    if how == "nan az":
        az[j : j + n] = np.nan
    else:
        keep = np.ones(t.size, bool)
        keep[j : j + n] = False
        t, az, theta = t[keep], az[keep], theta[keep]
    got, _ = _run(t, az, theta)
    assert all(e.ok for e in got) and got[6].quality == "repaired" and got[6].n_repaired == n
    assert abs(got[6].slip - clean[6].slip) <= 0.2 * clean[6].slip_std


def test_a_long_hole_still_flags_the_cycle_and_losses_count_in_the_whole_cycle(drive):
    s, clean = drive
    az = s.az.copy()
    az[_row(s, 4, 0.3) : _row(s, 4, 0.3) + 8] = np.nan  # 8 ms in the stance
    az[_row(s, 7, -0.5) : _row(s, 7, -0.5) + 8] = np.nan  # 8 ms in the rigid half, before the features' window
    got, est = _run(s.t, az, s.theta)
    assert got[4].quality == "nan" and got[7].quality == "nan" and not got[4].ok and math.isnan(got[4].slip)
    assert sum(e.ok for e in got) == len(clean) - 2 and est.counters["flagged_nan"] == 2
