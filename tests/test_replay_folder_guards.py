"""Guards of the many-logs replay (and `diagnose --per-log`): -o never writes over a log it reads (a folder's
too), the command's own earlier table in the folder is left out; a folder where no log gave an estimate says
why in the table and exits 1; a reference slip outside [0, 1) (+-inf too) is refused by --use-reference and --truth;
ROS 2 bag joint states without positions and a bad --max-joint-gap get messages that say what is wrong; --jobs
below 1 is a usage error."""

from __future__ import annotations

import csv
import hashlib

import pytest

from slipest.cli.main import main
from slipest.io.log_csv import LogWriter
from slipest.offline.replay import TABLE_COLUMNS
from tests.cli_support import slipest_in_process
from tests.log_makers import stream, write_bag, write_csv


def _md5(path) -> str:
    return hashlib.md5(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def drive():
    return stream(4, seed=3)


def _folder_log(drive, folder, name: str):
    """The drive written as the log ``name`` in ``folder`` (made here): its path."""
    folder.mkdir()
    return write_csv(folder / name, *drive)


def _table(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# -- D3: -o naming a log in a folder ----------------------------------------------------------------------------


def test_replay_folder_refuses_an_output_that_is_one_of_its_logs(drive, tmp_path, capsys):
    folder = tmp_path / "drives"
    log = _folder_log(drive, folder, "run1.csv")
    before = _md5(log)
    rc = main(["replay", str(folder), "-o", str(log), "--no-progress", "--jobs", "1"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "refusing to write over it" in err and str(log) in err
    assert _md5(log) == before  # the drive log is untouched


def test_replay_folder_leaves_out_its_own_earlier_table(drive, tmp_path, capsys):
    folder = tmp_path / "drives"
    _folder_log(drive, folder, "run1.csv")
    out = folder / "table.csv"
    assert main(["replay", str(folder), "-o", str(out), "--no-progress", "--jobs", "1"]) == 0
    capsys.readouterr()
    rc = main(["replay", str(folder), "-o", str(out), "--no-progress", "--jobs", "1"])  # the table is there now
    err = capsys.readouterr().err
    assert rc == 0
    assert f"{out} left out" in err
    rows = _table(out)
    assert [r["log"] for r in rows] == [str(folder / "run1.csv")]
    assert rows[0]["verdict"] == "ok"


def test_diagnose_per_log_refuses_an_output_that_is_one_of_its_logs(drive, tmp_path, capsys):
    folder = tmp_path / "dg"
    log = _folder_log(drive, folder, "tb.csv")
    before = _md5(log)
    rc = main(["diagnose", "--per-log", str(folder), "-o", str(log), "--quick", "--no-progress", "--jobs", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and "refusing to write over it" in err and str(log) in err
    assert _md5(log) == before


# -- D4: no log of a folder gave an estimate ----------------------------------------------------------------------


def test_replay_folder_without_any_estimate_says_why_in_the_rows_and_exits_1(drive, tmp_path, capsys):
    s, sc = drive
    folder = tmp_path / "units"
    folder.mkdir()
    with LogWriter(folder / "g.csv", ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az / 9.81, s.theta, s.slip)  # az logged in g
    rc_one = main(["replay", str(folder / "g.csv"), "-o", str(tmp_path / "one.csv")])
    hint = [line[len("replay: "):] for line in capsys.readouterr().err.splitlines() if "in g" in line]
    assert rc_one == 1 and len(hint) == 1
    out = tmp_path / "table.csv"
    rc = main(["replay", str(folder), "-o", str(out), "--no-progress", "--jobs", "1"])
    err = capsys.readouterr().err
    assert rc == 1  # as the single log: no cycle estimated is not a success
    assert "no leg cycle was estimated in any log" in err
    (row,) = _table(out)
    assert row["verdict"] == "no cycle estimated"
    assert row["error"] == hint[0]  # the single-log replay's very words


# -- D9: a reference slip outside [0, 1) ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def percent_log(drive, tmp_path_factory):
    s, sc = drive
    path = tmp_path_factory.mktemp("pct") / "slip_percent.csv"
    with LogWriter(path, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, s.slip * 100)
    return path


@pytest.mark.parametrize("flags", [["--use-reference"], ["--truth"], ["--use-reference", "--truth"]])
def test_replay_refuses_a_reference_slip_in_percent(percent_log, flags, capsys):
    rc = main(["replay", str(percent_log), "--chunk-rows", "500", *flags])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(percent_log) in err and "outside [0, 1)" in err and "in percent?" in err
    assert "truth: slip" not in err  # no RMSE against the impossible reference
    assert main(["replay", str(percent_log)]) == 0  # a blind replay does not read the reference
    capsys.readouterr()


@pytest.mark.parametrize("value", [float("inf"), float("-inf")])
def test_replay_refuses_an_infinite_reference_slip_and_takes_nan_as_none(drive, value, tmp_path, capsys):
    """QA s25: an ``inf`` reference slip was passed over (only finite values were checked) where -0.05 and 25
    are refused; NaN is "no reference" and stays taken."""
    s, sc = drive
    slip = s.slip.copy()
    slip[3000] = value
    slip[3100] = float("nan")
    path = tmp_path / "inf.csv"
    with LogWriter(path, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, slip)
    rc, err = slipest_in_process(capsys, "replay", path, "--truth", "--chunk-rows", "500")
    assert rc == 2 and f"{path}: slip {value:g} at t = {s.t[3000]:.3f} s is outside [0, 1)" in err, err
    slip[3000] = 0.2
    nan_only = tmp_path / "nan.csv"
    with LogWriter(nan_only, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, slip)
    rc, err = slipest_in_process(capsys, "replay", nan_only, "--truth", "--chunk-rows", "500")
    assert rc == 0 and "truth: slip" in err, err


def test_folder_replay_with_use_reference_gives_the_percent_log_an_error_row(drive, percent_log, tmp_path, capsys):
    out = tmp_path / "table.csv"
    rc = main(["replay", str(percent_log), str(write_csv(tmp_path / "good.csv", *drive)), "--use-reference",
               "-o", str(out), "--no-progress", "--jobs", "1"])
    capsys.readouterr()
    rows = {r["log"]: r for r in _table(out)}
    assert rc == 1
    assert rows[str(percent_log)]["verdict"] == "error" and "in percent?" in rows[str(percent_log)]["error"]
    assert rows[str(tmp_path / "good.csv")]["verdict"] == "ok"


# -- D7: ROS 2 bags ---------------------------------------------------------------------------------------------------


def test_bag_joint_states_naming_the_joint_without_positions_say_so(drive, tmp_path, capsys):
    pytest.importorskip("rosbags")
    bag = write_bag(tmp_path / "emptypos", drive[0], positions=False)
    rc = main(["replay", bag, "--joint", "wheel_leg"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "name the joint 'wheel_leg' but carry no position for it" in err
    assert "no JointState message" not in err


@pytest.mark.parametrize("gap", ["-1", "0", "nan", "inf"])
def test_max_joint_gap_refuses_non_positive_and_non_finite_values(gap, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["replay", str(tmp_path / "bag"), "--max-joint-gap", gap])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--max-joint-gap" in err and "a number of seconds > 0" in err



# -- --jobs ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("jobs", ["0", "-1", "two"])
@pytest.mark.parametrize("command", [["replay"], ["diagnose", "--per-log"]])
def test_jobs_below_one_is_refused_by_the_arguments(command, jobs, drive, tmp_path, capsys):
    """--jobs 0 and -1 were taken (0 as one per core, -1 as one in this process): refused as a usage error naming
    --jobs before any log is read, as --legs is."""
    folder = tmp_path / "drives"
    _folder_log(drive, folder, "run1.csv")
    out = tmp_path / "table.csv"
    rc, err = slipest_in_process(capsys, *command, folder, "-o", out, "--no-progress", "--jobs", jobs)
    assert rc == 2 and f"argument --jobs: {jobs!r} is not a number of worker processes (a whole number >= 1)" in err
    assert not out.exists()
