"""Tests of ``slipest replay`` on small logs made here with the simulator."""

import csv
import io
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from slipest.cli.main import main
from slipest.cli.replay import COLUMNS
from slipest.io.log_csv import LogWriter
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

N_CYCLES = 7


@pytest.fixture(scope="module")
def log_path(tmp_path_factory):
    rng = np.random.default_rng(3)
    slip = np.repeat(rng.uniform(0.1, 0.45, 4), 2)[:N_CYCLES]
    sc = Scenario.per_cycle(StickSlipParams(kS=900.0, phiS=0.5, phiD=0.3), dict(noise_g=0.01, seed=4), slip=slip)
    s = simulate_stream(sc)
    path = tmp_path_factory.mktemp("logs") / "run.csv"
    with LogWriter(path, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, s.slip)
    return path


def _lines(path):
    return path.read_text().splitlines()


def run(args, capsys):
    rc = main(["replay", *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err


def test_csv_to_stdout_one_row_per_cycle(log_path, capsys):
    rc, out, err = run([log_path], capsys)
    assert rc == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    assert tuple(rows[0].keys()) == COLUMNS
    for needed in ("cycle", "t_end", "delta_a", "slip", "slip_std", "dphi", "dphi_std", "quality"):
        assert needed in COLUMNS
    # the log starts at theta = -pi/4 (written as -0.7853982) and ends on cycle N-1's last sample: N cycles, N
    # estimates (the last one at the end of the log)
    assert [int(r["cycle"]) for r in rows] == list(range(N_CYCLES))
    ok = [r for r in rows if r["quality"] == "ok"]
    assert len(ok) == N_CYCLES and "IMU noise 0.01" in err
    for r in ok:
        assert 0.0 <= float(r["slip"]) <= 0.55 and float(r["slip_std"]) > 0 and float(r["dphi_std"]) > 0
    # summary on stderr only
    assert "leg cycles" in err and f"{N_CYCLES} estimated" in err
    assert "truth" not in err
    assert "do not fit" not in err and "off the model" not in err  # a clean log fits the model


def test_slip_column_ignored_unless_asked(log_path, tmp_path, capsys):
    o1, o2 = tmp_path / "a.csv", tmp_path / "b.csv"
    assert run([log_path, "-o", o1], capsys)[0] == 0
    assert run([log_path, "-o", o2, "--truth"], capsys)[0] == 0
    r1 = list(csv.DictReader(o1.open()))
    r2 = list(csv.DictReader(o2.open()))
    assert [r["slip"] for r in r1] == [r["slip"] for r in r2]  # --truth only compares
    rc, out, err = run([log_path, "-o", tmp_path / "c.csv", "--use-reference"], capsys)
    assert rc == 0 and "reference slip used on" in err
    r3 = list(csv.DictReader((tmp_path / "c.csv").open()))
    assert all(r["used_reference"] == "1" for r in r3 if r["quality"] == "ok")
    assert [r["dphi"] for r in r3] != [r["dphi"] for r in r1]


def test_jsonl_and_truth_summary(log_path, capsys):
    rc, out, err = run([log_path, "--format", "jsonl", "--truth"], capsys)
    assert rc == 0
    recs = [json.loads(line) for line in out.splitlines()]
    assert len(recs) == N_CYCLES and list(recs[0].keys()) == list(COLUMNS)
    assert all(isinstance(r["slip"], float) for r in recs)
    assert recs[0]["slip_ref"] is not None and all(r["misfit"] is None or r["misfit"] >= 1 for r in recs)
    assert "truth: slip RMSE" in err and "95% interval coverage" in err
    # the summary's RMSE is the RMSE of the written rows against slip_ref
    e = np.array([r["slip"] - r["slip_ref"] for r in recs])
    rmse = float(err.split("truth: slip RMSE ")[1].split(",")[0])
    assert rmse == pytest.approx(float(np.sqrt(np.mean(e**2))), abs=1e-4)
    # the metadata give phiS and phiD: dphi is compared too
    assert "truth: dphi (log metadata 0.2 rad)" in err


def test_eq515_method(log_path, capsys):
    rc, out, err = run([log_path, "--method", "eq515", "--kS", 900, "--phiS", 0.5, "--phiD", 0.3], capsys)
    assert rc == 0
    rows = [r for r in csv.DictReader(io.StringIO(out)) if r["quality"] == "ok"]
    assert rows and all(float(r["dphi"]) == pytest.approx(0.2) and float(r["dphi_std"]) == 0.0 for r in rows)
    assert "method eq515" in err
    rc, out, err = run([log_path, "--method", "eq515"], capsys)
    assert rc == 2 and "kS" in err and out == ""


def test_malformed_row_errors_with_line_number(log_path, tmp_path, capsys):
    lines = _lines(log_path)
    header = next(i for i, line in enumerate(lines) if line.startswith("t,"))
    bad_line = header + 1 + 3000  # 1-based line number of the row we break
    lines[bad_line - 1] = "0.5,abc,0.1,0.2"
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    rc, out, err = run([bad], capsys)
    assert rc == 2
    assert f"line {bad_line}" in err and "slipest replay" in err
    rc, out, err = run([bad, "--skip-bad"], capsys)
    assert rc == 0
    assert "1 malformed row(s) skipped" in err and f"line {bad_line}" in err
    assert len(list(csv.DictReader(io.StringIO(out)))) == N_CYCLES


def test_missing_file_and_truth_without_slip_column(tmp_path, capsys):
    rc, out, err = run([tmp_path / "nope.csv"], capsys)
    assert rc == 2 and "no such file" in err
    p = tmp_path / "noslip.csv"
    t = np.arange(3000) / 1000.0
    with LogWriter(p, ("t", "az", "theta"), metadata={"nL": 4}) as w:
        w.write(t, np.full(t.size, 9.81), -math.pi / 4 + 0.63 * t)
    rc, out, err = run([p, "--truth"], capsys)
    assert rc == 2 and "slip" in err


def test_legs_from_metadata_or_option(log_path, capsys):
    rc, out, err = run([log_path], capsys)
    assert "4 legs" in err
    # the shipped models are for 4 legs: another number is refused, not estimated wrongly
    rc, out, err = run([log_path, "--legs", 3], capsys)
    assert rc == 2 and "4-leg" in err and out == ""


def _model_for_legs(path, n_legs, omega):
    """A small inverse model for another wheel-leg geometry, trained by tools/train_inverse.py (two speed nodes
    around ``omega``, a small schedule: quick, coarse; 5 held-out checks: each builds a grid table, ~0.3 s, and
    the replay's rows below are the same to the digit with 5 as with 30)."""
    import train_inverse  # tools/train_inverse.py

    lo, hi = 0.9 * omega, 1.1 * omega
    rc = train_inverse.main(["--legs", str(n_legs), "--nodes", "2", "--span", str(lo), str(hi), "--n-node", "1500",
                             "--schedule", "tiny", "--n-val", "60", "--n-check", "5", "--out", str(path)])
    assert rc == 0
    return path


def test_model_option_estimates_another_geometry(tmp_path, capsys):
    params = StickSlipParams(kS=900.0, phiS=0.5, phiD=0.3).with_(nL=6)
    sc = Scenario.per_cycle(params, dict(noise_g=0.01, seed=5), slip=np.full(8, 0.3))
    s = simulate_stream(sc)
    log6 = tmp_path / "six.csv"
    with LogWriter(log6, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, s.slip)
    # the shipped model is for 4 legs: refused
    rc, out, err = run([log6], capsys)
    assert rc == 2 and "4-leg" in err and out == ""
    model6 = _model_for_legs(tmp_path / "six_legs.npz", 6, params.omega)
    capsys.readouterr()  # (the training's own output)
    rc, out, err = run([log6, "--model", model6], capsys)
    assert rc == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    ok = [r for r in rows if r["quality"] == "ok"]
    assert len(ok) >= 6 and "6 legs" in err
    assert all(0.0 <= float(r["slip"]) <= 0.55 and float(r["slip_std"]) > 0 for r in ok)
    # a model file that is not one: a clear error naming it
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    rc, out, err = run([log6, "--model", bad], capsys)
    assert rc == 2 and "bad.json" in err and "not an inverse model file" in err and out == ""


@pytest.mark.parametrize("mistake, hint", [
    ("az_in_g", "az looks like it is in g"),
    ("gravity_removed", "az has no gravity in it"),
    ("axis_down", "az points down"),
    ("theta_degrees", "theta looks like it is in degrees"),
])
def test_a_unit_mistake_is_named_and_nothing_is_estimated(log_path, tmp_path, capsys, mistake, hint):
    from slipest.io.log_csv import read_log

    d = read_log(log_path)
    az, theta = d.az, d.theta
    az = {"az_in_g": az / 9.80665, "gravity_removed": az - 9.80665, "axis_down": -az}.get(mistake, az)
    if mistake == "theta_degrees":
        theta = np.degrees(theta)
    bad = tmp_path / f"{mistake}.csv"
    with LogWriter(bad, ("t", "az", "theta"), metadata={"nL": 4}) as w:
        w.write(d.t, az, theta)
    rc, out, err = run([bad], capsys)
    assert rc == 1, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert rows and not any(r["quality"] == "ok" for r in rows)
    assert hint in err and "no leg cycle was estimated" in err
    if mistake == "az_in_g":  # JSON lines: NaN is null
        rc, out, err = run([bad, "--format", "jsonl"], capsys)
        recs = [json.loads(line) for line in out.splitlines()]
        assert rc == 1 and recs and all(r["slip"] is None and r["quality"] == "units" for r in recs)


def test_a_log_the_model_cannot_explain_says_so_and_names_calibrate(tmp_path, capsys):
    """Touchdown impacts the simulator's model does not have: every cycle is flagged misfit (not estimated),
    the summary says the data do not fit the model and that slipest calibrate would help, and the exit
    status says nothing was estimated."""
    sc = Scenario.per_cycle(StickSlipParams(kS=1000.0, phiS=0.55, phiD=0.4), dict(noise_g=0.01, seed=4),
                            slip=np.repeat([0.1, 0.3, 0.2, 0.4], 2))
    sc = Scenario(cycles=sc.cycles, rate=sc.rate, noise_g=sc.noise_g, seed=sc.seed,
                  effects=({"name": "touchdown_impact", "amplitude": -13.2, "tau": 0.9, "freq": 9.6},))
    s = simulate_stream(sc)
    path = tmp_path / "impacts.csv"
    with LogWriter(path, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, s.slip)
    rc, out, err = run([path], capsys)
    rows = list(csv.DictReader(io.StringIO(out)))
    assert rc == 1 and len(rows) == 8 and all(r["quality"] == "misfit" for r in rows)
    assert "flagged (misfit 8)" in err
    assert "the data do not fit the estimator's model (8 of 8 cycles off it)" in err
    assert "'slipest calibrate'" in err and "the input looks wrong" not in err


def test_a_given_dphi_is_not_scored_as_an_estimate(log_path, capsys):
    """--truth with the soil given: the dphi rows are the value given (std 0), so its 'RMSE' and '95% coverage
    0.000' scored the user's input as an estimate; the summary says it was given, beside the log's value."""
    rc, out, err = run([log_path, "--method", "eq515", "--kS", 900, "--phiS", 0.5, "--phiD", 0.35, "--truth"], capsys)
    assert rc == 0 and "truth: slip RMSE" in err
    assert "truth: dphi was given (0.15 rad), not estimated; the log's metadata says 0.2 rad" in err
    assert "truth: dphi (log metadata" not in err
