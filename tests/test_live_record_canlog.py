"""`--record` of the raw CAN frames in python-can's log formats: a live `slipest can` run (firmware-sim over
the CAN server, every part in its own process) recorded in several formats at once, each replayed by
`slipest replay` to the very rows the live run printed; complete after SIGTERM (and a second signal);
flushed as it goes; the errors a user can meet."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import can
import pytest

from slipest.cli.estimate_output import parse_rows
from slipest.cli.main import main
from slipest.io.bus_args import BusConfig
from slipest.io.can_messages import encode_imu
from slipest.io.can_source import CanSource
from slipest.io.serial_source import SerialSource
from slipest.live.recording import FrameRecorder, Recording, record_kind
from tests.hil_support import Stopping, can_server, firmware_sim, slipest_cmd, socketcand_args

PERIOD = 2 * math.pi / (4 * 0.63)
BLF_HEADER = 144  # bytes of a BLF's file header, written first


def window(k: int, frac: float = 0.5) -> float:
    return (k + 0.5 + 0.5 * frac) * PERIOD


def live_rows(proc) -> dict:
    return {(int(r["wheel"]), int(r["cycle"])): r for r in parse_rows(proc.lines, ("wheel",))}


def replayed_rows(log, capsys) -> tuple[dict, str]:
    rc = main(["replay", str(log)])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return live_rows(type("P", (), {"lines": out.splitlines()})), err


def test_a_live_can_run_recorded_in_python_can_formats_replays_to_the_rows_printed_live(tmp_path, capsys):
    logs = [tmp_path / "drive.asc", tmp_path / "drive.blf", tmp_path / "drive.log", tmp_path / "drive.trc.gz"]
    pycsv = tmp_path / "frames.csv"  # python-can's CSV: --record-frames (a .csv --record is the samples)
    samples = tmp_path / "samples.csv"
    report = tmp_path / "live.json"
    with Stopping() as procs:
        server, port = can_server()
        procs.add(server)
        est = procs.add(slipest_cmd("can", *socketcand_args(port), *[a for p in logs for a in ("--record", str(p))],
                                    "--record-frames", str(pycsv), "--record", str(samples), "--report", str(report),
                                    "--cycles", "6", "--idle-timeout", "3", "--duration", "60"))
        est.wait_err("listening on CAN bus", timeout=60)
        dev = procs.add(firmware_sim("can", *socketcand_args(port), "--wheels", "2", "--cycles", "7", "--speed", "8",
                                     "--noise", "0.01", "--seed", "8", "--send-reference",
                                     "--fault", f"drop@{window(2):.3f}:n=1",
                                     "--fault", f"unknown-ids@{window(1):.3f}:n=13"))
        est.wait_line(r"^0,1,", timeout=30)
        # flushed as it goes: the frames of the first cycles are on disk while the run goes on
        asc_lines = sum(1 for _ in open(logs[0]))
        blf_size = os.path.getsize(logs[1])
        assert asc_lines > 2000 and blf_size > BLF_HEADER + 4096, (asc_lines, blf_size)
        assert est.wait(60) == 0, est.stderr
        dev.wait(30)
    live = json.loads(report.read_text())
    src = live["source"]
    received = src["ok"] + src["unknown_id"] + src["bad_frame"] + src["not_data"]
    assert src["unknown_id"] == 13 and src["ok"] > 20000
    printed = live_rows(est)
    assert {w for w, _ in printed} == {0, 1} and printed[(0, 2)]["quality"] == "repaired"  # the lost frame, bridged
    assert int(printed[(0, 2)]["n_repaired"]) == 1
    assert sum(r["quality"] == "ok" for r in printed.values()) >= 10
    for log in logs + [pycsv]:
        # every frame received is in the log, as the counters say
        frames = list(can.LogReader(str(log)))
        assert len(frames) == received == live["estimation"]["frame_logs"][str(log)]["frames_recorded"], log
        assert sum(not 0x110 <= m.arbitration_id <= 0x135 for m in frames) == 13  # the unknown IDs too
        rows, err = replayed_rows(log, capsys)
        assert rows == printed, log  # every column of every row
        assert f"{received} CAN frames read" in err and "13 other IDs" in err
    # the samples recording is still the .csv --record
    assert samples.read_text().startswith("# nL=4")


def test_a_frame_log_is_complete_after_sigterm_and_a_second_signal(tmp_path, capsys):
    blf = tmp_path / "drive.blf"
    asc = tmp_path / "drive.asc.gz"
    report = tmp_path / "live.json"
    with Stopping() as procs:
        server, port = can_server()
        procs.add(server)
        est = procs.add(slipest_cmd("can", *socketcand_args(port), "--record", str(blf), "--record", str(asc),
                                    "--report", str(report), "--no-publish"))
        est.wait_err("listening on CAN bus", timeout=60)
        procs.add(firmware_sim("can", *socketcand_args(port), "--cycles", "20", "--speed", "8", "--noise", "0.01",
                               "--seed", "3"))
        est.wait_line(r"^0,2,", timeout=30)
        est.signal(signal.SIGTERM)
        # once it said it took the SIGTERM: sent 5 ms after it instead, both signals could be pending together
        # (under load) and the lower-numbered SIGINT is then handled first, whatever the order they were sent in
        est.wait_err("stopping (interrupted (SIGTERM))", timeout=30)
        est.signal(signal.SIGINT)  # an impatient second signal while it stops
        assert est.wait(30) == 0, est.stderr
    live = json.loads(report.read_text())
    assert live["reason"] == "interrupted (SIGTERM)"
    received = live["source"]["ok"] + live["source"]["unknown_id"]
    printed = live_rows(est)
    for log in (blf, asc):
        assert len(list(can.LogReader(str(log)))) == received  # the BLF's header written, the gzip closed
        rows, _ = replayed_rows(log, capsys)
        assert rows == printed and len(printed) >= 3


def test_serial_refuses_a_can_log_and_says_why(tmp_path, capsys):
    rc = main(["serial", "/dev/null", "--record", str(tmp_path / "drive.blf")])
    err = capsys.readouterr().err
    assert rc != 0 and "serial frames" in err and "--record run.csv" in err and "rounded" in err
    assert not (tmp_path / "drive.blf").exists()
    with pytest.raises(SystemExit):  # (argparse: slipest serial has no --record-frames)
        main(["serial", "/dev/null", "--record-frames", str(tmp_path / "f.csv")])
    capsys.readouterr()
    # the library says it for any source without CAN frames, before creating a file
    with pytest.raises(ValueError, match="delivers none"):
        Recording([str(tmp_path / "a.asc")], source=SerialSource("/dev/null"), n_legs=4)
    assert not (tmp_path / "a.asc").exists()


def test_an_existing_log_is_never_overwritten_unless_told(tmp_path, capsys):
    old = tmp_path / "drive.asc"
    old.write_text("precious\n")
    bus = ["-i", "socketcand", "-c", "vcan0", "--bus-option", "host=127.0.0.1", "--bus-option", "port=9"]
    new = tmp_path / "new.blf"
    rc = main(["can", *bus, "--record", str(new), "--record", str(old)])
    err = capsys.readouterr().err
    assert rc != 0 and "drive.asc exists" in err and "--overwrite" in err
    assert old.read_text() == "precious\n" and not new.exists()  # checked before any file is created


@pytest.mark.parametrize("name,match", [("x.txt", "not a python-can log"), ("x.blf.gz", "cannot write it"),
                                        ("x.db.gz", "cannot write it")])
def test_frame_logs_python_can_cannot_write_or_replay_cannot_read_are_refused(tmp_path, name, match):
    with pytest.raises(ValueError, match=match):
        FrameRecorder(str(tmp_path / name))


def test_mf4_needs_asammdf_and_says_which_extra_brings_it(tmp_path):
    """Without asammdf (hidden from a fresh interpreter here), recording a .mf4 and replaying one are refused
    naming `pip install 'slipest[mf4]'` (python-can's own message names its extra, not slipest's)."""
    hidden = "import sys; sys.modules['asammdf'] = None\n"
    record = hidden + ("from slipest.live.recording import FrameRecorder\n"
                       "try:\n    FrameRecorder(sys.argv[1])\nexcept ValueError as exc:\n    sys.exit(str(exc))\n")
    p = subprocess.run([sys.executable, "-c", record, str(tmp_path / "x.mf4")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 1 and "pip install 'slipest[mf4]'" in p.stderr and "x.mf4" in p.stderr, p.stderr
    assert not (tmp_path / "x.mf4").exists()
    drive = tmp_path / "drive.mf4"
    drive.write_bytes(b"MDF     4.10    ")  # refused on opening, before a byte is read
    replay = hidden + "from slipest.cli.main import main\nsys.exit(main(['replay', sys.argv[1]]))\n"
    p = subprocess.run([sys.executable, "-c", replay, str(drive)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "pip install 'slipest[mf4]'" in p.stderr and "drive.mf4" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and p.stdout == ""


def test_with_asammdf_a_mf4_recorder_opens(tmp_path):
    pytest.importorskip("asammdf", reason="the [mf4] extra is not installed (not in [test]: pyproject.toml says why)")
    rec = FrameRecorder(str(tmp_path / "y.mf4"))
    rec.close()
    assert (tmp_path / "y.mf4").stat().st_size > 0


@pytest.mark.parametrize("name,kind", [("a.csv", "samples"), ("a.CSV", "samples"), ("run", "samples"),
                                       ("a.txt", "samples"), ("a.asc", "frames"), ("a.BLF", "frames"),
                                       ("a.log", "frames"), ("a.trc", "frames"), ("a.db", "frames"),
                                       ("a.mf4", "frames"), ("a.asc.gz", "frames"), ("a.csv.gz", "frames")])
def test_what_a_name_records(name, kind):
    assert record_kind(name) == kind  # as `slipest replay` reads the file back


def test_a_write_error_is_raised_in_the_loop_naming_the_file(tmp_path):
    """A frame log on a full disk (/dev/full): the reader thread's write fails, the next flush raises it
    with the file's name and the counts; nothing is written halfway afterwards."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full here")
    path = tmp_path / "full.asc"
    path.symlink_to("/dev/full")
    rec = FrameRecorder(str(path), overwrite=True)
    for i in range(2000):
        rec(encode_imu(0, i, 9.81, 0.1, i * 1e-3))
    assert rec.frames_not_recorded > 0 and rec.error is not None
    with pytest.raises(OSError, match=r"full\.asc: recording the CAN frames failed .* frames recorded"):
        rec.flush(force=True)
    with pytest.raises(OSError):
        rec.close()


def test_a_can_source_gives_its_listeners_every_frame_before_decoding(tmp_path):
    """In-process: the CAN server in a thread, a CanSource with a frame log, frames of ours, of unknown IDs
    and malformed ones sent by a plain python-can bus: the log holds every one, in order."""
    from slipest.io.socketcand_server import start_in_thread

    host, port, stop = start_in_thread()
    config = BusConfig("socketcand", "vcan0", {"host": host, "port": port})
    log = tmp_path / "all.log"
    source = CanSource(config)
    rec = Recording([str(log)], source=source, n_legs=4)
    sender = None
    try:
        source.start(wait_open=5)
        stop.wait_for_clients(1)
        sender = can.Bus(interface="socketcand", host=host, port=port, channel="vcan0")
        sent = []
        for i in range(300):
            msg = encode_imu(i % 2, i, 9.81, 0.1, i * 1e-3) if i % 3 else can.Message(
                arbitration_id=0x7F0 + i % 5, data=bytes([i % 256]) * (i % 9), is_extended_id=False)
            sender.send(msg)
            sent.append((msg.arbitration_id, bytes(msg.data)))
        deadline = time.monotonic() + 10
        while rec.frame_logs[0].frames < len(sent) and time.monotonic() < deadline:
            time.sleep(0.02)
            rec.flush()
    finally:
        if sender is not None:
            sender.shutdown()
        source.close()
        rec.close()
        stop()
    got = [(m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(log))]
    assert got == sent
    assert rec.counters() == {str(log): {"frames_recorded": 300, "frames_not_recorded": 0}}


def test_a_samples_recording_that_cannot_be_written_names_its_file_and_rows(tmp_path):
    """A samples CSV on a full disk (/dev/full): the error names the file and the rows it holds (was a bare
    "[Errno 28] No space left on device")."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full here")
    import numpy as np

    from slipest.io.device_stream import WheelSamples
    from slipest.live.recording import Recorder

    path = tmp_path / "full.csv"
    path.symlink_to("/dev/full")
    rec = Recorder(str(path), n_legs=4, overwrite=True)
    with pytest.raises(OSError, match=r"full\.csv: recording the samples failed \(No space left on device\) after "
                                      r"0 rows"):
        rec.open_wheel(0)
        n = 5000
        rec.add(0, WheelSamples(np.arange(n) * 1e-3, np.full(n, 9.81), np.zeros(n), np.full(n, np.nan),
                                np.zeros(n, bool), np.zeros(n)))
        rec.flush(force=True)
