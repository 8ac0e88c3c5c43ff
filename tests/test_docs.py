"""What the docs say holds: docs/api.md's examples run as written; docs/wire-formats.md's time bases.

Each api.md example is taken from the page itself and run with only its placeholders filled in (a pty
of firmware-sim for the rover's port, files made here for the logs it names), so a stale name or
argument in the page fails here.
"""

import math
import re
import time
from pathlib import Path

import numpy as np
import pytest

from slipest.io.log_csv import read_log
from tests.hil_support import Stopping, firmware_sim, serial_device
from tests.log_makers import can_frames, stream, write_can_log, write_csv

API_MD = Path(__file__).resolve().parent.parent / "docs" / "api.md"


def example(containing: str) -> str:
    """The one ```python block of docs/api.md that contains ``containing``."""
    blocks = [b for b in re.findall(r"```python\n(.*?)```", API_MD.read_text(), re.S) if containing in b]
    assert len(blocks) == 1, f"{len(blocks)} examples contain {containing!r}"
    return blocks[0]


def filled(code: str, **placeholders: str) -> str:
    for old, new in placeholders.items():
        assert old in code, f"docs/api.md's example no longer has {old!r}"
        code = code.replace(old, new)
    return code


def test_the_live_example_estimates_records_and_stops(tmp_path):
    code = filled(example("run_live(source, live"), **{
        '"/dev/ttyUSB0"': "PORT",
        '"/var/lib/slipest/run.csv"': "RECORD",
        "StopConditions(duration=600)": "StopConditions(cycles=4, duration=60)",
    })
    published = []
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--cycles", "6", "--speed", "8", "--noise", "0.01", "--seed", "4",
                                     "--wheels", "2"))
        ns = {"PORT": serial_device(dev), "RECORD": str(tmp_path / "run.csv"),
              "publish": lambda wheel, est: published.append((wheel, est))}
        exec(compile(code, str(API_MD), "exec"), ns)
    result = ns["result"]
    assert result.reason == "4 cycles reached" and not result.interrupted
    assert result.estimation["estimates"] == sum(1 for _, e in published if e.ok) >= 6  # 2 wheels x >= 3
    assert {w for w, _ in published} == {0, 1}
    ok = [e for _, e in published if e.ok]
    assert all(0.1 < e.slip < 0.45 for e in ok)  # true slip 0.25
    # the recording: wheel 0 at the path, wheel 1 beside it, every sample the estimator was given
    for wheel, name in ((0, "run.csv"), (1, "run.wheel1.csv")):
        log = read_log(tmp_path / name)
        assert len(log) == result.estimation[f"wheel{wheel}"]["rows_recorded"] > 0
        assert log.metadata["nL"] == "4" and np.isnan(log.slip).all()  # no reference sent
        # serial t is the device's clock, whole: firmware-sim's starts at 8 x this host's monotonic clock
        assert abs(log.t[0] / 8 - time.monotonic()) < 60
        closes = {round(e.t_end, 6) for w, e in published if w == wheel}
        assert closes and closes <= set(np.round(log.t, 6).tolist())  # estimates' times are the samples' times


def test_the_log_format_example_reads_and_writes(tmp_path, monkeypatch):
    s, sc = stream(n_cycles=2)
    write_csv(tmp_path / "drive.csv", s, sc)
    write_csv(tmp_path / "long.csv", s, sc)
    monkeypatch.chdir(tmp_path)
    code = example("from slipest.io.log_csv import")
    ns = {"t": s.t, "az": s.az, "theta": s.theta, "slip": s.slip}
    exec(compile(code, str(API_MD), "exec"), ns)
    assert ns["log"].metadata["nL"] == "4" and len(ns["log"]) == len(s.t)
    back = read_log(tmp_path / "out.csv")
    assert back.metadata["nL"] == "4"
    np.testing.assert_allclose(back.az, s.az, atol=5e-7)
    np.testing.assert_allclose(back.theta, s.theta, atol=5e-8)
    with pytest.raises(FileExistsError):  # "refuses to overwrite unless overwrite=True"
        exec(compile(code, str(API_MD), "exec"), ns)


def test_the_replay_example_replays_a_can_log(tmp_path, monkeypatch, capsys):
    s, _ = stream(n_cycles=4)
    write_can_log(tmp_path / "drive.blf", can_frames({0: s}))
    monkeypatch.chdir(tmp_path)
    ns = {}
    exec(compile(example("Replay(\"drive.blf\""), str(API_MD), "exec"), ns)
    result = ns["result"]
    (row,) = result.rows()
    assert row["verdict"] == "ok" and row["wheel"] == 0 and row["estimated"] >= 2
    assert math.isfinite(row["slip_rmse"]) and row["slip_rmse"] < 0.1  # truth: the log's reference slip
    printed = capsys.readouterr().out
    assert re.search(r"^0 0 0\.\d+ ok$", printed, re.M)  # one line per estimate: wheel, cycle, slip, quality
    assert "CAN frames read from drive.blf" in printed and "truth:" in printed


def test_can_times_start_at_the_first_timemod_and_keep_the_device_steps(tmp_path):
    """docs/wire-formats.md section 3: CAN carries the device time modulo 0.65536 s only."""
    from slipest.io.can_messages import TIME_MOD_PERIOD
    from slipest.model.stream import SampleChunk
    from slipest.offline.replay import Replay

    s, _ = stream(n_cycles=3)
    boot = 1000.3  # the device's clock at the first sample [s]
    late = SampleChunk(t=s.t + boot, az=s.az, theta=s.theta, slip=s.slip, cycle=s.cycle)
    log = write_can_log(tmp_path / "late.asc", can_frames({0: late}))
    got = []
    Replay(log).run(lambda wheel, e: got.append(e))
    first = boot % TIME_MOD_PERIOD
    assert got and 0 <= first < TIME_MOD_PERIOD
    assert got[0].t_start == pytest.approx(first, abs=1e-5)  # the first message's TimeMod (10 us steps)
    for e in got:  # then the device's steps: a sample's time since the first, plus that origin
        assert np.min(np.abs(s.t + first - e.t_end)) < 1e-5
    assert got[-1].t_end > 3 * TIME_MOD_PERIOD  # unwrapped across many periods


def test_the_estimate_table_lists_every_field_and_no_other():
    """docs/api.md's `Estimate` table documents exactly ESTIMATE_FIELDS (fields are added over time)."""
    from slipest.online import ESTIMATE_FIELDS

    text = API_MD.read_text()
    table = text[text.index("### `Estimate`"):]
    table = table[:table.index("\n\n", table.index("| field |"))]
    documented = set()
    for row in table.splitlines()[2:]:
        if row.startswith("| `"):
            documented |= set(re.findall(r"`(\w+)`", row.split("|")[1]))
    assert documented == set(ESTIMATE_FIELDS)
