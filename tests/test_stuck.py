"""The stuck-sensor rule on the samples SlipEstimator is given (slipest.stuck): a frozen az is flagged "stuck",
a clipped one is not, a run is counted across a cycle's start; the plain statement of the run count."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipest.cli.main import main
from slipest.online import SlipEstimator
from slipest.stuck import STUCK_MIN_SAMPLES, repeat_runs
from tests.log_makers import stream, write_csv


def _plain(az, lead_value, lead_count):
    az = list(az)
    if not az:
        return 0, lead_count
    finite = [v for v in az if not math.isnan(v)]
    lo, hi = (min(finite), max(finite)) if finite else (math.inf, -math.inf)
    longest, run = 0, 0
    for i, v in enumerate(az):
        if i == 0:
            run = lead_count + 1 if lead_count > 0 and v == lead_value else 1
        else:
            run = run + 1 if v == az[i - 1] else 1
        if lo < v < hi:
            longest = max(longest, run)
    return longest, run


@settings(max_examples=400, deadline=None)
@given(st.lists(st.sampled_from([9.0, 9.5, 10.0, 10.5, math.nan]), max_size=30), st.sampled_from([9.5, 10.0, math.nan]),
       st.integers(0, 5))
def test_repeat_runs_is_the_plain_statement(values, lead_value, lead_count):
    """Runs of bit-identical values (NaN breaks them), the cycle's extremes left out of the longest, a run
    carried on from before the array."""
    assert repeat_runs(np.array(values, dtype=float), lead_value, lead_count) == _plain(values, lead_value, lead_count)


@pytest.fixture(scope="module")
def drive():
    run, sc = stream(slip=[0.3] * 10, seed=6)
    est = SlipEstimator(n_legs=4)
    clean = {e.cycle: e for e in est.push_many(run.t, run.az, run.theta) + est.finish()}
    return run, sc, clean


def _frozen(run, clean, k, start, seconds):
    """az frozen for ``seconds`` from ``start`` s after cycle k opened."""
    az = run.az.copy()
    t0 = clean[k].t_start + start
    sel = np.flatnonzero((run.t >= t0) & (run.t < t0 + seconds))
    az[sel] = az[sel[0]]
    return az


def _rows(run, az, one_by_one=False, **kw):
    est = SlipEstimator(n_legs=4, **kw)
    if one_by_one:
        rows = [e for i in range(run.t.size) for e in est.push(run.t[i], az[i], run.theta[i])]
    else:
        rows = est.push_many(run.t, az, run.theta)
    return est, {e.cycle: e for e in rows + est.finish()}


def test_a_frozen_az_flags_its_cycle_stuck_and_only_it(drive):
    run, _, clean = drive
    az = _frozen(run, clean, 4, 0.3, 1.5)
    est, rows = _rows(run, az)
    assert rows[4].quality == "stuck" and math.isnan(rows[4].slip)
    assert all(rows[c].quality == clean[c].quality for c in rows if c != 4)
    assert est.counters["flagged_stuck"] == 1
    _, one = _rows(run, az, one_by_one=True)
    assert {c: e.as_dict() for c, e in one.items()} == {c: e.as_dict() for c, e in rows.items()}
    _, off = _rows(run, az, stuck_time=0.0)  # the rule off: estimated from the frozen samples
    assert off[4].quality == "ok"


def test_a_run_across_a_cycle_start_is_counted_on_and_a_short_one_is_not_stuck(drive):
    run, _, clean = drive
    k = 5
    n_before = int(np.count_nonzero((run.t > clean[k].t_start - 0.012) & (run.t <= clean[k].t_start)))
    az = _frozen(run, clean, k, -0.012, 0.030)  # 30 ms, of which 12 in cycle k - 1: k holds the rest
    _, rows = _rows(run, az)
    assert 0 < n_before < 20 and rows[k].quality == "stuck" and rows[k - 1].ok
    _, short = _rows(run, _frozen(run, clean, k, 0.3, 0.015))  # 15 ms: not a stuck sensor
    assert short[k].ok
    assert STUCK_MIN_SAMPLES == 12


def test_a_clipped_az_is_not_a_stuck_one(drive):
    """An IMU saturating at its range holds its largest value over each peak: not a frozen sensor."""
    run, _, clean = drive
    cap = np.percentile(run.az, 99.0)
    est, rows = _rows(run, np.minimum(run.az, cap))
    assert est.counters.get("flagged_stuck", 0) == 0 and sum(e.ok for e in rows.values()) >= len(clean) - 1


def test_a_replayed_log_with_a_frozen_sensor_says_stuck(tmp_path, drive, capsys):
    run, sc, clean = drive
    run.az[:] = _frozen(run, clean, 3, 0.5, 1.0)
    path = write_csv(tmp_path / "frozen.csv", run, sc)
    assert main(["replay", str(path), "--legs", "4", "-o", str(tmp_path / "out.csv")]) == 0
    err = capsys.readouterr().err
    assert "stuck 1" in err
    out = (tmp_path / "out.csv").read_text().splitlines()
    assert sum(",stuck," in line for line in out) == 1
    assert main(["replay", str(path), "--legs", "4", "--stuck-time", "0", "-o", str(tmp_path / "off.csv")]) == 0
    assert ",stuck," not in (tmp_path / "off.csv").read_text()


def test_a_noise_free_log_repeating_its_printed_digits_is_not_stuck(tmp_path, capsys):
    """A noise-free simulated log at a slow leg repeats az in its printed digits for hundreds of samples on
    the rigid half: not a frozen sensor (the rule needs noise)."""
    log = tmp_path / "quiet.csv"
    assert main(["simulate", "--slip", "0.2", "--kS", "800", "--phiS", "0.6", "--phiD", "0.35", "--cycles", "6",
                 "--noise", "0", "--omega", "0.35", "-o", str(log)]) == 0
    from slipest.io.log_csv import read_log

    az = read_log(log).az
    assert repeat_runs(az, math.nan, 0)[0] >= 20  # the repeats are there
    capsys.readouterr()
    assert main(["replay", str(log), "--legs", "4", "-o", str(tmp_path / "out.csv")]) == 0
    assert "stuck" not in capsys.readouterr().err
