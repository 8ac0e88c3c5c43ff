"""Logs a careless or unlucky user hands the commands: one clear line naming the file and what is wrong, the
right exit status, and no Python traceback. Real files, the real CLI."""

import pytest

from slipest.cli.main import main
from slipest.units import G
from tests.log_makers import can_frames, stream, write_can_log, write_csv


def test_a_file_that_is_not_a_blf_or_an_empty_one_is_named_not_a_traceback(tmp_path, capsys):
    for name, data in (("garbage.blf", b"\x00\x01 not a BLF container " * 40), ("empty.blf", b"")):
        (tmp_path / name).write_bytes(data)
        assert main(["replay", str(tmp_path / name), "-o", str(tmp_path / "out.csv")]) == 2
        err = capsys.readouterr().err
        assert f"{name}: python-can cannot open it" in err and "Traceback" not in err


def test_a_blf_cut_short_is_said_to_be_and_what_it_holds_is_replayed(tmp_path, capsys):
    run, _ = stream(n_cycles=6, seed=2)
    whole = write_can_log(tmp_path / "drive.blf", can_frames({0: run}))
    data = (tmp_path / "drive.blf").read_bytes()
    (tmp_path / "cut.blf").write_bytes(data[: 2 * len(data) // 3])
    assert main(["replay", whole, "-o", str(tmp_path / "whole.csv")]) == 0
    assert "cut short" not in capsys.readouterr().err
    main(["replay", str(tmp_path / "cut.blf"), "-o", str(tmp_path / "cut.csv")])
    err = capsys.readouterr().err
    assert "cut.blf is cut short" in err and "the frames in them are lost" in err
    assert len((tmp_path / "cut.csv").read_text().splitlines()) > 1  # the cycles it holds


def test_a_log_without_samples_says_so(tmp_path, capsys):
    (tmp_path / "header.csv").write_text("# nL=4\nt,az,theta,slip\n")
    assert main(["replay", str(tmp_path / "header.csv"), "-o", str(tmp_path / "out.csv")]) == 1
    assert "no leg cycle: the log holds no samples" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["replay", "diagnose", "calibrate"])
def test_no_legs_is_refused_by_the_arguments(tmp_path, capsys, command):
    with pytest.raises(SystemExit) as exc:
        main([command, "x.csv", "--legs", "0"] + (["-o", str(tmp_path / "r.json")] if command == "calibrate" else []))
    assert exc.value.code == 2 and "'0' is not a number of legs" in capsys.readouterr().err


def test_diagnose_names_az_logged_in_g_before_fitting(tmp_path, capsys):
    run, sc = stream(n_cycles=4, seed=8)
    run.az[:] = run.az / G
    log = write_csv(tmp_path / "in_g.csv", run, sc)
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(log), "--quick", "--no-progress"])
    assert "in_g.csv: az looks like it is in g (a median of " in str(exc.value.code)
