"""`slipest simulate`: the log it writes, its reference values, its scenario files and its errors."""

import math

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
