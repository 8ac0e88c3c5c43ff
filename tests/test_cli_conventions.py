"""The command line's conventions: `python -m slipest`, --version, the package's top-level names, py.typed,
logging (-v/-q/--log-level), `--format jsonl` for live commands, and `--config rover.toml`."""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

import slipest
from slipest.cli import command
from slipest.cli.config_file import ConfigFileError, file_keys, load_config_file
from slipest.cli.main import main, parse_args
from slipest.online import ESTIMATE_FIELDS
from tests.hil_support import PY, Stopping, firmware_sim, serial_device, slipest_cmd, stop_once_said
from tests.cli_support import slipest_in_process

ROOT = Path(__file__).resolve().parents[1]
#: A log line: date, time to the millisecond, level, logger, message.
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} (DEBUG|INFO|WARNING|ERROR) ([\w.]+): (.*)$")


def _run(*args, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([PY, *args], capture_output=True, text=True, timeout=120, cwd=ROOT, **kwargs)


# --- entry points and the package ---------------------------------------------------------------------------


def test_python_m_slipest_and_the_versions():
    p = _run("-m", "slipest", "--version")
    assert p.returncode == 0 and p.stdout.strip() == f"slipest {slipest.__version__}"
    p = _run("-m", "slipest", "replay", "--help")
    assert p.returncode == 0 and "usage: slipest replay" in p.stdout
    p = _run("-m", "firmware_sim", "--version")
    assert p.returncode == 0 and p.stdout.strip() == f"firmware-sim {slipest.__version__}"
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert pyproject["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "slipest.__version__"}


def test_import_slipest_is_cheap_and_its_names_load_on_first_use():
    p = _run("-c", "import slipest, sys; print(sorted(m for m in ('numpy', 'numba', 'scipy', 'can', 'slipest.online') "
             "if m in sys.modules)); from slipest import SlipEstimator; print(SlipEstimator.__module__)")
    assert p.returncode == 0, p.stderr
    assert p.stdout.split("\n")[:2] == ["[]", "slipest.online"]
    from slipest.live import LiveEstimation
    from slipest.online import SlipEstimator

    assert slipest.SlipEstimator is SlipEstimator and slipest.LiveEstimation is LiveEstimation
    assert slipest.ESTIMATE_FIELDS == ESTIMATE_FIELDS
    assert all(hasattr(slipest, name) for name in slipest.__all__)
    assert set(slipest.__all__) <= set(dir(slipest))
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        slipest.Nope  # noqa: B018


def test_the_package_ships_py_typed():
    assert (ROOT / "slipest" / "py.typed").is_file()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in pyproject["tool"]["setuptools"]["package-data"]["slipest"]
    assert pyproject["project"]["license"] == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")


# --- logging --------------------------------------------------------------------------------------------------


def _levels(argv):
    p = argparse.ArgumentParser()
    command.add_logging_arguments(p)
    return logging.getLevelName(command.log_level(p.parse_args(argv)))


def test_log_levels_from_the_options():
    assert _levels([]) == "INFO"
    assert _levels(["-v"]) == "DEBUG" and _levels(["-vv"]) == "DEBUG"
    assert _levels(["-q"]) == "WARNING" and _levels(["-qq"]) == "ERROR" and _levels(["-qqq"]) == "ERROR"
    assert _levels(["-q", "-v"]) == "INFO"
    assert _levels(["-q", "--log-level", "debug"]) == "DEBUG"


def test_live_messages_go_through_logging_with_time_and_level(capsys):
    base = ["-m", "slipest", "can", "-i", "virtual", "-c", "conventions", "--duration", "0.3"]
    p = _run(*base)
    assert p.returncode == 0 and p.stdout == ""  # no cycle: no estimates, not even a header
    lines = p.stderr.strip().split("\n")
    parsed = [LOG_LINE.match(line) for line in lines if not line.startswith("  ")]  # counters: indented lines
    assert all(parsed), lines
    assert ("INFO", "slipest.can", "listening on CAN bus virtual:conventions") in [m.groups() for m in parsed]
    assert any(m.group(3) == "counters:" for m in parsed)
    quiet = _run(*base, "-q")
    assert quiet.returncode == 0 and quiet.stderr == ""  # INFO hidden
    # a fatal error is logged at ERROR, shown even with -q, and the command fails
    # (refused: the CLI in this process, see _main)
    rc, err = slipest_in_process(capsys, "serial", str(ROOT / "no-such-port"), "--wait-open", "0.2", "-q")
    assert rc == 1
    m = LOG_LINE.match(err.strip())
    assert m and m.group(1) == "ERROR" and m.group(2) == "slipest.serial" and "no-such-port" in m.group(3), err


# --- --config --------------------------------------------------------------------------------------------------


def _config(tmp_path, text: str) -> Path:
    path = tmp_path / "rover.toml"
    path.write_text(text)
    return path


def test_a_config_file_gives_the_options_and_the_command_line_overrides_it(tmp_path):
    cfg = _config(tmp_path, 'port = "/dev/ttyUSB7"\nlegs = 5\nwheel = [0, 1]\nmodel = "models/m.json"\nkS = 1000\n'
                  'stuck_samples = 0\nuse-reference = true\nformat = "jsonl"\nlog-level = "warning"\nquiet = 1\n')
    args = parse_args(["serial", "--config", str(cfg)])
    assert (args.port, args.legs, args.wheel, args.kS, args.stuck_samples) == ("/dev/ttyUSB7", 5, [0, 1], 1000.0, 0)
    assert args.use_reference is True and args.format == "jsonl" and args.log_level == "WARNING" and args.quiet == 1
    assert args.model == str(tmp_path / "models" / "m.json")  # relative to the file
    args = parse_args(["serial", "/dev/ttyACM0", "--config", str(cfg), "--legs", "4", "--wheel", "2", "-q", "-q"])
    assert (args.port, args.legs, args.wheel, args.quiet) == ("/dev/ttyACM0", 4, [2], 2)  # replaced, not added to
    assert args.kS == 1000.0  # the rest still from the file
    can = _config(tmp_path, 'interface = "socketcand"\nchannel = "can0"\nbus-kwargs = { host = "127.0.0.1", '
                  'port = 29536, tcp_tune = false }\nbus-option = ["a=1"]\n')
    args = parse_args(["can", "--config", str(can)])
    assert (args.interface, args.channel) == ("socketcand", "can0")
    assert sorted(args.bus_option) == ["a=1", "host=127.0.0.1", "port=29536", "tcp_tune=false"]
    from slipest.io.bus_args import bus_config_from_args

    assert bus_config_from_args(args).options == {"a": 1, "host": "127.0.0.1", "port": 29536, "tcp_tune": False}


@pytest.mark.parametrize("text,message", [
    ("wheels = [0]", "unknown key 'wheels' (did you mean 'wheel'?)"),
    ("config = 'x.toml'", "unknown key 'config' (keys: baudrate, cycles, dphi, duration, format, "),
    ("legs = 'four'", "key 'legs': expected a whole number of legs >= 1, got 'four'"),
    ("legs = 4.5", "key 'legs': expected a whole number of legs >= 1, got 4.5"),
    ("legs = 0", "key 'legs': expected a whole number of legs >= 1, got 0"),
    ("kS = true", "key 'kS': true/false is for flags; expected a number"),
    ("use-reference = 1", "key 'use-reference': a flag takes true or false, got 1"),
    ("method = 'magic'", "key 'method': 'magic' is not one of default, eq515"),
    ("wheel = { a = 1 }", "key 'wheel': expected a list, got a table"),
    ("legs = [4]", "key 'legs': expected a single value, got a list"),
    ("legs = ", "not valid TOML: "),
])
def test_a_bad_config_file_names_the_file_and_the_key(tmp_path, text, message):
    cfg = _config(tmp_path, text + "\n")
    with pytest.raises(ConfigFileError) as err:
        load_config_file(str(cfg), _serial_parser())
    assert str(err.value).startswith(f"{cfg}: {message}")


def test_a_bad_config_file_stops_the_command_with_a_usage_error(tmp_path, capsys):
    cfg = _config(tmp_path, "wheels = [0]\n")
    rc, err = slipest_in_process(capsys, "serial", "--config", str(cfg))
    assert rc == 2
    assert err.strip().endswith(f"slipest serial: error: {cfg}: unknown key 'wheels' (did you mean 'wheel'?)")
    rc, err = slipest_in_process(capsys, "serial", "--config", str(tmp_path / "missing.toml"))
    assert rc == 2 and f"{tmp_path / 'missing.toml'}: no such file" in err
    rc, err = slipest_in_process(capsys, "serial", "--config", str(_config(tmp_path, "legs = 4\n")),
                                 "--wait-open", "0.1")
    assert rc == 1 and "no PORT" in err


def _serial_parser():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    from slipest.cli import serial_cmd

    serial_cmd.add_parser(sub)
    return sub.choices["serial"]


def test_every_live_option_can_be_in_the_file():
    keys = file_keys(_serial_parser())
    for key in ("port", "baudrate", "legs", "wheel", "model", "method", "kS", "phiS", "phiD", "dphi", "record",
                "format", "log-level", "quiet", "verbose", "duration", "stuck-samples", "use-reference",
                "quiet-notice"):
        assert key in keys, key
    assert "config" not in keys and "help" not in keys


def test_a_quiet_link_is_said_after_5_s_unless_told_otherwise():
    from slipest.live.loop import run_live

    parser = _serial_parser()
    assert parser.parse_args(["/dev/ttyX"]).quiet_notice == 5.0 == inspect.signature(run_live).parameters[
        "quiet_notice"].default
    assert parser.parse_args(["/dev/ttyX", "--quiet-notice", "2"]).quiet_notice == 2.0


def test_a_quiet_notice_that_is_not_a_positive_time_is_refused_before_the_port_is_opened(capsys):
    rc, err = slipest_in_process(capsys, "serial", "/dev/ttyNONE", "--quiet-notice", "0")
    assert rc != 0
    assert "--quiet-notice must be a number of seconds > 0" in err and "ttyNONE" not in err


# --- a live run from a config file, estimates as JSON lines -----------------------------------------------------


def test_live_serial_from_a_config_file_prints_json_lines_that_replay_agrees_with(tmp_path, capsys):
    rec = tmp_path / "rec.wheel1.csv"  # "rec.csv" names wheel 0's recording; wheel 1's is this
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--cycles", "5", "--speed", "16", "--noise", "0.01", "--seed", "3",
                                     "--wheels", "2", "--linger", "0.3"))
        cfg = _config(tmp_path, f'port = "{serial_device(dev)}"\nwheel = [1]\nformat = "jsonl"\nrecord = "rec.csv"\n'
                      'idle-timeout = 3\nduration = 60\nlog-level = "WARNING"\n')
        est = procs.add(slipest_cmd("serial", "--config", str(cfg)))
        # (the run's 60 s duration counts from its start, the device's preparation included: with the kernels
        # compiled cold that took 135 s under load, the run left first and the device waited for a reader
        # forever. tests/conftest.py compiles them before the tests)
        assert dev.wait(60) == 0, dev.stderr
        stop_once_said(est, ": disconnected (")  # the device's end read (a WARNING): not 3 s of idle later
        assert est.wait(60) == 0, est.stderr
    rows = [json.loads(line) for line in est.lines]
    assert len(rows) >= 4 and all(tuple(r) == ("wheel",) + ESTIMATE_FIELDS and r["wheel"] == 1 for r in rows)
    assert all(LOG_LINE.match(line).group(1) == "WARNING" for line in est.err_lines if not line.startswith("  "))
    ok = [r for r in rows if r["quality"] == "ok"]
    assert len(ok) >= 3 and all(0.1 < r["slip"] < 0.45 for r in ok)  # true slip 0.25
    # the replay in this process: the CLI's code path (as tests/test_live_record_canlog.py::replayed_rows)
    capsys.readouterr()
    rc = main(["replay", str(rec), "--format", "jsonl"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    replayed = [json.loads(line) for line in out.splitlines()]
    assert len(replayed) == len(rows)
    for live, again in zip(rows, replayed):  # the same (the recording keeps az to 1e-6 m/s^2: floats to 1e-4)
        assert list(again) == list(ESTIMATE_FIELDS)
        for key, value in again.items():
            if isinstance(value, float):
                assert live[key] == pytest.approx(value, rel=1e-4), key
            else:
                assert live[key] == value, key


def test_format_none_prints_no_estimates(tmp_path):
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--cycles", "3", "--speed", "16", "--noise", "0.01", "--linger", "0.3"))
        est = procs.add(slipest_cmd("serial", serial_device(dev), "--format", "none", "--idle-timeout", "3",
                                    "--report", str(tmp_path / "r.json")))
        assert dev.wait(60) == 0
        stop_once_said(est, ": disconnected (")  # the device's end read: not 3 s of idle later
        assert est.wait(60) == 0, est.stderr
    assert est.lines == []
    assert json.loads((tmp_path / "r.json").read_text())["estimation"]["estimates"] >= 2
