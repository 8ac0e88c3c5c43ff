"""SlipEstimator.noise_estimate: the median of the last cycles' noise measures, as numpy computes it; a cycle much
noisier than it (a burst) referred to its own noise."""

from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.online import NOISE_CYCLES, SlipEstimator
from slipest.units import G
from tests.log_makers import stream


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(0.0, 1.0, allow_nan=False) | st.floats(1e-300, 1e300), min_size=1, max_size=2 * NOISE_CYCLES))
def test_noise_estimate_is_numpys_median_of_the_last_cycles(measures):
    """The running noise estimate is bit for bit np.median of the last NOISE_CYCLES measures (odd and even counts,
    any magnitudes); NaN before the first."""
    est = SlipEstimator.__new__(SlipEstimator)  # the median alone: no model needed
    est.noise = None
    est._noises = deque(maxlen=NOISE_CYCLES)  # as SlipEstimator.__init__ sets it
    assert np.isnan(est.noise_estimate)
    for i, m in enumerate(measures):
        est._noises.append(m)
        last = measures[max(0, i + 1 - NOISE_CYCLES) : i + 1]
        assert est.noise_estimate == float(np.median(last))


@pytest.fixture(scope="module")
def steady():
    """A 16-cycle drive at slip 0.3 and 0.01 g, and its clean estimates."""
    run, _ = stream(slip=[0.3] * 16, seed=4)
    est = SlipEstimator(n_legs=4)
    rows = est.push_many(run.t, run.az, run.theta) + est.finish()
    return run, {r.cycle: r for r in rows}, est


def test_clean_cycles_are_never_a_noise_burst(steady):
    _, _, est = steady
    assert est.counters["cycles_noise_burst"] == 0 and "noise" not in est.hints


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_cycle_much_noisier_than_the_running_noise_is_referred_to_its_own(steady, seed):
    """A burst of 0.15 g over one whole cycle among 0.01 g ones: the cycle is referred to its own noise (its
    reported noise is the burst's, its interval holding the truth); counted and
    said once. Referred to the running 0.01 g, such cycles came out 5-10 standard deviations off."""
    run, clean, _ = steady
    k = 8
    sel = (run.t > clean[k].t_start) & (run.t <= clean[k].t_end)
    az = run.az.copy()
    az[sel] += 0.15 * G * np.random.default_rng(seed).standard_normal(int(sel.sum()))
    est = SlipEstimator(n_legs=4)
    rows = {r.cycle: r for r in est.push_many(run.t, az, run.theta) + est.finish()}
    burst = rows[k]
    assert burst.ok and 0.12 < burst.noise < 0.18
    assert abs(burst.slip - 0.3) < 2.5 * burst.slip_std
    assert est.counters["cycles_noise_burst"] == 1 and "0.01" in est.hints["noise"]
    assert est.counters["noise_g"] == pytest.approx(clean[k].noise, rel=0.2)  # the running noise unmoved


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_a_burst_on_the_stance_alone_is_referred_to_the_stance_noise(steady, seed):
    """A burst of 0.1-0.2 g on one cycle's stance only, its rigid half (where the noise is measured) quiet: the
    stance's own measure finds it and the cycle is referred to it. Referred to the running 0.01 g, 5 of 8 such
    cycles came out 6-11 standard deviations off with intervals tighter than a clean cycle's."""
    run, clean, _ = steady
    k = 8
    phase = run.theta - (2 * np.pi / 4) * k
    sel = (run.t > clean[k].t_start) & (run.t <= clean[k].t_end) & (phase >= 0.0)
    for level in (0.1, 0.2):
        az = run.az.copy()
        az[sel] += level * G * np.random.default_rng(seed).standard_normal(int(sel.sum()))
        est = SlipEstimator(n_legs=4)
        rows = {r.cycle: r for r in est.push_many(run.t, az, run.theta) + est.finish()}
        burst = rows[k]
        assert burst.ok and 0.8 * level < burst.noise < 1.2 * level
        assert abs(burst.slip - 0.3) < 2.5 * burst.slip_std
        assert est.counters["cycles_noise_burst"] == 1 and "noise" in est.hints
        assert all(rows[j].noise < 0.02 for j in rows if j != k and rows[j].ok)
