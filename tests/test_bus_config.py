"""CAN options as python-can's tools take them: its configuration when -i/-c are omitted, and --bus-kwargs."""

from __future__ import annotations

import argparse
import os
import subprocess

import can
import pytest

from slipest.io.bus_args import add_bus_arguments, bus_config_from_args, resolve_bus_config
from tests.hil_support import PY


@pytest.fixture
def no_can_config(tmp_path, monkeypatch):
    """python-can sees no configuration but what a test gives it (a fresh HOME, no CAN_* variables)."""
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    if any(cfg for cfg in (can.rc, can.util.load_file_config())):
        pytest.skip("a python-can configuration outside HOME (e.g. /etc/can.conf) is in the way")
    return tmp_path


def _args(argv):
    p = argparse.ArgumentParser()
    add_bus_arguments(p)
    return p.parse_args(argv)


def test_bus_kwargs_is_bus_option_spelt_as_python_can_does(no_can_config):
    args = _args(["-i", "virtual", "-c", "x", "--bus-kwargs", "a=1", "b=true", "c=0x10", "--bus-option", "d=text"])
    assert bus_config_from_args(args).options == {"a": 1, "b": True, "c": 16, "d": "text"}


def test_without_interface_the_environment_is_used_and_the_bus_opens(no_can_config, monkeypatch):
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "from-env")
    config = bus_config_from_args(_args([]))
    assert (config.interface, config.channel) == ("virtual", "from-env")
    assert bus_config_from_args(_args(["-c", "from-cli"])).channel == "from-cli"  # the command line wins
    with config.open() as bus, can.Bus(interface="virtual", channel="from-env") as peer:
        peer.send(can.Message(arbitration_id=0x123, data=b"\x01\x02"))
        msg = bus.recv(2.0)
    assert msg is not None and msg.arbitration_id == 0x123 and bytes(msg.data) == b"\x01\x02"


def test_without_interface_the_config_file_is_used(no_can_config):
    (no_can_config / ".canrc").write_text("[default]\ninterface = virtual\nchannel = from-file\nbitrate = 250000\n")
    config = bus_config_from_args(_args(["--bus-option", "receive_own_messages=true"]))
    assert (config.interface, config.channel) == ("virtual", "from-file")
    assert config.options == {"bitrate": 250000, "receive_own_messages": True}
    assert bus_config_from_args(_args(["-b", "500000"])).options["bitrate"] == 500000  # the command line wins


def test_no_interface_anywhere_says_where_to_give_one(no_can_config):
    with pytest.raises(ValueError, match=r"no CAN interface: give -i/--interface .*CAN_INTERFACE.*~/\.canrc"):
        bus_config_from_args(_args([]))
    with pytest.raises(ValueError, match=r'Unknown interface type "nope" \(python-can knows: .*socketcand'):
        resolve_bus_config("nope", "x")


def test_the_commands_use_python_cans_configuration(no_can_config, capsys):
    env = dict(os.environ)  # the fixture took CAN_* out and set HOME
    p = subprocess.run([PY, "-m", "slipest", "can", "--duration", "0.3"], capture_output=True, text=True, timeout=120,
                       env={**env, "CAN_INTERFACE": "virtual", "CAN_CHANNEL": "configured"})
    assert p.returncode == 0, p.stderr
    assert "INFO slipest.can: listening on CAN bus virtual:configured" in p.stderr
    # without a configuration both commands refuse before any work: their CLIs in this process (the fixture's
    # environment is this process's), no new interpreter's start-up
    from firmware_sim import cli as device_cli
    from slipest.cli.main import main

    capsys.readouterr()
    rc = main(["can", "--duration", "0.3"])
    err = capsys.readouterr().err
    assert rc == 1 and "ERROR slipest.can: no CAN interface: give -i/--interface" in err
    assert "Unknown interface type" not in err
    with pytest.raises(SystemExit) as exc:
        device_cli.main(["can", "--cycles", "1"])
    assert exc.value.code == 2 and "no CAN interface: give -i/--interface" in capsys.readouterr().err
