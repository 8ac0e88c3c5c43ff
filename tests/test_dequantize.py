"""A whole-count encoder's angle interpolated between its count changes, online (slipest.dequantize), and the
estimator on such an encoder."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipest.cli.main import main
from slipest.dequantize import MAX_HOLD, AngleDequantizer, counts_whole_steps, dequantize_log
from slipest.io.log_csv import LogWriter
from slipest.online import SlipEstimator
from tests.log_makers import stream

RATE = 1000.0


def _angle(seconds=12.0, stop=None):
    """Time [s] and a leg angle [rad] whose speed changes 0.35-1.1 rad/s (and stands still over ``stop``)."""
    t = np.arange(0.0, seconds, 1.0 / RATE)
    speed = 0.7 + 0.35 * np.sin(2 * math.pi * t / 5.0)
    if stop is not None:
        speed[(t >= stop[0]) & (t < stop[1])] = 0.0
    theta = np.concatenate([[0.0], np.cumsum(speed[1:] / RATE)]) - 0.4
    return t, theta


def _counts(theta, counts):
    q = 2 * math.pi / counts
    return np.round(theta / q) * q


def _all(parts):
    """Concatenated ``(t, az, theta, ref)`` of the parts let out (None parts skipped)."""
    parts = [p for p in parts if p is not None]
    return tuple(np.concatenate([np.asarray(p[k], dtype=float) for p in parts]) for k in range(4))


def _sample_by_sample(d, t, az, theta, ref):
    """What :meth:`AngleDequantizer.push` lets out, sample by sample (a sample passed through as itself)."""
    parts = []
    for i in range(t.size):
        out = d.push(t[i], az[i], theta[i], ref[i])
        parts.append(out if out is not None else (t[i:i + 1], az[i:i + 1], theta[i:i + 1], ref[i:i + 1]))
    parts.append(d.flush())
    return _all(parts)


def test_a_coarse_encoder_is_interpolated_once_found_and_every_sample_comes_out_once_in_order():
    t, true = _angle()
    coarse = _counts(true, 191)
    d = AngleDequantizer()
    out = _all([d.feed(t, np.zeros_like(t), coarse), d.flush()])
    np.testing.assert_array_equal(out[0], t)
    q = 2 * math.pi / 191
    err = np.abs(out[2] - true)
    assert err[:200].max() > 0.4 * q  # found after some counts: the first ones pass as reported
    assert err[2000:-200].max() < 0.05 * q  # then within a twentieth of a count
    assert np.abs(coarse - true)[2000:-200].max() > 0.45 * q
    assert d.interpolated > 0.9 * t.size  # all but the counts before it was found (measured 95 %)


def test_a_fine_angle_and_a_leg_standing_still_pass_through_untouched():
    t, theta = _angle(stop=(4.0, 7.0))
    az = np.full(t.size, 9.81)
    d = AngleDequantizer()
    out = d.feed(t, az, theta)
    assert out[2] is theta and out[1] is az  # the very arrays, no delay
    # a 14-bit encoder at 1 kHz changes nearly every sample: not a whole-count staircase at this speed
    fine = _counts(theta, 2**14)
    out = AngleDequantizer().feed(t, az, fine)
    assert out[2] is fine
    assert not d.active and d.holding == 0


def test_one_sample_at_a_time_gives_what_arrays_give_with_gaps_a_stop_and_a_wrapped_angle():
    t, true = _angle(seconds=16.0, stop=(6.0, 7.5))
    coarse = _counts(true, 150)
    coarse[3000:3005] = np.nan  # lost angles
    coarse[9000] = np.nan
    wrapped = (coarse + math.pi) % (2 * math.pi) - math.pi  # as a device wraps it
    az = np.linspace(9.0, 10.0, t.size)
    ref = np.where(np.arange(t.size) % 700 < 350, 0.2, np.nan)
    d = AngleDequantizer()
    whole = _all([d.feed(t, az, coarse, ref), d.flush()])
    one = _sample_by_sample(AngleDequantizer(), t, az, coarse, ref)
    for a, b in zip(whole, one):
        np.testing.assert_array_equal(a, b)  # same samples, same order, the same angles
    d = AngleDequantizer()
    rng = np.random.default_rng(3)
    cuts = np.sort(rng.choice(np.arange(1, t.size), 40, replace=False))
    parts = [d.feed(*(x[a:b] for x in (t, az, wrapped, ref))) for a, b in zip(np.r_[0, cuts], np.r_[cuts, t.size])]
    chunks = _all(parts + [d.flush()])
    for a, b in zip(one[:2] + one[3:], chunks[:2] + chunks[3:]):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(chunks[2], one[2], rtol=0, atol=1e-12)  # unwrapped again (to rounding)
    np.testing.assert_array_equal(np.isnan(one[2]), np.isnan(coarse))  # lost angles stay lost, in place
    ok = np.isfinite(one[2]) & (t > 2.0) & (t < 15.5) & ((t < 5.9) | (t > 7.6))
    assert np.abs(one[2] - true)[ok].max() < 0.05 * 2 * math.pi / 150


def test_a_leg_standing_still_is_not_held_longer_than_max_hold():
    t, true = _angle(seconds=12.0, stop=(5.0, 9.0))
    coarse = _counts(true, 150)
    d = AngleDequantizer()
    longest = 0
    for i in range(t.size):
        d.push(t[i], 9.81, coarse[i])
        longest = max(longest, d.holding)
    assert d.active
    assert longest <= MAX_HOLD * RATE + 2


#: The soil's dphi [rad] of tests.log_makers.stream's drives (phiS 0.5, phiD 0.3).
DPHI = 0.2


@pytest.fixture(scope="module")
def drive():
    """A 30-cycle drive at 1 kHz, 0.01 g, slip redrawn every 3 cycles: the stream, its exact angle, the slips."""
    slips = np.repeat(np.random.default_rng(5).uniform(0.05, 0.45, 10), 3)
    run, _ = stream(slip=slips)
    return run, run.theta, slips


def _estimates(run, theta, one_by_one=False, **kw):
    est = SlipEstimator(n_legs=4, **kw)
    if one_by_one:
        rows = [e for i in range(run.t.size) for e in est.push(run.t[i], run.az[i], theta[i])] + est.finish()
    else:
        rows = est.push_many(run.t, run.az, theta) + est.finish()
    return est, {r.cycle: r for r in rows if r.ok}


def test_the_estimator_on_a_coarse_encoder_gives_what_it_gives_on_a_fine_one_and_says_so(drive):
    run, fine_theta, slips = drive
    coarse = _counts(fine_theta, 150)
    _, fine = _estimates(run, fine_theta)
    est, deq = _estimates(run, coarse)
    _, raw = _estimates(run, coarse, dequantize=False)
    cyc = [c for c in range(10, slips.size) if c in fine and c in deq and c in raw]
    assert len(cyc) >= 18

    def rms(rows, key, truth):
        return math.sqrt(np.mean([(getattr(rows[c], key) - truth[c]) ** 2 for c in cyc]))

    fine_slip = {c: fine[c].slip for c in cyc}
    assert rms(deq, "slip", fine_slip) < 0.003  # measured 0.0002
    assert rms(raw, "slip", fine_slip) > 0.01  # measured 0.037 (0.047 on the 14-feature model): the staircase's cost
    deq_dphi = rms(deq, "dphi", {c: DPHI for c in cyc})
    assert deq_dphi < 0.015  # measured 0.0079 (0.0085 on the 14-feature model)
    # the staircase's cost in the soil: measured 0.025, three times the dequantised (0.047 on the 14-feature model)
    assert rms(raw, "dphi", {c: DPHI for c in cyc}) > 2.0 * deq_dphi
    assert "encoder" in est.hints and "150" in est.hints["encoder"]
    assert est.counters["samples_interpolated"] > 0.9 * run.t.size


def test_push_and_push_many_agree_on_a_coarse_encoder(drive):
    run, fine_theta, _ = drive
    coarse = _counts(fine_theta, 150)
    _, many = _estimates(run, coarse)
    _, one = _estimates(run, coarse, one_by_one=True)
    assert many.keys() == one.keys()
    for c in many:
        assert many[c].as_dict() == one[c].as_dict()


@pytest.mark.parametrize("coarse", [False, True])
def test_mismatched_or_two_dimensional_arrays_are_refused_before_anything_is_taken(drive, coarse):
    """push_many refuses arrays of unequal length or not 1-D with the segmenter's error, also once a coarse
    encoder is being interpolated (whose hold-back used to take them), and counts no sample of a refused call;
    push refuses a sample that is not three numbers. The stream then goes on as if the calls never came."""
    run, fine_theta, _ = drive
    theta = _counts(fine_theta, 150) if coarse else fine_theta
    est = SlipEstimator(n_legs=4)
    n = 3000
    first = est.push_many(run.t[:n], run.az[:n], theta[:n])
    taken = est.counters["samples"]
    for bad in ((run.t[n:n + 100], run.az[n:n + 99], theta[n:n + 100]),
                (run.t[n:n + 100].reshape(10, 10), run.az[n:n + 100].reshape(10, 10), theta[n:n + 100].reshape(10, 10)),
                (run.t[None, n:n + 100], run.az[n:n + 100], theta[n:n + 100])):
        with pytest.raises(ValueError, match="push_many\\(\\) needs equal-length 1-D arrays"):
            est.push_many(*bad)
    with pytest.raises(ValueError, match="slip_ref must have the shape of t"):
        est.push_many(run.t[n:n + 100], run.az[n:n + 100], theta[n:n + 100], slip_ref=np.zeros(99))
    with pytest.raises(TypeError):
        est.push(run.t[n], run.az[n], [theta[n]])
    assert est.counters["samples"] == taken
    rows = first + est.push_many(run.t[n:], run.az[n:], theta[n:]) + est.finish()
    _, want = _estimates(run, theta)
    assert {r.cycle: r.as_dict() for r in rows if r.ok} == {c: r.as_dict() for c, r in want.items()}


def test_a_fine_encoder_gives_the_same_estimates_with_and_without_the_interpolation(drive):
    run, fine_theta, _ = drive
    est, on = _estimates(run, fine_theta)
    _, off = _estimates(run, fine_theta, dequantize=False)
    assert on.keys() == off.keys()
    for c in on:
        assert on[c].as_dict() == off[c].as_dict()
    assert est.counters["samples_interpolated"] == 0 and "encoder" not in est.hints


def test_a_replay_of_a_coarse_encoder_log_says_the_angle_was_interpolated_and_not_that_the_input_is_wrong(
        drive, tmp_path, capsys):
    run, fine_theta, _ = drive
    path = tmp_path / "coarse.csv"
    with LogWriter(path, ("t", "az", "theta")) as w:
        w.write(run.t, run.az, _counts(fine_theta, 150))
    rc = main(["replay", str(path), "--legs", "4", "-o", str(tmp_path / "out.csv")])
    err = capsys.readouterr().err
    assert rc == 0
    line = [ln for ln in err.splitlines() if "whole counts" in ln]
    assert len(line) == 1 and "150 a revolution" in line[0] and "looks wrong" not in line[0]


def test_a_whole_log_is_interpolated_as_the_stream_is_once_the_stream_has_started():
    t, fine = _angle(stop=(6.0, 7.0))
    coarse = _counts(fine, 150)
    out = dequantize_log(t, coarse)
    stream = AngleDequantizer()
    got = _all([stream.feed(t, np.zeros(t.size), coarse), stream.flush()])[2]
    assert out.shape == t.shape
    # the stream starts after its detection's counts; from there the two are the same kernel, sample for sample
    start = int(np.flatnonzero(got != coarse)[0])
    assert 0 < start < t.size // 4
    np.testing.assert_array_equal(out[start:], got[start:])
    # the whole log is interpolated before the stream's start too, its first count extrapolated back
    moving = (t < 5.9) | (t >= 7.1)  # a count on either side of the stop is as reported, as in the stream
    q = 2 * math.pi / 150
    assert np.max(np.abs(coarse - fine)[:start]) > 0.4 * q
    assert np.max(np.abs(out - fine)[moving]) < 0.1 * q
    assert np.max(np.abs(out - fine)[:start]) < 0.1 * q


def test_a_fine_or_short_log_is_returned_as_it_is_and_mismatched_arrays_are_refused():
    t, fine = _angle(seconds=3.0)
    assert not counts_whole_steps(t, fine)
    assert dequantize_log(t, fine) is not None
    np.testing.assert_array_equal(dequantize_log(t, fine), fine)
    np.testing.assert_array_equal(dequantize_log(t[:5], _counts(fine[:5], 150)), _counts(fine[:5], 150))
    with pytest.raises(ValueError, match="same length"):
        dequantize_log(t, fine[:-1])


def test_a_whole_log_angle_is_unwrapped_around_its_lost_samples_and_then_interpolated():
    t, fine = _angle(seconds=4.0)
    lost = fine.copy()
    lost[[100, 2000]] = np.nan
    wrapped = np.mod(lost + math.pi, 2 * math.pi) - math.pi
    out = dequantize_log(t, wrapped)
    ok = np.isfinite(lost)
    np.testing.assert_allclose(out[ok], lost[ok] - (lost[0] - out[0]), atol=1e-12)  # unwrapped, as one
    assert np.isnan(out[[100, 2000]]).all()  # the lost samples keep their place
    coarse = np.mod(_counts(lost, 150) + math.pi, 2 * math.pi) - math.pi  # wrapped whole counts
    q = 2 * math.pi / 150
    err = dequantize_log(t, coarse) - (lost - (lost[0] - out[0]))
    assert np.nanmax(np.abs(err)) < 0.1 * q


@pytest.mark.parametrize("spike", [3.4e38, 1e3, -50.0])
def test_a_glitched_angle_neither_hangs_nor_shifts_the_unwrapping(drive, spike):
    """One corrupted angle among a coarse encoder's counts: taken as no wrap (a wrapped angle never jumps by
    3 pi or more), so the unwrapping of the angles after it is untouched; the estimator drops the sample
    (a theta jump) and numbers every cycle as without it. (A float32's largest value looped forever
    unwrapping it by 2 pi at a time.)"""
    run, fine_theta, _ = drive
    coarse = _counts(fine_theta, 150)
    bad = coarse.copy()
    bad[9100] = spike
    clean_est, clean = _estimates(run, coarse)
    est, got = _estimates(run, bad)
    assert got.keys() == clean.keys()
    assert est.counters["segmenter_samples_jump"] >= 1
    d = AngleDequantizer()
    out = _all([d.feed(run.t, run.az, bad), d.flush()])
    assert out[2].size == run.t.size
    around = np.r_[8000:9100, 9101:10200]  # the interpolated angle around the glitch, the glitch left out
    assert np.all(np.abs(np.diff(out[2][around])) < 0.1)


def test_a_new_angle_level_starts_the_interpolation_over(drive):
    """A coarse encoder re-zeroed 30 rad on (a restart): five samples kept as reported, then the new level is
    taken and its counts interpolated again, as smoothly as before the jump."""
    run, fine_theta, _ = drive
    j = 9100
    moved = _counts(fine_theta, 150)
    moved[j:] += 30.0
    d = AngleDequantizer()
    out = _all([d.feed(run.t, run.az, moved), d.flush()])[2]
    truth = fine_theta + np.where(np.arange(fine_theta.size) >= j, 30.0, 0.0)
    before, after = np.r_[3000:j - 500], np.r_[j + 2000:fine_theta.size - 2000]
    err_before = np.abs(out[before] - truth[before]).max()
    err_after = np.abs(out[after] - truth[after]).max()
    step = 2 * math.pi / 150
    assert err_before < 0.25 * step and err_after < 0.25 * step  # interpolated (a staircase errs by half a count)
