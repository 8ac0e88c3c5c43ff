"""Tests of slipest.segmentation: streaming leg-cycle segmentation.

Streams are synthetic: theta = theta0 + omega * t (omega = 0.63 rad/s) sampled
at 1 kHz, az = 9.81 m/s^2 plus a decaying sine per cycle. Each stream fault
gets its own test that checks the flag it must raise and that the ok cycles
around it are still right.
"""

import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from slipest.segmentation import QUALITIES, QUALITY_PRIORITY, CycleSegmenter, LegCycle
from slipest.units import G

OMEGA = 0.63  # rad/s
FS = 1000.0  # Hz
NL = 4
H = math.pi / NL  # half a leg period [rad]
P = 2 * H  # leg period [rad]


def make_stream(T=20.0, fs=FS, omega=OMEGA, th0=-0.3, n_legs=NL, t0=0.0):
    """t [s], az [m/s^2], theta [rad] (unwrapped) of a rover driving forward."""
    t = t0 + np.arange(int(round(T * fs))) / fs
    th = th0 + omega * (t - t0)
    p = 2 * math.pi / n_legs
    ph = (th + p / 2) % p - p / 2
    az = 9.81 + 2.0 * np.exp(-8.0 * np.maximum(ph, 0.0)) * np.sin(40.0 * ph)
    return t, az, th


def run_push(seg, t, az, th):
    out = []
    for a, b, c in zip(np.asarray(t).tolist(), np.asarray(az).tolist(), np.asarray(th).tolist()):
        out += seg.push(a, b, c)
    return out


def run_many(seg, t, az, th, chunk=65536):
    out = []
    for i in range(0, len(t), chunk):
        out += seg.push_many(t[i : i + chunk], az[i : i + chunk], th[i : i + chunk])
    return out


def expected_window(t, az, th, k, window=(0.0, H)):
    """Samples of cycle k's window for a monotone (forward, clean) stream."""
    mk = k * P
    ph = th - mk
    m = (ph >= window[0]) & (ph < window[1])
    return t[m], az[m], ph[m]


def assert_cycle_matches_stream(c, t, az, th, window=(0.0, H)):
    et, eaz, eph = expected_window(t, az, th, c.k, window)
    np.testing.assert_array_equal(c.t, et)
    np.testing.assert_array_equal(c.az, eaz)
    np.testing.assert_allclose(c.theta_phase, eph, atol=1e-9)
    assert c.n_samples == len(et)


def by_k(cycles):
    return {c.k: c for c in cycles}


# ---------------------------------------------------------------------------
# clean stream, closing, window
# ---------------------------------------------------------------------------


def test_clean_stream_all_ok_and_windows_right():
    t, az, th = make_stream(T=30.0)
    seg = CycleSegmenter(n_legs=NL)
    cycles = run_push(seg, t, az, th)
    # theta goes from -0.3 to 18.6 rad: cycles k = 0 .. (last closed)
    last_closed = math.floor((th[-1] - H) / P)
    assert [c.k for c in cycles] == list(range(0, last_closed + 1))
    assert all(c.quality == "ok" and c.ok and c.flags == () for c in cycles)
    for c in cycles:
        assert_cycle_matches_stream(c, t, az, th)
        assert np.all(c.theta_phase >= 0.0) and np.all(c.theta_phase < H)
        # (pi/4) / (0.63 rad/s) * 1 kHz samples, give or take one
        assert abs(c.n_samples - H / OMEGA * FS) <= 1.5
    # consecutive cycles share their boundary sample
    for a, b in zip(cycles, cycles[1:]):
        assert b.t_start == a.t_end
    c = seg.counters
    assert c["samples_seen"] == len(t)
    assert c["samples_dropped"] == 0
    assert c["cycles_ok"] == len(cycles) == c["cycles_emitted"]


def test_cycle_closes_exactly_on_closing_sample():
    t, az, th = make_stream(T=12.0)
    seg = CycleSegmenter(n_legs=NL)
    emitted_at = {}
    for i in range(len(t)):
        for c in seg.push(t[i], az[i], th[i]):
            emitted_at[c.k] = i
    assert len(emitted_at) >= 3
    for k, i in emitted_at.items():
        first_after = int(np.flatnonzero(th >= k * P + H)[0])
        assert i == first_after, (k, i, first_after)
        c_end = t[first_after]
        assert th[i - 1] < k * P + H <= th[i]
        assert c_end == t[i]


def test_t_start_t_end_are_boundary_samples():
    t, az, th = make_stream(T=12.0)
    cycles = run_many(CycleSegmenter(), t, az, th)
    for c in cycles[1:]:
        i_start = int(np.flatnonzero(th >= c.k * P - H)[0])
        i_end = int(np.flatnonzero(th >= c.k * P + H)[0])
        assert c.t_start == t[i_start]
        assert c.t_end == t[i_end]


def test_custom_window_full_stance_and_narrow():
    t, az, th = make_stream(T=15.0)
    for window in [(-H, H), (-H / 2, H / 2), (0.1, 0.3)]:
        cycles = run_many(CycleSegmenter(n_legs=NL, window=window), t, az, th)
        assert len(cycles) >= 4
        # the first cycle's window starts before the stream: partial for the full stance
        for c in cycles[1:]:
            assert c.quality == "ok", (window, c)
            assert_cycle_matches_stream(c, t, az, th, window)
            assert c.theta_phase.min() >= window[0] and c.theta_phase.max() < window[1]


def test_other_leg_count():
    t, az, th = make_stream(T=15.0, n_legs=5)
    cycles = run_many(CycleSegmenter(n_legs=5), t, az, th)
    h5 = math.pi / 5
    assert len(cycles) == math.floor((th[-1] - h5) / (2 * h5)) + 1
    for c in cycles:
        assert c.ok
        assert c.theta_phase.max() < h5


def test_legcycle_is_frozen_and_arrays_read_only():
    t, az, th = make_stream(T=6.0)
    c = run_many(CycleSegmenter(), t, az, th)[0]
    assert isinstance(c, LegCycle)
    with pytest.raises(AttributeError):
        c.quality = "ok"
    with pytest.raises(ValueError):
        c.az[0] = 0.0


# ---------------------------------------------------------------------------
# wrapping
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("wrap", ["pm_pi", "zero_2pi"])
def test_wrapped_and_unwrapped_give_same_cycles(wrap):
    t, az, th = make_stream(T=40.0)  # 25 rad: about 4 revolutions
    if wrap == "pm_pi":
        thw = (th + math.pi) % (2 * math.pi) - math.pi
    else:
        thw = th % (2 * math.pi)
    ref_seg = CycleSegmenter(theta_wrap="none")
    ref = run_many(ref_seg, t, az, th)
    seg = CycleSegmenter(theta_wrap="auto")
    got = run_many(seg, t, az, thw)
    assert seg.counters["wraps"] == np.count_nonzero(np.abs(np.diff(thw)) > math.pi) > 0
    assert len(got) == len(ref)
    dk = got[0].k - ref[0].k
    assert dk % NL == 0  # the angle offset is a whole number of revolutions
    for a, b in zip(got, ref):
        assert a.k - b.k == dk
        assert a.quality == b.quality == "ok"
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.az, b.az)
        np.testing.assert_allclose(a.theta_phase, b.theta_phase, atol=1e-9)
    # push gives the same as push_many on the wrapped stream
    assert run_push(CycleSegmenter(), t, az, thw) == got


def test_wrapped_stream_without_unwrapping_is_not_ok():
    """theta_wrap='none' on a wrapped stream: the wrap is a backward jump."""
    t, az, th = make_stream(T=20.0)
    thw = (th + math.pi) % (2 * math.pi) - math.pi
    cycles = run_many(CycleSegmenter(theta_wrap="none"), t, az, thw)
    assert any(c.quality == "reverse" for c in cycles)


# ---------------------------------------------------------------------------
# stream faults
# ---------------------------------------------------------------------------


def test_jitter_and_uneven_sampling_is_fine():
    rng = np.random.default_rng(1)
    dt = (1.0 + rng.uniform(-0.4, 0.4, 30000)) / FS
    t = np.cumsum(dt)
    th = -0.3 + OMEGA * t
    az = 9.81 + rng.normal(0, 0.5, t.size)
    cycles = run_many(CycleSegmenter(), t, az, th)
    assert len(cycles) >= 6
    assert all(c.ok for c in cycles)
    for c in cycles:
        assert_cycle_matches_stream(c, t, az, th)


def test_first_partial_cycle():
    t, az, th = make_stream(T=10.0, th0=0.2)  # starts inside cycle 0's window
    cycles = run_many(CycleSegmenter(), t, az, th)
    assert cycles[0].k == 0 and cycles[0].quality == "partial"
    assert cycles[0].theta_phase[0] == pytest.approx(0.2)
    assert all(c.ok for c in cycles[1:]) and len(cycles) >= 3
    for c in cycles[1:]:
        assert_cycle_matches_stream(c, t, az, th)
    # started before the window: the first cycle is complete and ok
    t, az, th = make_stream(T=10.0, th0=-0.1)
    cycles = run_many(CycleSegmenter(), t, az, th)
    assert cycles[0].k == 0 and cycles[0].ok


def test_a_start_a_hair_before_a_cycle_is_that_cycle():
    # a log's rounded angle: -pi/4 written with 7 decimals is -0.7853982, 2e-8 rad before cycle 0 starts
    t, az, th = make_stream(T=6.0, th0=-0.7853982)
    cycles = run_many(CycleSegmenter(window=(-H, H)), t, az, th)
    assert cycles[0].k == 0 and cycles[0].ok and cycles[0].t_start == t[0]
    assert all(c.ok for c in cycles)


@pytest.mark.parametrize("window", [(0.0, H), (-H, H)])
def test_finish_emits_the_last_cycle_complete_or_partial(window):
    # a stream that ends on the last sample of cycle 2 (the sample closing it never comes)
    t, az, th = make_stream(T=10.0, th0=-H)
    end = int(np.flatnonzero(th - 2 * P < H)[-1]) + 1
    seg = CycleSegmenter(window=window)
    first = cycles = run_many(seg, t[:end], az[:end], th[:end])
    assert [c.k for c in cycles] == [0, 1] and cycles[1].ok
    last = seg.finish()
    assert [c.k for c in last] == [2] and last[0].ok and last[0].t_end == t[end - 1]
    assert_cycle_matches_stream(last[0], t, az, th, window)
    assert seg.counters["cycles_emitted"] == 3
    assert seg.finish() == []  # nothing open any more
    # the stream stopped in the middle of cycle 2's window: partial, never ok
    cut = int(np.flatnonzero(th - 2 * P < 0.5 * H)[-1]) + 1
    seg = CycleSegmenter(window=window)
    run_many(seg, t[:cut], az[:cut], th[:cut])
    last = seg.finish()
    assert [c.k for c in last] == [2] and last[0].quality == "partial"
    # pushing on starts a new stream: a clock that starts again is not "time backwards"
    again = run_many(seg, t[:end], az[:end], th[:end]) + seg.finish()
    assert [(c.k, c.quality) for c in again] == [(c.k, c.quality) for c in first] + [(2, "ok")]
    assert seg.counters["time_backwards"] == 0 and seg.counters["resyncs"] == 2


def test_finish_on_a_fresh_segmenter_emits_nothing():
    seg = CycleSegmenter()
    assert seg.finish() == [] and seg.counters["cycles_emitted"] == 0


def test_time_gap_in_window_flags_gap():
    t, az, th = make_stream(T=20.0)
    # drop 50 ms of samples in the middle of cycle 3's window
    i = int(np.flatnonzero(th >= 3 * P + 0.4)[0])
    keep = np.ones(t.size, bool)
    keep[i : i + 50] = False
    t2, az2, th2 = t[keep], az[keep], th[keep]
    cycles = by_k(run_many(CycleSegmenter(), t2, az2, th2))
    assert cycles[3].quality == "gap"
    for k in (1, 2, 4, 5):
        assert cycles[k].ok
        assert_cycle_matches_stream(cycles[k], t2, az2, th2)


def test_gap_across_window_start_flags_gap():
    t, az, th = make_stream(T=20.0)
    i = int(np.flatnonzero(th >= 2 * P)[0])
    keep = np.ones(t.size, bool)
    keep[i - 20 : i + 20] = False  # the window's first samples and the ones before it
    cycles = by_k(run_many(CycleSegmenter(), t[keep], az[keep], th[keep]))
    assert cycles[2].quality == "gap"
    assert cycles[1].ok and cycles[3].ok


def test_explicit_max_gap():
    t, az, th = make_stream(T=10.0)
    i = int(np.flatnonzero(th >= 1 * P + 0.3)[0])
    keep = np.ones(t.size, bool)
    keep[i : i + 3] = False  # a 4 ms step
    cycles = by_k(run_many(CycleSegmenter(max_gap=0.0035), t[keep], az[keep], th[keep]))
    assert cycles[1].quality == "gap"
    cycles = by_k(run_many(CycleSegmenter(max_gap=0.0045), t[keep], az[keep], th[keep]))
    assert cycles[1].ok


def test_theta_jump_in_window_flags_gap():
    t, az, th = make_stream(T=20.0)
    th2 = th.copy()
    i = int(np.flatnonzero(th >= 2 * P + 0.3)[0])
    th2[i:] += 0.2  # encoder skipped 0.2 rad while time went on
    cycles = by_k(run_many(CycleSegmenter(), t, az, th2))
    assert cycles[2].quality == "gap"
    assert cycles[1].ok and cycles[3].ok
    assert_cycle_matches_stream(cycles[3], t, az, th2)


def test_jump_over_whole_cycles_counts_skipped():
    t, az, th = make_stream(T=20.0)
    th2 = th.copy()
    i = int(np.flatnonzero(th >= 1 * P + 0.3)[0])
    th2[i:] += 2 * P + 0.05  # from cycle 1's window into cycle 3's: cycle 2 never seen
    seg = CycleSegmenter()
    cycles = run_many(seg, t, az, th2)
    ks = [c.k for c in cycles]
    assert ks[:3] == [0, 1, 3]
    assert by_k(cycles)[1].quality == "gap"
    assert by_k(cycles)[3].quality == "gap"  # its window was entered by the jump
    assert seg.counters["cycles_skipped"] == 1
    assert by_k(cycles)[4].ok
    assert_cycle_matches_stream(by_k(cycles)[4], t, az, th2)


@pytest.mark.parametrize("hair", [2e-8, 5e-5])
def test_a_jump_landing_a_hair_before_a_cycle_starts_that_cycle(hair):
    """A device restarted (firmware-sim, 25 s later): its first angle, -pi/4 as a float32, is 2e-8 rad before
    a cycle's start. It starts that cycle, as a first sample does; it used to open the cycle before it with this
    one sample at its very end, a cycle nobody drove, emitted ('gap') and counted as one."""
    t, az, th = make_stream(T=10.0, th0=-H)
    end = th < 3 * P + H  # the first run: cycles 0-3, to the last sample of cycle 3
    t, az, th = t[end], az[end], th[end]
    t2, az2, th2 = make_stream(T=10.0, th0=-H - hair, t0=t[-1] + 25.0)
    th2 = th2 + 10 * P  # unwrapped 10 cycles on (the branch the leg speed predicts)
    for run in (run_many, run_push):
        seg = CycleSegmenter()
        cycles = run(seg, np.r_[t, t2], np.r_[az, az2], np.r_[th, th2]) + seg.finish()
        assert [c.k for c in cycles] == [0, 1, 2, 3] + [10, 11, 12, 13], run
        assert all(c.ok for c in cycles if c.k != 3) and by_k(cycles)[3].quality == "gap"  # closed 25 s late
        assert by_k(cycles)[10].t_start == t2[0]
        assert seg.counters["cycles_skipped"] == 6
    # a landing farther before the start (1.2 ms of driving) is in the cycle before: flagged, never ok
    t3, az3, th3 = make_stream(T=10.0, th0=-H - 0.63 * 1.2e-3, t0=t[-1] + 25.0)
    cycles = by_k(run_many(CycleSegmenter(), np.r_[t, t3], np.r_[az, az3], np.r_[th, th3 + 10 * P]))
    assert cycles[9].quality == "gap" and cycles[9].n_samples == 2 and cycles[10].ok


def test_stop_inside_window_flags_stopped_and_emits_nothing_meanwhile():
    t, az, th = make_stream(T=20.0)
    th2 = th.copy()
    i0 = int(np.flatnonzero(th >= 2 * P + 0.3)[0])
    n_stop = 3000  # 3 s standing still, IMU still sampling
    th2[i0 : i0 + n_stop] = th[i0]
    th2[i0 + n_stop :] = th[i0 + n_stop :] - (th[i0 + n_stop] - th[i0])
    seg = CycleSegmenter()
    emitted = []
    for i in range(t.size):
        for c in seg.push(t[i], az[i], th2[i]):
            emitted.append((i, c))
    during = [c for i, c in emitted if i0 <= i < i0 + n_stop]
    assert during == []
    cycles = by_k([c for _, c in emitted])
    assert cycles[2].quality == "stopped"
    assert cycles[1].ok and cycles[3].ok
    assert_cycle_matches_stream(cycles[3], t, az, th2)


def test_short_pause_is_not_a_stop():
    t, az, th = make_stream(T=12.0)
    th2 = th.copy()
    i0 = int(np.flatnonzero(th >= 1 * P + 0.3)[0])
    th2[i0 : i0 + 200] = th[i0]  # 0.2 s < stop_time
    th2[i0 + 200 :] -= th[i0 + 200] - th[i0]
    cycles = by_k(run_many(CycleSegmenter(stop_time=0.5), t, az, th2))
    assert cycles[1].ok


def test_stop_before_window_does_not_flag():
    t, az, th = make_stream(T=15.0)
    th2 = th.copy()
    i0 = int(np.flatnonzero(th >= 2 * P - 0.3)[0])  # in the braking half
    th2[i0 : i0 + 3000] = th[i0]
    th2[i0 + 3000 :] -= th[i0 + 3000] - th[i0]
    cycles = by_k(run_many(CycleSegmenter(), t, az, th2))
    assert cycles[2].ok
    assert_cycle_matches_stream(cycles[2], t, az, th2)


def test_stopped_forever_mid_stance_memory_bounded():
    seg = CycleSegmenter(max_samples=2048, initial_capacity=256)
    t, az, th = make_stream(T=3.0, th0=-0.1)
    first = run_many(seg, t, az, th)
    assert [c.k for c in first] == [0] and first[0].ok
    th_stop = th[-1]
    n = 0
    emitted = []
    # ten minutes of standing still inside cycle 0/1's window, 1 kHz
    for i in range(60):
        tt = t[-1] + (n + np.arange(10000) + 1) / FS
        emitted += seg.push_many(tt, np.full(tt.size, 9.81), np.full(tt.size, th_stop))
        n += tt.size
        assert seg.buffer_capacity <= 2048
    assert emitted == []
    assert seg.counters["samples_overflow"] > 500000
    # it drives on: that cycle is too long, then all is well again
    t2 = t[-1] + (n + np.arange(8000) + 1) / FS
    th2 = th_stop + OMEGA * (t2 - t2[0] + 1e-3)
    az2 = 9.81 + np.sin(50 * t2)
    cycles = seg.push_many(t2, az2, th2)
    assert cycles[0].quality == "too_long"
    assert cycles[0].t.size == 0 and cycles[0].n_samples > 600000
    assert cycles[1].ok
    assert seg.buffer_capacity <= 2048


def test_long_stream_buffers_do_not_grow():
    seg = CycleSegmenter()
    cap0 = seg.buffer_capacity
    t, az, th = make_stream(T=3600.0)  # one hour at 1 kHz
    n_ok = 0
    for i in range(0, t.size, 65536):
        n_ok += sum(c.ok for c in seg.push_many(t[i : i + 65536], az[i : i + 65536], th[i : i + 65536]))
    assert seg.buffer_capacity == cap0
    assert n_ok == seg.counters["cycles_emitted"] > 800
    assert seg.counters["samples_seen"] == t.size


def test_too_long_cycle_dropped_with_empty_arrays():
    t, az, th = make_stream(T=10.0)
    seg = CycleSegmenter(max_samples=500, initial_capacity=64)
    cycles = run_many(seg, t, az, th)
    assert cycles and all(c.quality == "too_long" for c in cycles)
    assert all(c.t.size == 0 and c.az.size == 0 and c.n_samples > 1200 for c in cycles)
    assert seg.buffer_capacity == 500
    assert seg.counters["samples_overflow"] == sum(c.n_samples - 500 for c in cycles)
    assert run_push(CycleSegmenter(max_samples=500, initial_capacity=64), t, az, th) == cycles


def test_reverse_flagged_and_resynchronised():
    t, az, th = make_stream(T=25.0)
    th2 = th.copy()
    t_rev = 6.0
    m = t >= t_rev
    tt = t[m] - t_rev
    # 2 s backwards at the same speed, then forward again
    th2[m] = th[m][0] - OMEGA * np.minimum(tt, 2.0) + OMEGA * np.maximum(tt - 2.0, 0.0)
    seg = CycleSegmenter()
    emitted = []
    for i in range(t.size):
        for c in seg.push(t[i], az[i], th2[i]):
            emitted.append((i, c))
    cycles = [c for _, c in emitted]
    rev = [c for c in cycles if c.quality == "reverse"]
    assert len(rev) == 1 and rev[0].k == 2
    assert not any(c.ok for c in cycles if c.t_end > t_rev and c.t_start < t_rev + 2.0)
    # nothing is emitted while driving backwards (after the reversal is seen)
    i_rev = [i for i, c in emitted if c.quality == "reverse"][0]
    assert not any(i_rev < i < np.searchsorted(t, t_rev + 2.0) for i, _ in emitted)
    # after resuming, forward cycles are ok and right
    after = [c for c in cycles if c.t_start >= t_rev + 2.0]
    assert after[0].quality == "partial"  # resumed inside cycle 1's window
    later = after[1:]
    assert len(later) >= 4 and all(c.ok for c in later)
    t_after = t >= t_rev + 2.0
    for c in later:
        assert_cycle_matches_stream(c, t[t_after], az[t_after], th2[t_after])
    cnt = seg.counters
    assert cnt["reversals"] == 1 and cnt["cycles_reverse"] == 1
    assert cnt["samples_reverse"] > 1900
    assert run_many(CycleSegmenter(), t, az, th2, chunk=777) == cycles


def test_encoder_jitter_below_reverse_tol_is_not_reverse():
    t, az, th = make_stream(T=15.0)
    rng = np.random.default_rng(3)
    thj = th + rng.uniform(-0.003, 0.003, th.size)
    seg = CycleSegmenter(reverse_tol=0.01)
    cycles = run_many(seg, t, az, thj)
    assert seg.counters["reversals"] == 0
    assert len(cycles) >= 5 and all(c.ok for c in cycles)


@pytest.mark.parametrize("run, quality", [(1, "ok"), (4, "ok"), (5, "nan")])
def test_nan_az_in_window_bridged_when_short_flagged_when_long(run, quality):
    # at 1 kHz the adaptive max_gap is 5 ms: up to four NaN samples in a row are a hole the estimator bridges
    t, az, th = make_stream(T=15.0)
    az2 = az.copy()
    i = int(np.flatnonzero(th >= 2 * P + 0.4)[0])
    az2[i : i + run] = np.nan
    j = int(np.flatnonzero(th >= 3 * P - 0.4)[0])  # braking half: outside the window
    az2[j : j + 10] = np.nan
    seg = CycleSegmenter()
    cycles = by_k(run_many(seg, t, az2, th))
    assert cycles[2].quality == quality and cycles[2].n_missing == run
    assert np.isnan(cycles[2].az).sum() == run and seg.usable(cycles[2].az).sum() == cycles[2].n_samples - run
    assert cycles[1].ok and cycles[3].ok and cycles[1].n_missing == cycles[3].n_missing == 0


@pytest.mark.parametrize("which", ["theta", "t"])
def test_nan_theta_or_t_sample_dropped_and_counted_missing(which):
    t, az, th = make_stream(T=15.0)
    t2, th2 = t.copy(), th.copy()
    i = int(np.flatnonzero(th >= 2 * P + 0.4)[0])
    (th2 if which == "theta" else t2)[i] = np.nan
    seg = CycleSegmenter()
    cycles = by_k(run_many(seg, t2, az, th2))
    assert cycles[2].ok and cycles[2].n_missing == 1
    assert cycles[2].n_samples == expected_window(t, az, th, 2)[0].size - 1
    assert seg.counters["samples_invalid"] == 1
    # six rows in a row: a 7 ms hole, flagged
    (th2 if which == "theta" else t2)[i : i + 6] = np.nan
    cycles = by_k(run_many(CycleSegmenter(), t2, az, th2))
    assert cycles[2].quality == "gap" and cycles[1].ok and cycles[3].ok


def test_rows_missing_from_the_stream_are_counted():
    t, az, th = make_stream(T=15.0)
    i = int(np.flatnonzero(th >= 2 * P + 0.4)[0])
    keep = np.ones(t.size, bool)
    keep[i : i + 3] = False
    keep[i + 50] = False
    cycles = by_k(run_many(CycleSegmenter(), t[keep], az[keep], th[keep]))
    assert cycles[2].ok and cycles[2].n_missing == 4


@pytest.mark.parametrize("run, quality", [(1, "ok"), (5, "saturated")])
def test_saturated_and_clip_values(run, quality):
    t, az, th = make_stream(T=15.0)
    az2 = az.copy()
    i = int(np.flatnonzero(th >= 1 * P + 0.4)[0])
    az2[i : i + run] = 16 * G  # full scale
    j = int(np.flatnonzero(th >= 2 * P + 0.4)[0])
    az2[j : j + run] = -np.inf
    m = int(np.flatnonzero(th >= 3 * P + 0.4)[0])
    az2[m : m + run] = 77.125  # the IMU's clip value
    cycles = by_k(run_many(CycleSegmenter(clip_values=(77.125, -77.125)), t, az2, th))
    for k in (1, 2, 3):
        assert cycles[k].quality == quality and cycles[k].n_missing == run
    assert cycles[0].ok and cycles[4].ok
    # without the clip value, 77.125 m/s^2 (< 16 g) is a legitimate reading
    assert by_k(run_many(CycleSegmenter(), t, az2, th))[3].n_missing == 0


@pytest.mark.parametrize("kind", ["duplicate", "backwards"])
def test_time_duplicate_or_backwards_counted_and_flagged(kind):
    t, az, th = make_stream(T=15.0)
    t2 = t.copy()
    i = int(np.flatnonzero(th >= 2 * P + 0.4)[0])
    t2[i] = t2[i - 1] if kind == "duplicate" else t2[i - 1] - 0.0005
    seg = CycleSegmenter()
    cycles = by_k(run_many(seg, t2, az, th))
    assert cycles[2].quality == "time"
    key = "time_duplicate" if kind == "duplicate" else "time_backwards"
    assert seg.counters[key] == 1
    assert cycles[1].ok and cycles[3].ok
    assert_cycle_matches_stream(cycles[3], t2, az, th)


def test_clock_reset_does_not_stop_the_stream():
    t, az, th = make_stream(T=20.0)
    t2 = t.copy()
    i = int(np.flatnonzero(th >= 2 * P + 0.4)[0])
    t2[i:] -= 100.0  # clock jumps back by 100 s and goes on
    seg = CycleSegmenter()
    cycles = by_k(run_many(seg, t2, az, th))
    assert cycles[2].quality == "time"
    assert seg.counters["time_backwards"] == 1
    assert cycles[3].ok and cycles[4].ok


def test_sparse_window():
    t, az, th = make_stream(T=30.0, fs=20.0)  # 20 Hz: ~25 samples per window
    cycles = run_many(CycleSegmenter(min_samples=40), t, az, th)
    assert cycles and all(c.quality == "sparse" for c in cycles)
    cycles = run_many(CycleSegmenter(min_samples=8), t, az, th)
    assert all(c.ok for c in cycles)


# ---------------------------------------------------------------------------
# chunking invariance: push (one sample) and push_many (any chunks, mixed with
# push) run the same state machine and must give the same cycles and counters
# ---------------------------------------------------------------------------


def faulty_stream():
    """Every fault at once: wraps, jitter, gaps, stop, reverse, NaNs (single and runs),
    saturation (single and runs), duplicate and backward timestamps."""
    rng = np.random.default_rng(7)
    t, az, th = make_stream(T=60.0)
    t = t + rng.uniform(-2e-4, 2e-4, t.size)
    th = th + rng.uniform(-0.002, 0.002, th.size)
    # stop 2 s inside a window
    i0 = int(np.flatnonzero(th >= 3 * P + 0.3)[0])
    th[i0 : i0 + 2000] = th[i0]
    th[i0 + 2000 :] -= th[i0 + 2000] - th[i0]
    # reverse 1.5 s
    i1 = int(np.flatnonzero(th >= 6 * P + 0.2)[0])
    d = np.arange(th.size - i1) / FS
    th[i1:] = th[i1] - OMEGA * np.minimum(d, 1.5) + OMEGA * np.maximum(d - 1.5, 0) + (th[i1:] - th[i1] - OMEGA * d)
    az[rng.integers(0, t.size, 5)] = np.nan
    th[rng.integers(0, t.size, 3)] = np.nan
    t[rng.integers(0, t.size, 2)] = np.nan
    az[rng.integers(0, t.size, 4)] = 200.0
    for i in rng.integers(0, t.size - 20, 2):  # runs too long to bridge
        az[i : i + 12] = np.nan
    for i in rng.integers(0, t.size - 20, 2):
        az[i : i + 12] = 200.0
    dup = rng.integers(1, t.size, 3)
    t[dup] = t[dup - 1]
    keep = np.ones(t.size, bool)
    for g in rng.integers(0, t.size - 100, 6):
        keep[g : g + rng.integers(5, 80)] = False
    t, az, th = t[keep], az[keep], th[keep]
    th = (th + math.pi) % (2 * math.pi) - math.pi  # wrapped, NaNs stay NaN
    return t, az, th


def test_push_and_push_many_identical_on_faulty_stream():
    t, az, th = faulty_stream()
    seg1 = CycleSegmenter()
    ref = run_push(seg1, t, az, th)
    flags = {f for c in ref for f in c.flags}
    assert {"stopped", "reverse", "gap", "nan", "saturated", "time"} <= flags
    assert sum(c.ok for c in ref) >= 5
    for chunk in (7, 100, 4096, 65536, t.size):
        seg2 = CycleSegmenter()
        got = run_many(seg2, t, az, th, chunk=chunk)
        assert got == ref, chunk
        assert seg2.counters == seg1.counters, chunk
    # one or two samples per call (slow): on the first 15 s, which hold the stop
    m = 15000
    seg1 = CycleSegmenter()
    ref = run_push(seg1, t[:m], az[:m], th[:m])
    assert any(c.quality != "ok" for c in ref)
    for chunk in (1, 2):
        seg2 = CycleSegmenter()
        assert run_many(seg2, t[:m], az[:m], th[:m], chunk=chunk) == ref
        assert seg2.counters == seg1.counters


def test_push_many_random_chunking_and_mixing_with_push():
    t, az, th = faulty_stream()
    ref = run_push(CycleSegmenter(), t, az, th)
    rng = np.random.default_rng(11)
    seg = CycleSegmenter()
    out = []
    i = 0
    while i < t.size:
        n = int(rng.integers(0, 3000))
        if rng.random() < 0.3:
            for j in range(i, min(i + n, t.size)):
                out += seg.push(t[j], az[j], th[j])
        else:
            out += seg.push_many(t[i : i + n], az[i : i + n], th[i : i + n])
        i += n
    assert out == ref


@st.composite
def fault_streams(draw):
    n = draw(st.integers(min_value=50, max_value=3000))
    seed = draw(st.integers(min_value=0, max_value=2**31 - 1))
    rng = np.random.default_rng(seed)
    fs = draw(st.sampled_from([50.0, 200.0, 1000.0]))
    omega = draw(st.floats(min_value=0.2, max_value=4.0))
    dt = (1.0 + rng.uniform(-0.3, 0.3, n)) / fs
    # some dwell (stops) and reversals through a random speed profile
    speed = omega * np.repeat(rng.choice([1.0, 1.0, 1.0, 0.0, -0.7], size=n // 25 + 1), 25)[:n]
    t = np.cumsum(dt)
    th = draw(st.floats(min_value=-7.0, max_value=7.0)) + np.cumsum(speed * dt)
    th += rng.normal(0, draw(st.sampled_from([0.0, 0.001, 0.02])), n)
    az = 9.81 + rng.normal(0, 3, n)
    for arr, val in ((az, np.nan), (th, np.nan), (t, np.nan), (az, 400.0)):
        k = int(rng.integers(0, 4))
        arr[rng.integers(0, n, k)] = val
    if rng.random() < 0.5:
        d = rng.integers(1, n, 3)
        t[d] = t[d - 1] - rng.choice([0.0, 0.01])
    if rng.random() < 0.5:
        th = (th + math.pi) % (2 * math.pi) - math.pi
    chunks = draw(st.lists(st.integers(min_value=1, max_value=400), min_size=1, max_size=10))
    n_legs = draw(st.sampled_from([3, 4, 6]))
    h = math.pi / n_legs
    window = draw(st.sampled_from([None, (-h, h), (0.2 * h, 0.8 * h)]))
    max_samples = draw(st.sampled_from([65536, 40]))
    return t, az, th, chunks, dict(n_legs=n_legs, window=window, max_samples=max_samples, initial_capacity=16)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fault_streams())
def test_push_equals_push_many_property(data):
    t, az, th, chunks, kw = data
    seg1 = CycleSegmenter(**kw)
    ref = run_push(seg1, t, az, th)
    seg2 = CycleSegmenter(**kw)
    got = []
    i = 0
    j = 0
    while i < t.size:
        n = chunks[j % len(chunks)]
        got += seg2.push_many(t[i : i + n], az[i : i + n], th[i : i + n])
        i += n
        j += 1
    assert got == ref
    assert seg1.counters == seg2.counters
    for c in ref:
        assert c.quality in QUALITIES
        assert c.quality == (c.flags[0] if c.flags else "ok")
        assert c.t.size == c.az.size == c.theta_phase.size
        if "too_long" in c.flags:
            assert c.t.size == 0 and c.n_samples > kw["max_samples"]
        else:
            assert c.t.size == c.n_samples
        if c.ok:  # unusable samples only in short holes, counted
            assert (~seg1.usable(c.az)).sum() <= c.n_missing and np.all(np.diff(c.t) > 0)
    assert seg1.buffer_capacity <= kw["max_samples"]


# ---------------------------------------------------------------------------
# counters, parameters, speed
# ---------------------------------------------------------------------------


def test_counters_add_up():
    t, az, th = faulty_stream()
    seg = CycleSegmenter()
    cycles = run_many(seg, t, az, th)
    c = seg.counters
    assert c["samples_seen"] == t.size
    assert c["samples_dropped"] == c["samples_invalid"] + c["samples_reverse"] + c["samples_overflow"]
    assert c["samples_invalid"] == int(np.count_nonzero(~(np.isfinite(t) & np.isfinite(th))))
    assert c["cycles_emitted"] == len(cycles)
    for q in QUALITIES:
        assert c[f"cycles_{q}"] == sum(cy.quality == q for cy in cycles)
    assert c["time_duplicate"] >= 1 and c["reversals"] == 1
    assert set(QUALITY_PRIORITY) | {"ok"} == set(QUALITIES)


def test_reset_forgets_the_stream():
    t, az, th = make_stream(T=10.0)
    seg = CycleSegmenter()
    a = run_many(seg, t, az, th)
    seg.reset()
    assert seg.counters["samples_seen"] == 0
    assert run_many(seg, t, az, th) == a


@pytest.mark.parametrize(
    "kw",
    [
        dict(n_legs=0),
        dict(window=(0.2, 0.1)),
        dict(window=(0.0, 1.0)),
        dict(max_gap=0.0),
        dict(theta_wrap="sometimes"),
        dict(reverse_tol=0.0),
        dict(max_samples=0),
        dict(full_scale=-1.0),
    ],
)
def test_bad_parameters_raise(kw):
    with pytest.raises(ValueError):
        CycleSegmenter(**kw)


def test_push_many_rejects_mismatched_arrays():
    seg = CycleSegmenter()
    with pytest.raises(ValueError, match="equal-length"):
        seg.push_many(np.zeros(3), np.zeros(2), np.zeros(3))
    assert seg.push_many([], [], []) == []


def test_push_is_fast_enough():
    """push() one sample at a time: well under 10 us per sample (CPU time)."""
    t, az, th = make_stream(T=30.0)
    tl, al, hl = t.tolist(), az.tolist(), th.tolist()
    seg = CycleSegmenter()
    push = seg.push
    t0 = time.process_time()
    for a, b, c in zip(tl, al, hl):
        push(a, b, c)
    per_sample = (time.process_time() - t0) / len(tl)
    assert per_sample < 10e-6, per_sample


# ---------------------------------------------------------------------------
# the compiled window checks against a plain numpy statement of the rules
# ---------------------------------------------------------------------------


def _numpy_window_checks(t, az, ph, pre, post, max_gap, gap_factor, max_dtheta, stop_dtheta, stop_time, full_scale,
                         clip):
    """The rules of "Missing samples and holes" (and the rest), stated plainly: (flags, n_missing)."""
    ts = np.concatenate([[pre[0]] if pre else [], t, [post[0]] if post else []])
    ps = np.concatenate([[pre[1]] if pre else [], ph, [post[1]] if post else []])
    off = 1 if pre else 0
    nan = np.isnan(az)
    sat = ~nan & ((np.abs(az) >= full_scale) | np.isin(az, clip))
    kind = np.zeros(ts.size, int)  # 0 usable (the neighbours too), 1 NaN, 2 saturated (inf included)
    kind[off : off + t.size][nan] = 1
    kind[off : off + t.size][sat] = 2
    names = {1: "nan", 2: "saturated"}
    flags = set()
    missing = int(nan.sum() + sat.sum())
    if ts.size >= 2:
        dts = np.diff(ts)
        if (dts <= 0).any():
            flags.add("time")
        if (np.abs(np.diff(ps)) > max_dtheta).any():
            flags.add("gap")
        pos = dts[dts > 0]
        if pos.size:
            med = float(np.median(pos))
            limit = gap_factor * med if max_gap is None else max_gap
            missing += sum(int(round(d / med)) - 1 for d in dts if d > 1.5 * med)
            good = np.flatnonzero(kind == 0)
            for a, b in zip(good, good[1:]):
                if ts[b] - ts[a] > limit:
                    inside = set(kind[a + 1 : b].tolist()) - {0}
                    flags |= {names[k] for k in inside} if inside else {"gap"}
            if good.size and good[-1] < ts.size - 1 and ts[-1] - ts[good[-1]] > limit:
                flags |= {names[k] for k in set(kind[good[-1] + 1 :].tolist())}
            if not good.size:
                flags |= {names[k] for k in set(kind.tolist())}
        elif (kind[off : off + t.size] > 0).all():
            flags |= {names[k] for k in set(kind.tolist()) - {0}}
        thr = np.maximum.accumulate(ps)
        j = np.searchsorted(thr, thr + stop_dtheta, side="left") - 1
        if ((ts[j] - ts) > stop_time).any():
            flags.add("stopped")
    elif kind[off]:
        flags.add(names[kind[off]])
    return flags, missing


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    n=st.integers(1, 60),
    seed=st.integers(0, 2**32 - 1),
    pre=st.booleans(),
    post=st.booleans(),
    given_gap=st.booleans(),
)
def test_window_checks_match_the_rules(n, seed, pre, post, given_gap):
    from slipest.segmentation import _F_GAP, _F_NAN, _F_SATURATED, _F_STOPPED, _F_TIME, _window_checks

    rng = np.random.default_rng(seed)
    p_fault = rng.choice([0.0, 0.02, 0.3])  # clean windows, rare faults, many
    dt = np.where(rng.random(n + 2) < p_fault, rng.choice([0.0, -0.0005, 0.004, 0.02, 0.6], size=n + 2), 0.001)
    tt = np.cumsum(dt)
    dth = np.where(rng.random(n + 2) < p_fault, rng.choice([0.0, -0.002, 0.01, 0.2], size=n + 2), 0.00063)
    th = np.cumsum(dth)
    az = rng.normal(9.81, 3.0, n)
    clip = np.array([12.5]) if rng.random() < 0.5 else np.empty(0)
    for _ in range(rng.integers(0, 3)):
        i = rng.integers(0, n)
        az[i : i + rng.integers(1, 8)] = rng.choice([np.nan, 200.0, -200.0, 12.5])  # runs of 1-7 bad samples
    t, ph = tt[1 : n + 1], th[1 : n + 1]
    args = (0.01 if given_gap else None, 5.0, 0.08, 0.01, 0.5, 16 * G, clip)
    want, want_missing = _numpy_window_checks(t, az, ph, (tt[0], th[0]) if pre else None,
                                              (tt[-1], th[-1]) if post else None, *args)
    bits, missing = _window_checks(t, az, ph, pre, tt[0], th[0], post, tt[-1], th[-1],
                                   math.nan if args[0] is None else args[0], *args[1:])
    names = {_F_TIME: "time", _F_GAP: "gap", _F_STOPPED: "stopped", _F_NAN: "nan", _F_SATURATED: "saturated"}
    assert {name for bit, name in names.items() if bits & bit} == want
    assert missing == want_missing


@pytest.mark.parametrize("spike", [1e3, -1e3, 1e6, 3.4e38, 1e300])
def test_a_glitched_theta_sample_is_dropped_and_counted_not_followed(spike):
    """One corrupted angle (a float32's largest value, a huge or a negative one) is a jump no leg makes: the
    sample is dropped and counted, every cycle keeps its number and its quality, one window loses the sample;
    push and push_many agree. (It used to open cycle 637 or 636620, then flag the next sample reverse and
    number cycle 10 twice; 3.4e38 hung the replay.)"""
    t, az, th = make_stream(T=20.0)
    clean = run_many(CycleSegmenter(NL), t, az, th)
    bad = th.copy()
    j = int(np.searchsorted(t, 9.1))
    bad[j] = spike
    for run in (run_many, run_push):
        seg = CycleSegmenter(NL)
        got = run(seg, t, az, bad)
        assert [c.k for c in got] == [c.k for c in clean]
        assert [c.quality for c in got] == [c.quality for c in clean]
        assert sum(c.n_samples for c in clean) - sum(c.n_samples for c in got) in (0, 1)
        assert seg.counters["samples_jump"] == 1 and seg.counters["reversals"] == 0


def test_a_new_angle_level_is_taken_after_five_samples_that_agree():
    """An encoder re-zeroed 30 rad back (a restart): five samples dropped, then the new level is taken as any
    backward jump is (reverse, resynchronised), and cycles are cut on it; 30 rad forward: a gap."""
    t, az, th = make_stream(T=20.0)
    j = int(np.searchsorted(t, 9.1))
    for shift, flag in ((-30.0, "reverse"), (30.0, "gap")):
        moved = th.copy()
        moved[j:] += shift
        seg = CycleSegmenter(NL)
        got = run_many(seg, t, az, moved)
        assert seg.counters["samples_jump"] == 4
        assert flag in [c.quality for c in got]
        after = [c for c in got if c.t_start > t[j] + 3.0]
        assert after and all(c.quality == "ok" for c in after)
        for c in after:  # numbered on the new level: each opened at an angle of its own cycle
            opened = float(np.interp(c.t_start, t, moved))
            assert c.k * P - H - 1e-6 <= opened < c.k * P + H
