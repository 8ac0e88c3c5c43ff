"""SlipEstimator.noise_estimate: the median of the last cycles' noise measures, as numpy computes it."""

from collections import deque

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.online import NOISE_CYCLES, SlipEstimator


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
