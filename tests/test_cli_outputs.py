"""Where the commands write: never over a file they read, never into a directory, a recorded log never replaced by
a simulated one unasked; checked before anything is read, written or computed. Real files, the real CLI."""

import time

import pytest

from slipest.cli.main import main
from tests.log_makers import stream, write_csv


@pytest.fixture()
def log(tmp_path):
    run, sc = stream(n_cycles=4, seed=3)
    return write_csv(tmp_path / "drive.csv", run, sc)


def _refused(argv, capsys, *words):
    with pytest.raises(SystemExit) as exc:
        code = main(argv)
        raise SystemExit(code)  # (replay returns its status; the others raise)
    err = str(exc.value.code) + capsys.readouterr().err
    assert exc.value.code not in (0, None) and all(w in err for w in words), err


def test_replay_calibrate_and_diagnose_refuse_to_write_over_a_log_they_read(log, tmp_path, capsys):
    before = log.read_bytes()
    _refused(["replay", str(log), "-o", str(log)], capsys, "one of the files read")
    t0 = time.monotonic()
    _refused(["calibrate", str(log), "--legs", "4", "--no-progress", "-o", str(log)], capsys, "one of the files read")
    _refused(["diagnose", str(log), "--json", str(log), "--no-progress"], capsys, "one of the files read")
    assert time.monotonic() - t0 < 30  # refused before the calibration and the diagnosis ran
    assert log.read_bytes() == before  # (the replay used to truncate it to its header)


def test_outputs_that_are_directories_or_in_no_directory_are_refused_first(log, tmp_path, capsys):
    (tmp_path / "out").mkdir()
    _refused(["replay", str(log), "-o", str(tmp_path / "out")], capsys, "is a directory")
    _refused(["replay", str(log), "--plot", str(tmp_path / "out")], capsys, "is a directory")
    _refused(["calibrate", str(log), "--no-progress", "-o", str(tmp_path / "out")], capsys, "is a directory")
    _refused(["diagnose", str(log), "--no-progress", "--json", str(tmp_path / "out")], capsys, "is a directory")
    _refused(["simulate", "--cycles", "1", "-o", str(tmp_path / "out")], capsys, "is a directory")
    _refused(["simulate", "--cycles", "1", "-o", str(tmp_path / "no" / "x.csv")], capsys, "no directory")


def test_simulate_replaces_a_simulated_log_but_not_a_recorded_one_unless_told(log, tmp_path, capsys):
    before = log.read_bytes()  # a log written as a recording would be (no source=slipest simulate line)
    _refused(["simulate", "--cycles", "1", "-o", str(log)], capsys, "not a simulated log", "--overwrite")
    assert log.read_bytes() == before
    sim = tmp_path / "sim.csv"
    assert main(["simulate", "--cycles", "1", "-o", str(sim)]) == 0
    one = sim.read_bytes()
    assert b"# source=slipest simulate" in one
    assert main(["simulate", "--cycles", "2", "-o", str(sim)]) == 0 and sim.read_bytes() != one
    assert main(["simulate", "--cycles", "1", "--overwrite", "-o", str(log)]) == 0 and log.read_bytes() != before


def test_a_plot_is_written_where_it_is_named_whatever_its_extension(log, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    target = tmp_path / "plot_without_extension"
    assert main(["replay", str(log), "-o", str(tmp_path / "rows.csv"), "--plot", str(target)]) == 0
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (tmp_path / "plot_without_extension.png").exists()
    assert f"wrote {target}" in capsys.readouterr().err


def test_a_command_that_makes_its_directories_may_name_a_new_one(tmp_path):
    """calibrate creates the rover file's directories (it always did): a new directory is no problem there."""
    from slipest.cli.output_paths import output_problem

    new = tmp_path / "rovers" / "r.json"
    assert output_problem(new, makes_dirs=True) is None
    assert "no directory" in output_problem(new)


def test_calibrate_replaces_a_rover_file_but_no_other_file_unless_told(log, tmp_path, capsys):
    """`calibrate -o drive_copy.csv` (an existing log that is not an input) had replaced it with a rover file;
    every refusal comes before the calibration's minutes."""
    from slipest.rover.file import KIND

    other = tmp_path / "other_drive.csv"
    other.write_bytes(log.read_bytes())
    t0 = time.monotonic()
    _refused(["calibrate", str(log), "--no-progress", "-o", str(other)], capsys, "not a rover file", "--overwrite")
    assert other.read_bytes() == log.read_bytes()
    # a rover file is what a recalibration replaces: that one is let through to the calibration (which then
    # refuses this one short log: the refusal is not about -o)
    rover = tmp_path / "rover.json"
    rover.write_text('{"kind": "%s"}' % KIND)
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(log), "--no-progress", "--no-diagnosis", "-o", str(rover)])
    assert "rover file" not in str(exc.value.code) and "--overwrite" not in str(exc.value.code)
    assert time.monotonic() - t0 < 30


@pytest.mark.parametrize("where", ["/proc/slipest-rover.json", ""])
def test_an_output_that_cannot_be_written_is_refused_before_the_work(where, log, capsys):
    """`calibrate -o /proc/x.json` failed after the whole calibration; `-o ''` with 'Is a directory'."""
    import os

    if where.startswith("/proc") and not os.path.isdir("/proc"):
        pytest.skip("no /proc on this system")
    t0 = time.monotonic()
    _refused(["calibrate", str(log), "--no-progress", "-o", where], capsys, "cannot write" if where else "name a file")
    _refused(["diagnose", str(log), "--no-progress", "--json", where], capsys,
             "cannot write" if where else "name a file")
    assert time.monotonic() - t0 < 30
