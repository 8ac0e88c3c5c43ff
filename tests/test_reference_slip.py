"""A cycle's reference slip: the value its samples carry most often, robust to a column that changes a sample
early or late (slipest.online.ReferenceTally)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.online import ReferenceTally, SlipEstimator

SLIPS = np.array([0.05, 0.40, 0.10, 0.30, 0.20, 0.45, 0.15, 0.25])


def _stream():
    sc = Scenario.per_cycle(StickSlipParams(), dict(noise_g=0.01, rate=1000.0, seed=3), slip=SLIPS)
    return simulate_stream(sc)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([0.1, 0.2, 0.3, math.nan]), min_size=0, max_size=40),
       st.lists(st.integers(0, 40), max_size=3))
def test_add_many_is_add_on_every_value(values, cuts):
    one = ReferenceTally()
    for v in values:
        one.add(v)
    many = ReferenceTally()
    arr = np.array(values, dtype=float)
    edges = [0, *sorted(min(c, arr.size) for c in cuts), arr.size]
    for a, b in zip(edges[:-1], edges[1:]):
        many.add_many(arr[a:b])
    x, y = one.take(), many.take()
    assert (math.isnan(x) and math.isnan(y)) or x == y


def test_most_frequent_wins_and_a_tie_goes_to_the_latest():
    t = ReferenceTally()
    assert math.isnan(t.take())
    for v in (0.3, 0.3, 0.1, math.inf, math.nan):
        t.add(v)
    assert t.take() == 0.3
    t.add(0.2)
    t.add(0.4)  # one message each: the later replaces the earlier
    assert t.take() == 0.4
    assert math.isnan(t.take())  # taken: the next cycle starts empty


def test_a_slip_column_that_changes_early_still_labels_every_cycle_with_its_own_slip():
    s = _stream()
    cyc = np.asarray(s.cycle)
    slip = np.asarray(s.slip, dtype=float)
    # the column changes 3 samples before each cycle's boundary (a reference logged early)
    early = slip.copy()
    change = np.flatnonzero(np.diff(cyc) != 0) + 1
    for j in change:
        early[j - 3:j] = slip[j]
    for push_one in (False, True):
        est = SlipEstimator(n_legs=4)
        if push_one:
            out = []
            for a, b, c, d in zip(s.t.tolist(), s.az.tolist(), s.theta.tolist(), early.tolist()):
                out += est.push(a, b, c, d)
        else:
            out = est.push_many(s.t, s.az, s.theta, early)
        out += est.finish()
        got = {e.cycle: e.slip_ref for e in out if 0 <= e.cycle < SLIPS.size and math.isfinite(e.slip_ref)}
        assert len(got) >= SLIPS.size - 1
        for k, ref in got.items():
            assert ref == SLIPS[k], (push_one, k, ref)
