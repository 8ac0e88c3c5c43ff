"""The compiled helpers of slipest.online (_window_speed, _rigid_mean) against the plain numpy statements of what
they compute."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.online import _rigid_mean, _window_speed


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


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0) | st.just(math.nan) | st.just(-0.8 * math.pi / 4) | st.just(-0.05 * math.pi / 4),
                max_size=40), st.integers(0, 2**32 - 1))
def test_rigid_mean_equals_the_numpy_statement(phases, seed):
    """Mean az over the phases in [-0.8 half, -0.05 half]: the numpy statement to rounding (NaN phases left out,
    phases on the bounds in, NaN when none)."""
    half = math.pi / 4
    phase = np.array(phases, dtype=float)
    az = 9.81 + np.random.default_rng(seed).normal(0.0, 3.0, phase.size)
    sel = (phase >= -0.8 * half) & (phase <= -0.05 * half)
    want = float(np.mean(az[sel])) if sel.any() else math.nan
    got = _rigid_mean(phase, az, half)
    assert (math.isnan(got) and math.isnan(want)) or got == pytest.approx(want, rel=1e-12)
