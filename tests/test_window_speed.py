"""slipest.online._window_speed (compiled) against the plain numpy statement of what it computes."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.online import _window_speed


def _plain(t, phase, half):
    inside = np.flatnonzero((phase >= 0.0) & (phase <= half))
    if inside.size < 2:
        return math.nan
    i0, i1 = int(inside[0]), int(inside[-1])
    span = float(t[i1] - t[i0])
    return float(phase[i1] - phase[i0]) / span if span > 0 else math.nan


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-1.0, 1.5) | st.just(math.nan) | st.just(0.0) | st.just(math.pi / 4), max_size=40),
       st.floats(1e-4, 0.01), st.booleans())
def test_window_speed_equals_the_numpy_statement(phases, dt, repeat_time):
    """Mean leg speed over the samples with phase in [0, half]: bit for bit the numpy statement (NaN phases,
    phases on the bounds, fewer than two samples inside, no time elapsed)."""
    phase = np.array(phases, dtype=float)
    t = np.zeros(phase.size) if repeat_time else np.arange(phase.size) * dt
    got, want = _window_speed(t, phase, math.pi / 4), _plain(t, phase, math.pi / 4)
    assert (math.isnan(got) and math.isnan(want)) or got == want
