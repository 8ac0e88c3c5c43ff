"""`slipest diagnose` on bad data: what replay repairs or flags is repaired or left out, and said (in the --per-log
table too); what cannot be diagnosed (a reference slip outside [0, 1), a --plots that is no directory) is refused
before any work; a ROS 2 bag is read as replay reads it.

Real log files, the real CLI (in-process), small simulated logs."""

import csv
import importlib.util
import json
import time

import numpy as np
import pytest

from slipest.cli.main import main
from slipest.io.log_csv import LogWriter
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.offline.diagnose import DIAGNOSE_COLUMNS
from tests.cli_support import slipest_in_process
from tests.log_makers import write_bag

COLUMNS = ("t", "az", "theta", "slip")
META = {"nL": "4", "MH": "1", "mF": "0.2", "lS": "0.1763"}
FAST = ["--quick", "--no-progress", "--effects", "angle_offset"]


def _stream(slips, effects=(), noise=0.01, seed=3):
    sc = Scenario.per_cycle(StickSlipParams(), imu={"rate": 1000.0, "noise_g": noise, "seed": seed}, slip=slips)
    return simulate_stream(Scenario(cycles=sc.cycles, rate=1000.0, noise_g=noise, seed=seed, effects=tuple(effects)))


def _write(path, t, az, theta, slip):
    with LogWriter(path, COLUMNS, metadata=META, overwrite=True) as w:
        w.write(t, az, theta, slip)
    return path


def _diagnose(argv, capsys):
    """(exit status, stdout, stderr, the --json report or None) of `slipest diagnose ARGV`."""
    try:
        rc = main(["diagnose", *argv])
    except SystemExit as exc:
        rc = exc.code
    out, err = capsys.readouterr()
    doc = None
    if "--json" in argv:
        path = argv[argv.index("--json") + 1]
        try:
            with open(path) as fh:
                doc = json.load(fh)
        except FileNotFoundError:
            pass
    return rc, out, err, doc


@pytest.fixture(scope="module")
def offset_run():
    """A drive with an encoder angle offset (the diagnosis names angle_offset on it)."""
    return _stream(np.repeat([0.1, 0.3, 0.45], 3), effects=({"name": "angle_offset", "offset": 0.15},))


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_one_glitch_sample_of_any_size_is_left_out_and_the_verdict_is_the_clean_logs(offset_run, tmp_path, capsys):
    """D1: one az sample of 1e4 or 1e300 m/s^2 in the whole log is left out as the estimator leaves it out
    (slipest.despike): same verdict, same noise floor and nominal gap as the clean log, no RuntimeWarning, and the
    report says one glitch sample was left out (text and JSON ``samples_repaired``)."""
    s = offset_run
    clean = _write(tmp_path / "clean.csv", s.t, s.az, s.theta, s.slip)
    rc, out, _, ref = _diagnose([str(clean), *FAST, "--json", str(tmp_path / "clean.json")], capsys)
    assert rc == 0 and ref["verdict"] == "angle_offset", out
    assert ref["samples_repaired"] == 0 and "glitch sample" not in out
    for value in (1e4, 1e300):
        az = s.az.copy()
        az[az.size // 2] = value
        log = _write(tmp_path / f"glitch_{value:g}.csv", s.t, az, s.theta, s.slip)
        rc, out, err, doc = _diagnose([str(log), *FAST, "--json", str(tmp_path / "g.json")], capsys)
        assert rc == 0, err
        assert doc["verdict"] == ref["verdict"] == "angle_offset", out
        assert doc["noise"]["bin_g"] == pytest.approx(ref["noise"]["bin_g"], rel=0.05)
        assert doc["gap_nominal"] == pytest.approx(ref["gap_nominal"], rel=0.05)
        assert doc["samples_repaired"] == 1 and doc["cycles"] == ref["cycles"]
        assert "1 glitch sample left out" in out and " nan" not in out and " inf" not in out


def test_cycles_replay_flags_are_left_out_and_counted_by_flag(tmp_path, capsys):
    """D2: a 100 s logger pause inside a cycle (replay: ``gap``) and two drives appended in one file (replay:
    ``reverse``) are left out as replay leaves them out; the diagnosis of what is left is that of the clean log
    (``none``, the same soil), and the report says how many cycles were left out, by flag."""
    s = _stream(np.full(6, 0.2), seed=1)
    base = _write(tmp_path / "base.csv", s.t, s.az, s.theta, s.slip)
    rc, out, _, ref = _diagnose([str(base), *FAST, "--json", str(tmp_path / "b.json")], capsys)
    assert rc == 0 and ref["verdict"] == "none" and ref["cycles_left_out"] == {}, out
    t = s.t.copy()
    t[7000:] += 100.0
    pause = _write(tmp_path / "pause.csv", t, s.az, s.theta, s.slip)
    cat = np.concatenate
    twice = _write(tmp_path / "twice.csv", cat([s.t, s.t]), cat([s.az, s.az]), cat([s.theta, s.theta]),
                   cat([s.slip, s.slip]))
    for log, flag in ((pause, "gap"), (twice, "reverse")):
        rc, out, err, doc = _diagnose([str(log), *FAST, "--json", str(tmp_path / "r.json")], capsys)
        assert rc == 0, err
        assert doc["cycles_left_out"] == {flag: 1}, out
        assert f"data: 1 leg cycle left out, flagged as replay flags them ({flag} 1)" in out
        assert doc["verdict"] == "none", out
        assert doc["nominal"]["soil"]["kS"] == pytest.approx(ref["nominal"]["soil"]["kS"], rel=0.1)


def test_a_reference_slip_outside_0_1_is_refused_before_any_work(tmp_path, capsys):
    """D9: a reference slip in percent (or negative) is refused at once, naming the file, with the percent hint
    (slipest.offline.reference_slip.check_reference_slip, as calibrate refuses it); no report is written."""
    s = _stream(np.repeat([0.1, 0.3], 3))
    pct = _write(tmp_path / "percent.csv", s.t, s.az, s.theta, s.slip * 100)
    neg = _write(tmp_path / "negative.csv", s.t, s.az, s.theta, -s.slip)
    for log, words in ((pct, ("outside [0, 1)", "in percent?")), (neg, ("outside [0, 1)",))):
        t0 = time.monotonic()
        rc, out, err, doc = _diagnose([str(log), "--no-progress", "--json", str(tmp_path / "x.json")], capsys)
        msg = str(rc) + err
        assert rc not in (0, None) and str(log) in msg and all(w in msg for w in words), msg
        assert doc is None and "verdict" not in out
        assert time.monotonic() - t0 < 5  # refused before the fits


@pytest.mark.parametrize("where", ["a_file", "under_a_file", "proc"])
def test_plots_that_cannot_be_a_directory_are_refused_first(where, tmp_path, capsys):
    """D6: --plots naming an existing file, a path under a file or under /proc is refused before the diagnosis:
    one line naming --plots, exit 2 (as --json and replay --plot), no traceback, no --json written."""
    s = _stream(np.repeat([0.1, 0.3], 3))
    log = _write(tmp_path / "log.csv", s.t, s.az, s.theta, s.slip)
    (tmp_path / "notadir").write_text("")
    plots = {"a_file": tmp_path / "notadir", "under_a_file": tmp_path / "notadir" / "png",
             "proc": "/proc/slipest_plots"}[where]
    t0 = time.monotonic()
    rc, out, err, doc = _diagnose([str(log), *FAST, "--json", str(tmp_path / "r.json"), "--plots", str(plots)],
                                  capsys)
    assert rc == 2 and f"--plots {plots}" in err and "Traceback" not in err, err
    assert err.strip().count("\n") == 0 and doc is None and out == ""
    assert time.monotonic() - t0 < 5


def test_plots_into_a_new_directory_still_work(tmp_path, capsys):
    """--plots naming a directory that does not exist yet: created, the plots written in it."""
    pytest.importorskip("matplotlib")
    s = _stream(np.repeat([0.1, 0.3], 3))
    log = _write(tmp_path / "log.csv", s.t, s.az, s.theta, s.slip)
    rc, _, err, _ = _diagnose([str(log), *FAST, "--plots", str(tmp_path / "new" / "png")], capsys)
    assert rc == 0, err
    assert sorted(p.name for p in (tmp_path / "new" / "png").iterdir())[:2] == ["gap_by_angle.png", "waveforms.png"]


def test_a_ros2_bag_is_diagnosed_as_the_same_samples_in_a_csv(offset_run, tmp_path, capsys):
    """`slipest diagnose BAG_DIR` (it said "Is a directory") reads the bag as replay reads it (--slip-topic, --joint
    ...): the diagnosis of the same samples as in a CSV; without a slip topic it is refused, naming the option."""
    pytest.importorskip("rosbags")
    s = offset_run
    csv_log = _write(tmp_path / "drive.csv", s.t, s.az, s.theta, s.slip)
    bag = write_bag(tmp_path / "drive_bag", s)  # two joints: --joint names the wheel-leg's
    rc, out, _, ref = _diagnose([str(csv_log), *FAST, "--json", str(tmp_path / "csv.json")], capsys)
    assert rc == 0 and ref["verdict"] == "angle_offset", out
    argv = [bag, "--joint", "wheel_leg", "--slip-topic", "/slip", *FAST, "--json", str(tmp_path / "bag.json")]
    rc, out, err, doc = _diagnose(argv, capsys)
    assert rc == 0, err
    assert doc["verdict"] == "angle_offset" and doc["cycles"] == ref["cycles"] and doc["logs"] == [bag]
    assert doc["gap_nominal"] == pytest.approx(ref["gap_nominal"], rel=1e-4)
    assert doc["nominal"]["soil"]["kS"] == pytest.approx(ref["nominal"]["soil"]["kS"], rel=1e-4)
    rc, err = slipest_in_process(capsys, "diagnose", bag, "--joint", "wheel_leg", *FAST)
    assert rc == 1 and f"{bag}: no reference slip topic (--slip-topic)" in err and "Traceback" not in err, err


def test_the_per_log_table_counts_the_cycles_and_glitch_samples_left_out(offset_run, tmp_path, capsys):
    """--per-log rows carry what the single report's 'data:' line says: the glitch samples (one az of 1e4 m/s^2)
    and the cycles the segmenter flags (a logger pause: gap) left out; a bag in the folder is diagnosed too."""
    folder = tmp_path / "drives"
    folder.mkdir()
    s = offset_run
    az = s.az.copy()
    az[az.size // 2] = 1e4
    glitch = _write(folder / "glitch.csv", s.t, az, s.theta, s.slip)
    p = _stream(np.full(6, 0.2), seed=1)
    t = p.t.copy()
    t[7000:] += 100.0
    pause = _write(folder / "pause.csv", t, p.az, p.theta, p.slip)
    with_bag = importlib.util.find_spec("rosbags") is not None  # the [ros] extra
    if with_bag:
        write_bag(folder / "clean_bag", s, joints=("wheel_leg",))
    out = tmp_path / "table.csv"
    rc, _, err, _ = _diagnose(["--per-log", str(folder), "-o", str(out), "--jobs", "1", "--slip-topic", "/slip",
                               *FAST], capsys)
    assert rc == 0, err
    with open(out, newline="") as fh:
        rows = {r["log"]: r for r in csv.DictReader(fh)}
    assert list(next(iter(rows.values()))) == list(DIAGNOSE_COLUMNS)
    assert rows[str(glitch)]["verdict"] == "angle_offset", rows[str(glitch)]
    assert (rows[str(glitch)]["samples_repaired"], rows[str(glitch)]["cycles_left_out"]) == ("1", "0")
    assert rows[str(pause)]["verdict"] == "none", rows[str(pause)]
    assert (rows[str(pause)]["samples_repaired"], rows[str(pause)]["cycles_left_out"]) == ("0", "1")
    assert len(rows) == 2 + with_bag
    if with_bag:
        bag_row = rows[str(folder / "clean_bag")]
        assert bag_row["verdict"] == "angle_offset", bag_row
        assert (bag_row["samples_repaired"], bag_row["cycles_left_out"]) == ("0", "0")
