"""`slipest simulate`: the log it writes, its reference values, its scenario files and its errors."""

import math
import time

import numpy as np
import pytest

from slipest.cli.main import main
from slipest.io.log_csv import read_log
from slipest.units import G
from tests.test_model_stance import REFERENCE


def _propulsive_da(log, n_legs=4):
    """Da [g] of every leg cycle, over the propulsive half (phase in [0, pi/nL))."""
    half = math.pi / n_legs
    k = np.floor((log.theta + half) / (2 * half))
    phase = log.theta - 2 * half * k
    out = []
    for cycle in np.unique(k):
        a = log.az[(k == cycle) & (phase >= 0)]
        if len(a) > 10:  # a whole propulsive half, not a boundary sample rounded into the next cycle
            out.append((a.max() - a.min()) / G)
    return np.array(out)


@pytest.mark.parametrize("changes, da_ref, _", REFERENCE)
def test_simulate_reproduces_the_reference_da_at_10khz(tmp_path, changes, da_ref, _):
    out = tmp_path / "run.csv"
    opts = [f"--{k}={v}" for k, v in changes.items()]
    assert main(["simulate", *opts, "--cycles", "1", "--noise", "0", "--rate", "10000", "-o", str(out)]) == 0
    log = read_log(out)
    assert _propulsive_da(log) == pytest.approx([da_ref], rel=0.02)


def test_simulate_log_has_metadata_slip_and_gravity(tmp_path):
    out = tmp_path / "run.csv"
    main(["simulate", "--slip", "0.3", "--kS", "1200", "--cycles", "3", "--legs", "5", "--seed", "4", "--noise", "0.01", "-o", str(out)])
    log = read_log(out)
    assert log.metadata.n_legs == 5
    assert log.metadata["kS"] == "1200" and log.metadata["seed"] == "4" and log.metadata["noise_g"] == "0.01"
    assert np.all(log.slip == 0.3)
    np.testing.assert_allclose(np.diff(log.t), 1e-3, atol=1e-6)
    # gravity included: on the rigid half the hub rides a planted spoke (kinematic accel < 1% g)
    half = math.pi / 5
    phase = log.theta - 2 * half * np.floor((log.theta + half) / (2 * half))
    assert np.median(log.az[phase < 0]) == pytest.approx(G, rel=0.01)
    assert log.theta[0] == pytest.approx(-math.pi / 5, abs=1e-7)


def test_simulate_to_stdout(capsys):
    assert main(["simulate", "--cycles", "1", "--rate", "200"]) == 0
    text = capsys.readouterr().out
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    assert lines[0] == "t,az,theta,slip"
    assert len(lines) - 1 == math.ceil(2 * math.pi / (4 * 0.63) * 200)


def test_simulate_scenario_file(tmp_path):
    scenario = tmp_path / "drive.toml"
    scenario.write_text(
        """
[imu]
rate = 500.0
noise = 0.0
[[segment]]
cycles = 2
slip = 0.1
[[segment]]
cycles = 2
slip = 0.4
kS = 1400.0
"""
    )
    out = tmp_path / "run.csv"
    assert main(["simulate", "--scenario", str(scenario), "-o", str(out)]) == 0
    log = read_log(out)
    assert log.metadata["slip"] == "varies" and log.metadata["rate"] == "500"
    assert sorted(set(np.round(log.slip, 6))) == [0.1, 0.4]
    da = _propulsive_da(log)
    assert da[2] > da[0] * 1.5  # more slip on stiffer soil shakes the hub more


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--slip", "1.5"], "slip=1.5 must be in"),
        (["--cycles", "0"], "--cycles=0"),
        (["--kappa", "0"], "ill-posed"),
        (["--scenario", "/nonexistent/drive.toml"], "cannot read scenario"),
    ],
)
def test_simulate_errors_are_one_clear_line(tmp_path, capsys, argv, message):
    out = tmp_path / "run.csv"
    with pytest.raises(SystemExit) as exc:
        main(["simulate", *argv, "-o", str(out)])
    assert message in str(exc.value)
    assert not out.exists()  # no partial log left behind


def test_simulate_bad_scenario_names_the_file_and_key(tmp_path):
    scenario = tmp_path / "bad.toml"
    scenario.write_text("[[segment]]\ncycles = 2\nslipp = 0.1\n")
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", str(scenario)])
    assert "bad.toml" in str(exc.value) and "slipp" in str(exc.value)


@pytest.mark.parametrize("doc, where", [
    ('[[segment]]\ncycles = 2\nslip = 0.1\nkS = "soft"\n', "segment 1: kS = 'soft'"),
    ('[[segment]]\ncycles = 2\nslip = 0.1\n[[segment]]\ncycles = 2\nslip = [0.1, "x"]\n', "segment 2: slip = 'x'"),
    ('[model]\nomega = "fast"\n[[segment]]\ncycles = 2\nslip = 0.1\n', "[model]: omega = 'fast'"),
    ('[model]\nnL = 4.5\n[[segment]]\ncycles = 2\nslip = 0.1\n', "[model]: nL = 4.5"),
    ('[imu]\nrate = "1k"\n[[segment]]\ncycles = 2\nslip = 0.1\n', "[imu]: rate = '1k'"),
    ('[imu]\nseed = 1.5\n[[segment]]\ncycles = 2\nslip = 0.1\n', "[imu]: seed = 1.5"),
])
def test_simulate_a_value_of_the_wrong_type_names_the_file_segment_and_key(tmp_path, doc, where):
    scenario = tmp_path / "bad.toml"
    scenario.write_text(doc)
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", str(scenario)])
    assert "bad.toml" in str(exc.value) and where in str(exc.value), str(exc.value)


# --- bad values, interrupted runs, the header and the cycle length ---------------------------------------------

def _good_log(tmp_path, name="run.csv"):
    """A simulated log made a moment ago at ``name``: what a failed or interrupted run must leave untouched."""
    out = tmp_path / name
    assert main(["simulate", "--cycles", "1", "--rate", "200", "-o", str(out)]) == 0
    return out, out.read_bytes()


def _no_partial_files(tmp_path):
    """No temporary log left in the directory (the simulation writes into one beside -o)."""
    return [p.name for p in tmp_path.iterdir() if p.name.endswith(".part")] == []


@pytest.mark.parametrize("argv, message", [
    (["--kappa", "nan"], "kappa=nan must be a finite number"),
    (["--kappa", "inf"], "kappa=inf must be a finite number"),
    (["--kS", "nan"], "kS=nan must be a finite number"),
    (["--noise", "nan"], "noise=nan"),
])
def test_simulate_refuses_non_finite_options_and_names_them(tmp_path, argv, message):
    out, before = _good_log(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["simulate", *argv, "--cycles", "1", "-o", str(out)])
    assert message in str(exc.value)
    assert out.read_bytes() == before


@pytest.mark.parametrize("model, where", [
    ("viscous = nan", "[model]: viscous = nan must be a finite number"),
    ("stribeck_vs = 0.01\nstribeck_exp = nan", "[model]: stribeck_exp = nan must be a finite number"),
    ("ripple_amp = 0.1\nripple_phase = nan", "[model]: ripple_phase = nan must be a finite number"),
    ("kappa = inf", "[model]: kappa = inf must be a finite number"),
    ("nL = inf", "[model]: nL = inf must be a finite number"),
    ("n_hc = -1.0", "[model]: invalid stick-slip parameters: n_hc=-1.0 must be >= 0"),
    ("stribeck_exp = 0.0", "[model]: invalid stick-slip parameters: stribeck_exp=0.0 must be a positive"),
])
def test_simulate_scenario_non_finite_or_out_of_range_model_parameter_names_file_and_key(tmp_path, model, where):
    scenario = tmp_path / "bad.toml"
    scenario.write_text(f"[model]\n{model}\n[[segment]]\ncycles = 2\n")
    out = tmp_path / "run.csv"
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", str(scenario), "-o", str(out)])
    assert "bad.toml" in str(exc.value) and where in str(exc.value), str(exc.value)
    assert not out.exists()


@pytest.mark.parametrize("effects, message", [
    ('[[effect]]\nname = "imu_lowpass"\ncutoff = -5', "[[effect]] 1: imu_lowpass: cutoff=-5 Hz is outside"),
    ('[[effect]]\nname = "angle_offset"\noffset = 0.1\n[[effect]]\nname = "angle_offset"\noffset = 0.2',
     "named more than once: angle_offset"),
    ('[[effect]]\nname = "imu_lowpass"\ncutoff = "abc"', "[[effect]] 1: imu_lowpass: cutoff='abc' is not a number"),
    ("[[effect]]\nname = 5", "[[effect]] 1: unknown effect 5"),
    ('[[effect]]\nname = "imu_lowpass"\n[[effect]]\nname = "imu_lowpas"', "[[effect]] 2: unknown effect 'imu_lowpas'"),
])
def test_simulate_bad_scenario_effect_is_one_clear_line_and_leaves_the_log(tmp_path, capsys, effects, message):
    out, before = _good_log(tmp_path)
    scenario = tmp_path / "bad.toml"
    scenario.write_text(f"[[segment]]\ncycles = 2\n{effects}\n")
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", str(scenario), "-o", str(out)])
    assert "bad.toml" in str(exc.value) and message in str(exc.value), str(exc.value)
    assert out.read_bytes() == before  # checked when the scenario is loaded: -o never opened
    assert "Traceback" not in capsys.readouterr().err


def test_simulate_same_effect_twice_on_the_command_line_is_refused_before_writing(tmp_path):
    out, before = _good_log(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--cycles", "1", "--effect", "imu_lowpass", "--effect", "imu_lowpass:cutoff=20",
              "-o", str(out)])
    assert "named more than once: imu_lowpass" in str(exc.value)
    assert out.read_bytes() == before


def test_simulate_interrupted_leaves_the_previous_log_and_no_partial_file(tmp_path, monkeypatch, capsys):
    import slipest.model.stream as stream

    out, before = _good_log(tmp_path)
    real = stream.iter_stream

    def interrupted(scenario, *args, **kwargs):
        chunks = real(scenario, 1)
        yield next(chunks)  # some of the log is written, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(stream, "iter_stream", interrupted)
    assert main(["simulate", "--cycles", "5", "--rate", "200", "-o", str(out)]) == 130
    assert out.read_bytes() == before
    assert _no_partial_files(tmp_path)
    err = capsys.readouterr().err
    assert "interrupted: nothing written" in err and "left as it was" in err
    # no previous file: none is made
    fresh = tmp_path / "fresh.csv"
    assert main(["simulate", "--cycles", "5", "--rate", "200", "-o", str(fresh)]) == 130
    assert not fresh.exists() and _no_partial_files(tmp_path)
    assert f"no {fresh} made" in capsys.readouterr().err


def test_simulate_model_failure_leaves_the_previous_log(tmp_path):
    out, before = _good_log(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--kappa", "0", "--cycles", "1", "-o", str(out)])
    assert "ill-posed" in str(exc.value) and "nothing written" in str(exc.value)
    assert out.read_bytes() == before and _no_partial_files(tmp_path)


def test_simulate_sigterm_stops_the_run_and_writes_nothing(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    out, before = _good_log(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "slipest", "simulate", "--cycles", "100000", "-o", str(out)],
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not any(p.name.endswith(".part") and p.stat().st_size > 100_000 for p in tmp_path.iterdir()):
            assert proc.poll() is None and time.monotonic() < deadline, "the run never started writing"
            time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)
        err = proc.communicate(timeout=60)[1]
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert "interrupted: nothing written" in err
    assert out.read_bytes() == before and _no_partial_files(tmp_path)


def test_simulate_replaces_a_simulated_log_whole_and_keeps_the_overwrite_rule(tmp_path):
    import os

    out, before = _good_log(tmp_path)
    os.chmod(out, 0o640)
    assert main(["simulate", "--cycles", "2", "--rate", "200", "-o", str(out)]) == 0
    log = read_log(out)
    assert log.metadata["cycles"] == "2" and out.read_bytes() != before
    assert os.stat(out).st_mode & 0o777 == 0o640  # the file replaced keeps its permissions
    recorded = tmp_path / "recorded.csv"
    recorded.write_text("t,az,theta\n0,9.81,0\n")
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--cycles", "1", "-o", str(recorded)])
    assert "not a simulated log" in str(exc.value) and recorded.read_text() == "t,az,theta\n0,9.81,0\n"
    assert main(["simulate", "--cycles", "1", "--rate", "200", "--overwrite", "-o", str(recorded)]) == 0
    assert read_log(recorded).metadata["source"] == "slipest simulate"
    assert _no_partial_files(tmp_path)


def test_simulate_to_a_device_writes_into_it_and_does_not_replace_it():
    import os
    import stat

    assert main(["simulate", "--cycles", "1", "--rate", "200", "--overwrite", "-o", os.devnull]) == 0
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)


def test_simulate_header_records_every_model_parameter_the_scenario_changes(tmp_path):
    scenario = tmp_path / "mars.toml"
    scenario.write_text("[model]\ng = 3.71\nb_hc = 40.0\nstribeck_vs = 0.01\nripple_amp = 0.2\n"
                        "[imu]\nrate = 200.0\n[[segment]]\ncycles = 2\nslip = 0.3\n")
    out = tmp_path / "run.csv"
    assert main(["simulate", "--scenario", str(scenario), "-o", str(out)]) == 0
    meta = read_log(out).metadata
    assert (meta["g"], meta["b_hc"], meta["stribeck_vs"], meta["ripple_amp"]) == ("3.71", "40", "0.01", "0.2")
    for name in ("n_hc", "stribeck_exp", "viscous", "ripple_phase", "ripple_harmonic"):
        assert name not in meta  # at their defaults
    default = tmp_path / "default.csv"
    assert main(["simulate", "--cycles", "1", "--rate", "200", "-o", str(default)]) == 0
    assert "g" not in read_log(default).metadata and "b_hc" not in read_log(default).metadata


@pytest.mark.parametrize("argv, doc, message", [
    (["--seed", "-1"], None, "argument --seed: '-1' is not a seed (a whole number >= 0)"),
    ([], "[imu]\nseed = -5\n[[segment]]\ncycles = 2\n", "[imu]: seed = -5 must be a non-negative integer"),
])
def test_simulate_refuses_a_negative_seed(tmp_path, capsys, argv, doc, message):
    out, before = _good_log(tmp_path)
    if doc is not None:
        scenario = tmp_path / "seed.toml"
        scenario.write_text(doc)
        argv = ["--scenario", str(scenario)]
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--cycles", "2", *argv, "-o", str(out)])
    err = capsys.readouterr().err
    assert message in str(exc.value) + err, (exc.value, err)  # an option: argparse's usage error on stderr
    assert out.read_bytes() == before and "Traceback" not in err


def _refused_simulate(tmp_path, argv, doc, name: str) -> str:
    """``slipest simulate ARGV -o run.csv`` (with ``doc`` written as the scenario file ``name`` when given):
    its refusal's text; the output was not written."""
    out = tmp_path / "run.csv"
    if doc is not None:
        scenario = tmp_path / name
        scenario.write_text(doc)
        argv = ["--scenario", str(scenario)]
    with pytest.raises(SystemExit) as exc:
        main(["simulate", *argv, "-o", str(out)])
    assert not out.exists()
    return str(exc.value)


@pytest.mark.parametrize("argv, doc", [
    (["--omega", "0.001", "--cycles", "1"], None),
    ([], "[[segment]]\ncycles = 1\n[[segment]]\ncycles = 1\nomega = 0.001\n"),
])
def test_simulate_refuses_a_leg_so_slow_one_cycle_would_take_gigabytes(tmp_path, argv, doc):
    text = _refused_simulate(tmp_path, argv, doc, "slow.toml")
    assert "omega=0.001 rad/s lasts 1571 s" in text and "give a leg speed omega >= 0.0027 rad/s" in text, text
    if doc is not None:
        assert "slow.toml" in text and "leg cycle 2 " in text


@pytest.mark.parametrize("argv, doc, message", [
    (["--cycles", "100000000000"], None,
     "--cycles=100000000000: 100,000,000,000 leg cycles would take up to 3e+04 GB of memory"),
    ([], "[[segment]]\ncycles = 2\n[[segment]]\ncycles = 100000000000\nslip = 0.2\n",
     "big.toml: segment 2: cycles = 100000000000 (the scenario's cycles in all: 100,000,000,002): "
     "100,000,000,002 leg cycles would take up to 3e+04 GB"),
    # few enough cycles to build, too many samples to write (QA s25: a run of hours towards a 100 GB log)
    (["--cycles", "1000000"], None, "1,000,000 leg cycles lasting 2.493e+06 s at the IMU rate 1000 Hz are 2.49e+09 "
                                    "samples, a log of about 99.7 GB; a run may have at most 1e+09 samples"),
])
def test_simulate_refuses_a_run_too_large_before_it_allocates(tmp_path, capsys, argv, doc, message):
    """QA s25: ``--cycles 100000000000`` (and a scenario file's ``cycles``) died with a MemoryError traceback while
    building the cycles; now refused first, naming the option or the file and segment, and the size."""
    t0 = time.monotonic()
    text = _refused_simulate(tmp_path, argv, doc, "big.toml")
    assert message in text, text
    assert "Traceback" not in capsys.readouterr().err
    assert time.monotonic() - t0 < 20  # refused before any cycle is simulated


@pytest.mark.parametrize("argv, doc, message", [
    (["--omega", "1e6", "--cycles", "20"], None,
     "leg cycle 1 at omega=1e+06 rad/s with 4 legs lasts 1.57e-06 s, 0.00157 samples at the IMU rate 1000 Hz; "
     "a leg cycle must last at least 8 samples: give a leg speed omega <= 190 rad/s or a rate >= 5.1e+06 Hz"),
    ([], "[model]\nnL = 100000\n[[segment]]\ncycles = 2\n",
     "legs.toml: leg cycle 1 at omega=0.63 rad/s with 100000 legs lasts 9.97e-05 s, 0.0997 samples at the IMU "
     "rate 1000 Hz"),
    (["--cycles", "2", "--rate", "3"], None, "7.48 samples at the IMU rate 3 Hz"),
])
def test_simulate_refuses_a_leg_cycle_shorter_than_a_few_samples(tmp_path, argv, doc, message):
    """QA s25: ``--omega 1e6 --cycles 20`` wrote one data row and said "wrote 20 leg cycles" (a cycle shorter than a
    sample); now refused, naming the leg speed, the legs and the rate, and what would do."""
    text = _refused_simulate(tmp_path, argv, doc, "legs.toml")
    assert message in text, text
    out = tmp_path / "run.csv"
    assert main(["simulate", "--cycles", "2", "--rate", "5", "-o", str(out)]) == 0  # 12.5 samples a cycle: taken
    assert len(read_log(out)) == 25


def test_simulate_names_a_scenario_file_that_is_not_utf8_text(tmp_path, capsys):
    """QA s25: the error of a scenario file that is not UTF-8 named no file ("'utf-8' codec can't decode ...")."""
    scenario = tmp_path / "binary.toml"
    scenario.write_bytes(b"\xff\xfe[[segment]]\ncycles = 2\n")
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", str(scenario), "-o", str(tmp_path / "run.csv")])
    assert str(exc.value) == (f"slipest simulate: {scenario}: not UTF-8 text (byte 0xff at offset 0): a scenario "
                              "file is TOML text"), str(exc.value)


def test_simulate_help_states_the_leg_speed_floor(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    assert "omega >= 0.0027" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("doc, message", [
    ("[segment]\ncycles = 2\n", "[segment] is a single table: write [[segment]]"),
    ('[[segment]]\ncycles = 2\n[effect]\nname = "imu_lowpass"\n', "[effect] is a single table: write [[effect]]"),
    ("model = [1, 2]\n[[segment]]\ncycles = 2\n", "model = [1, 2] is an array: [model] must be a table"),
    ("imu = 5\n[[segment]]\ncycles = 2\n", "imu = 5 is a number: [imu] must be a table"),
    ("segment = [1, 2]\n", "segment 1 is a number, not a table"),
    ('effect = "imu_lowpass"\n[[segment]]\ncycles = 2\n', "effect must be an array of tables"),
    ("[[segment]]\ncycles = true\n", "segment 1: cycles = true is a boolean: cycles must be a positive integer"),
    ("[[segment]]\ncycles = 2\nslip = [0.1, true]\n", "segment 1: slip = true is a boolean: it must be a number"),
    ("[model]\nkappa = true\n[[segment]]\ncycles = 2\n", "[model]: kappa = true is a boolean: it must be a number"),
])
def test_simulate_a_section_of_the_wrong_shape_names_file_key_and_expected_shape(tmp_path, capsys, doc, message):
    scenario = tmp_path / "shape.toml"
    scenario.write_text(doc)
    out = tmp_path / "run.csv"
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--scenario", str(scenario), "--effect", "angle_offset", "--rate", "500", "-o", str(out)])
    assert "shape.toml" in str(exc.value) and message in str(exc.value), str(exc.value)
    assert not out.exists() and "Traceback" not in capsys.readouterr().err


def test_simulate_rate_above_the_model_step_suggests_dt(tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--rate", "20000", "--cycles", "1", "-o", str(tmp_path / "run.csv")])
    assert "coarser than the IMU period" in str(exc.value) and "--dt" in str(exc.value)
    out = tmp_path / "fine.csv"
    assert main(["simulate", "--rate", "20000", "--dt", "5e-5", "--cycles", "1", "-o", str(out)]) == 0
