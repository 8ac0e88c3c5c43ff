"""`slipest demo`: the virtual device and the estimator as separate processes, short runs on both links."""

from __future__ import annotations

import io
import re
from types import SimpleNamespace

import pytest

from slipest.cli.demo import DEMO_SCENARIO, _Display, scenario_toml
from slipest.model.scenario import Scenario
from tests.hil_support import slipest_cmd


def _estimate_lines(lines):
    return [line for line in lines if re.match(r"^\s+\d+\s+[\d.]+\s+[\d.]+ ±", line)]


def test_demo_scenario_round_trips_through_toml():
    import tomllib

    doc = tomllib.loads(scenario_toml(DEMO_SCENARIO))
    sc = Scenario.from_dict(doc)
    assert len(sc.cycles) == 40 and {round(c.kS) for c in sc.cycles} == {700, 1000, 1400}
    assert min(sc.slips) == 0.2 and max(sc.slips) == 0.45  # slip and soil change along the drive


def test_demo_over_a_pty_with_faults_exits_0_and_counts_what_was_injected():
    proc = slipest_cmd("demo", "--speed", "20", "--cycles", "10", "--faults")
    try:
        assert proc.wait(120) == 0, proc.stderr
    finally:
        proc.stop()
    out = proc.lines
    assert any("virtual device (pid" in line for line in out)
    est = _estimate_lines(out)
    assert len(est) >= 3  # estimates beside the truth, one line per cycle
    flagged = [line for line in out if line.rstrip().endswith(" nan")]
    assert len(flagged) >= 3  # the dropped frame, the corruption, the stuck sensor: never estimated from
    text = "\n".join(out)
    assert re.search(r"slip: RMSE 0\.\d+, 95% interval covers the truth in \d+% of cycles", text)
    assert re.search(r"the device injected: 1 dropped, 3 corrupted, \d+ lost in 1 disconnection", text)
    assert re.search(r"corrupted or malformed segments skipped, \d+ stuck-sensor samples not used", text)
    assert re.search(r"latency, device sample -> estimator intake: median [\d.]+ ms, p99 [\d.]+ ms", text)


def test_demo_over_the_can_server_exits_0_with_a_summary():
    proc = slipest_cmd("demo", "--bus", "can", "--speed", "20", "--cycles", "5")
    try:
        assert proc.wait(120) == 0, proc.stderr
    finally:
        proc.stop()
    text = "\n".join(proc.lines)
    assert "CAN server (pid" in text and "published back on the bus" in text
    assert len(_estimate_lines(proc.lines)) >= 3
    m = re.search(r"slip: RMSE (0\.\d+)", text)
    assert m and float(m.group(1)) < 0.15
    assert re.search(r"frames: \d+ received, 0 lost", text)


def test_demo_waits_for_a_device_that_is_still_preparing_its_run_then_gives_up_on_silence():
    # the device simulates its run (and, on the first run after an install, compiles its kernels: 37 s
    # measured) before it streams: that silence must not count as a dead device
    from slipest.cli.demo import _GAVE_UP, _NO_START, _START_LIMIT, _DeviceWatch

    w = _DeviceWatch()
    assert w.reason(now=60.0, started=0.0, last_data=None, device_exited=False) is None
    assert w.say_waiting  # the user is told why nothing shows yet, once
    w.say_waiting = False
    assert w.reason(now=61.0, started=0.0, last_data=None, device_exited=False) is None and not w.say_waiting
    assert w.reason(now=_START_LIMIT + 1, started=0.0, last_data=None, device_exited=False) == _NO_START
    w.streaming_since = 70.0  # it streams: 30 s without data from then on ends the run
    assert w.reason(now=99.0, started=0.0, last_data=None, device_exited=False) is None
    assert w.reason(now=101.0, started=0.0, last_data=None, device_exited=False) == _GAVE_UP
    assert w.reason(now=101.0, started=0.0, last_data=80.0, device_exited=False) is None
    assert w.reason(now=101.0, started=0.0, last_data=100.0, device_exited=True) == "the device finished"


def test_demo_side_by_side_prints_the_rover_estimates_quality():
    # (a rover file takes a calibration to make: the display alone, fed as the live run feeds it)
    sc = Scenario.from_dict(DEMO_SCENARIO)
    out = io.StringIO()
    display = _Display(sc, out, side_by_side=True)
    est = SimpleNamespace(cycle=1, ok=True, quality="repaired", slip=0.26, slip_std=0.05, dphi=0.17, dphi_std=0.08)
    shipped = SimpleNamespace(**{**vars(est), "quality": "ok"})
    display.live = SimpleNamespace(wheels={0: SimpleNamespace(estimator=SimpleNamespace(shipped={1: shipped}))})
    display(0, est, {})
    assert out.getvalue().rstrip().endswith("0.170  repaired"), out.getvalue()


@pytest.mark.parametrize("option, value, why", [
    ("--cycles", "0", "is not a number of leg cycles of the demo's drive (1..40)"),  # ran 1 cycle
    ("--cycles", "-5", "is not a number of leg cycles of the demo's drive (1..40)"),  # ran 1 cycle
    ("--cycles", "1000", "is not a number of leg cycles of the demo's drive (1..40)"),  # ran 40
    ("--seed", "-3", "is not a seed (a whole number >= 0)"),  # "the device failed:" and its numpy traceback
])
def test_demo_refuses_a_cycle_count_outside_its_drive_and_a_negative_seed(option, value, why, capsys):
    # refused as the arguments are parsed: the CLI in this process (no new interpreter's start-up); a refusal
    # that did not come would start the demo's processes and fail the SystemExit check with their output
    from slipest.cli.main import main

    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--speed", "20", option, value])
    out, err = capsys.readouterr()
    assert exc.value.code == 2, err
    assert err.splitlines()[-1] == f"slipest demo: error: argument {option}: {value!r} {why}", err
    assert not out.splitlines()  # nothing started


def test_demo_refuses_a_rover_file_that_cannot_be_used_as_replay_does(tmp_path, capsys):
    """A bad rover file: exit 2 with the file named, as `slipest replay --rover` refuses it (demo gave 1)."""
    from slipest.cli.main import main

    bad = tmp_path / "rover.json"
    bad.write_text('{"kind": "something else"}')
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(["demo", "--speed", "20", "--rover", str(bad)])
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and "rover.json" in err and "not a slipest rover file" in err and not out
