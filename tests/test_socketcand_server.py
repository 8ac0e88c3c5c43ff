"""Tests of the socketcand shared-bus server, with real python-can clients in
separate processes, python-can's logger/player CLIs and raw TCP clients."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

from slipest.io import socketcand_server as ss
from slipest.cli.main import main
from slipest.io.bus_args import BusConfig, BusOpenError, ReconnectingBus

# A python-can peer in its own process.  argv: bus kwargs (JSON), mode, n.
#   echo N: send back each of N received frames;  send N: after a line on
#   stdin, send N numbered frames;  recv N: print the N received frames (JSON).
PEER = r"""
import json, sys, can
kwargs, mode, n = json.loads(sys.argv[1]), sys.argv[2], int(sys.argv[3])
if kwargs.get("interface") == "socketcand":
    from slipest.io.bus_args import BusConfig
    kwargs.pop("interface")
    bus = BusConfig("socketcand", kwargs.pop("channel"), kwargs).open()
else:
    bus = can.Bus(**kwargs)
print("READY", flush=True)
try:
    if mode == "echo":
        for _ in range(n):
            msg = bus.recv(10)
            if msg is None:
                print("TIMEOUT", flush=True)
                break
            bus.send(can.Message(arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                                 data=msg.data, dlc=msg.dlc))
    elif mode == "send":
        sys.stdin.readline()
        for i in range(n):
            ext = i % 3 == 0
            bus.send(can.Message(arbitration_id=(i * 7919) & (0x1FFFFFFF if ext else 0x7FF),
                                 is_extended_id=ext, data=i.to_bytes(4, "little")))
    elif mode == "recv":
        got = []
        for _ in range(n):
            msg = bus.recv(10)
            if msg is None:
                break
            got.append([msg.arbitration_id, msg.is_extended_id, msg.data.hex()])
        print(json.dumps(got), flush=True)
finally:
    bus.shutdown()
print("DONE", flush=True)
"""


def numbered_frame(i: int) -> tuple[int, bool, str]:
    ext = i % 3 == 0
    return (i * 7919) & (0x1FFFFFFF if ext else 0x7FF), ext, i.to_bytes(4, "little").hex()


def start_peer(bus_kwargs: dict, mode: str, n: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", PEER, json.dumps(bus_kwargs), mode, str(n)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline().strip()
    if line != "READY":
        proc.kill()
        raise AssertionError(f"peer did not start: {line!r}")
    return proc


def finish_peer(proc: subprocess.Popen, timeout: float = 15.0) -> list[str]:
    out, _ = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, out
    return out.splitlines()


def socketcand_kwargs(host: str, port: int) -> dict:
    return {"interface": "socketcand", "host": host, "port": port, "channel": "vcan0"}


def socketcand_bus(host: str, port: int, channel: str = "vcan0") -> can.BusABC:
    """A python-can socketcand bus on the server, opened the library's way (bus_args)."""
    return BusConfig("socketcand", channel, {"host": host, "port": port}).open()


def msg_tuple(msg: can.Message) -> tuple[int, bool, str]:
    return msg.arbitration_id, msg.is_extended_id, bytes(msg.data).hex()


def sample_frames():
    frames = []
    for dlc in range(9):
        frames.append(can.Message(arbitration_id=0x100 + dlc, is_extended_id=False, data=bytes(range(0xF7, 0xF7 + dlc))))
        frames.append(can.Message(arbitration_id=0x1ABC0000 + dlc, is_extended_id=True, data=bytes(range(dlc))))
    frames += [can.Message(arbitration_id=0x000, is_extended_id=False, data=b"\x00"),
               can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\xff" * 8),
               can.Message(arbitration_id=0x00000000, is_extended_id=True, data=b""),
               can.Message(arbitration_id=0x000007FF, is_extended_id=True, data=b"\x01"),  # ext, looks small
               can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=b"\x0a" * 8)]
    return frames


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def cli_server():
    """The server as a separate process, started through its CLI."""
    proc = subprocess.Popen([sys.executable, "-m", "slipest.cli.main", "can-server", "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert line.startswith("socketcand server listening on 127.0.0.1:"), line
    port = int(line.rsplit(":", 1)[1])
    yield "127.0.0.1", port
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0
    assert "stopped: " in err and "frames_in=" in err


@pytest.fixture
def thread_server():
    host, port, stop = ss.start_in_thread(port=0)
    yield host, port, stop
    stop()


# --------------------------------------------------------------------------- cross-process


def test_two_processes_exchange_frames_both_directions(cli_server):
    host, port = cli_server
    frames = sample_frames()
    peer = start_peer(socketcand_kwargs(host, port), "echo", len(frames))
    with socketcand_bus(host, port) as bus:
        for msg in frames:
            bus.send(msg)
        echoed = [bus.recv(5.0) for _ in frames]
    finish_peer(peer)
    assert all(m is not None for m in echoed)
    assert [msg_tuple(m) for m in echoed] == [msg_tuple(m) for m in frames]
    assert [m.dlc for m in echoed] == [m.dlc for m in frames]
    assert all(m.channel == "vcan0" and m.timestamp > 1e9 for m in echoed)


def test_many_frames_without_loss_in_order(cli_server):
    host, port = cli_server
    n = 5000
    # peer -> this process
    with socketcand_bus(host, port) as bus:
        sender = start_peer(socketcand_kwargs(host, port), "send", n)
        sender.stdin.write("go\n")
        sender.stdin.flush()
        got = []
        for _ in range(n):
            msg = bus.recv(5.0)
            assert msg is not None, f"only {len(got)} of {n} frames arrived"
            got.append(msg_tuple(msg))
        finish_peer(sender)
        assert got == [numbered_frame(i) for i in range(n)]
        # this process -> peer
        receiver = start_peer(socketcand_kwargs(host, port), "recv", n)
        for i in range(n):
            arb, ext, data = numbered_frame(i)
            bus.send(can.Message(arbitration_id=arb, is_extended_id=ext, data=bytes.fromhex(data)))
        lines = finish_peer(receiver)
    assert [tuple(x) for x in json.loads(lines[0])] == [numbered_frame(i) for i in range(n)]


def test_channels_are_separate_buses(thread_server):
    host, port, stop = thread_server
    with socketcand_bus(host, port, "vcan0") as a, socketcand_bus(host, port, "can1") as b, \
            socketcand_bus(host, port, "can1") as c:
        b.send(can.Message(arbitration_id=0x42, is_extended_id=False, data=b"\x01"))
        got = c.recv(2.0)
        assert got is not None and msg_tuple(got) == (0x42, False, "01")
        assert a.recv(0.2) is None  # other channel
        assert b.recv(0.1) is None  # no echo to the sender
    assert stop.stats()["frames_out"] == 1


# --------------------------------------------------------------------------- python-can CLIs


def tcp_rx_queues_to(port: int) -> list[int]:
    """rx_queue of every local TCP socket connected to 127.0.0.1:port (Linux)."""
    out = []
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        remote, queues = fields[2], fields[4]
        if remote == f"0100007F:{port:04X}":
            out.append(int(queues.split(":")[1], 16))
    return out


#: Runs the module named by argv[1] as ``python -m`` would, with Ctrl-C raising KeyboardInterrupt. A
#: process started in the background by a non-interactive shell (``cmd &``, as CI runners may) inherits
#: SIGINT ignored, and Python then installs no KeyboardInterrupt handler: can.logger, which stops on
#: KeyboardInterrupt, would ignore the test's SIGINT (seen: both cases timed out under such a run).
_RUN_WITH_CTRL_C = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
                    "mod = sys.argv.pop(1); runpy.run_module(mod, run_name='__main__', alter_sys=True)")


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_can_logger_records_frames_to_a_file(thread_server, tmp_path, suffix):
    host, port, stop = thread_server
    path = tmp_path / f"capture{suffix}"
    logger = subprocess.Popen(
        [sys.executable, "-u", "-c", _RUN_WITH_CTRL_C, "can.logger", "-i", "socketcand", "-c", "vcan0", "-f", str(path),
         "--bus-kwargs", f"host={host}", f"port={port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = logger.stdout.readline()
        assert line.startswith("Connected to SocketCanDaemonBus"), line + logger.stderr.read()
        frames = sample_frames()
        with socketcand_bus(host, port) as bus:
            for msg in frames:
                bus.send(msg)
            # everything delivered to the logger's socket and read by it
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                if stop.stats()["frames_out"] == len(frames) and not any(tcp_rx_queues_to(port)):
                    break
                time.sleep(0.02)
            time.sleep(0.1)
        logger.send_signal(signal.SIGINT)
        logger.communicate(timeout=10)
    finally:
        if logger.poll() is None:
            logger.kill()
    recorded = list(can.LogReader(str(path)))
    assert [msg_tuple(m) for m in recorded] == [msg_tuple(m) for m in frames]


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_can_player_replays_a_file_into_the_bus(thread_server, tmp_path, suffix):
    host, port, stop = thread_server
    path = tmp_path / f"replay{suffix}"
    frames = sample_frames()
    with can.Logger(str(path)) as writer:
        for k, msg in enumerate(frames):
            writer(can.Message(timestamp=1000.0 + 0.001 * k, arbitration_id=msg.arbitration_id,
                               is_extended_id=msg.is_extended_id, data=msg.data, channel="vcan0"))
    with socketcand_bus(host, port) as bus:
        # "--" ends --bus-kwargs (it takes any number of values) before the file name
        player = subprocess.run(
            [sys.executable, "-m", "can.player", "-i", "socketcand", "-c", "vcan0",
             "--bus-kwargs", f"host={host}", f"port={port}", "--", str(path)],
            capture_output=True, text=True, timeout=20)
        assert player.returncode == 0, player.stderr
        got = [bus.recv(5.0) for _ in frames]
        assert bus.recv(0.1) is None
    assert all(m is not None for m in got)
    assert [msg_tuple(m) for m in got] == [msg_tuple(m) for m in frames]


# --------------------------------------------------------------------------- robustness


def raw_client(host: str, port: int, channel: bytes = b"vcan0", rcvbuf: int | None = None) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(5)
    sock.connect((host, port))
    assert sock.recv(64) == b"< hi >"
    sock.sendall(b"< open " + channel + b" >")
    assert sock.recv(64) == b"< ok >"
    sock.sendall(b"< rawmode >")
    assert sock.recv(64) == b"< ok >"
    return sock


def test_garbage_tcp_splits_and_disconnect_mid_message(thread_server):
    host, port, stop = thread_server
    with socketcand_bus(host, port) as rx:
        sock = socket.create_connection((host, port), timeout=5)
        assert sock.recv(64) == b"< hi >"
        sock.sendall(b"< send 123 1 01 >")  # before open: refused
        for byte in b"< open vcan0 >":  # split into single bytes
            sock.sendall(bytes([byte]))
        assert sock.recv(64) == b"< ok >"
        sock.sendall(b"< raw")
        time.sleep(0.01)
        sock.sendall(b"mode >")
        assert sock.recv(64) == b"< ok >"
        sock.sendall(b"< echo >")
        assert sock.recv(64) == b"< echo >"
        stream = (b"garbage text\r\n"          # 11 non-whitespace garbage bytes
                  b"< bogus >"                 # unknown command
                  b"< send 12G 1 00 >"         # bad hex ID
                  b"< send 123 9 1 2 3 4 5 6 7 8 9 >"  # DLC 9: no CAN FD
                  b"< send 123 2 01 >"         # fewer bytes than DLC
                  b"< send 800 0 >"            # 11-bit ID out of range
                  b"< send 1234 0 >"           # 4 hex digits: neither 11- nor 29-bit
                  b"< send 123 1 100 >"        # byte token too long
                  b"< send 1 2 a b >"          # valid: 0x001, data 0a 0b
                  b"< send 1FFFFFFF 1 ff >"    # valid: extended
                  b"< x < send 00000010 0 >")  # "< x " is garbage (3 bytes), then valid
        for i in range(0, len(stream), 5):  # TCP splits everywhere
            sock.sendall(stream[i:i + 5])
            time.sleep(0.001)
        sock.sendall(b"< send 123 1 ")  # ... and gone mid-message
        sock.close()
        got = [rx.recv(2.0) for _ in range(3)]
        assert rx.recv(0.2) is None
    assert [msg_tuple(m) for m in got] == [(0x001, False, "0a0b"), (0x1FFFFFFF, True, "ff"),
                                           (0x10, True, "")]
    deadline = time.monotonic() + 2
    while stop.stats()["clients"] != 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    s = stop.stats()
    assert s["bad_commands"] == 8
    assert s["garbage_bytes"] == len(b"garbagetext") + len(b"<x")  # whitespace is not counted
    assert s["clients"] == 0 and s["clients_total"] == 3  # rx, the connection BusConfig.open probed with, sock
    assert s["frames_in"] == 3


def test_long_garbage_is_bounded_and_bus_keeps_working(thread_server):
    host, port, stop = thread_server
    with socketcand_bus(host, port) as rx:
        sock = raw_client(host, port)
        sock.sendall(b"<" + b"A" * 100_000)  # never closed
        sock.sendall(b"> < send 7 1 07 >")
        got = rx.recv(2.0)
        assert got is not None and msg_tuple(got) == (0x007, False, "07")
        sock.close()
    s = stop.stats()
    assert s["bad_commands"] >= 1 and s["garbage_bytes"] >= 100_000


def test_open_refused_channel_and_unknown_commands():
    host, port, stop = ss.start_in_thread(channels=["can0"])
    try:
        sock = socket.create_connection((host, port), timeout=5)
        assert sock.recv(64) == b"< hi >"
        sock.sendall(b"< open vcan0 >")
        assert sock.recv(64).startswith(b"< error")
        sock.sendall(b"< open can0 >")
        assert sock.recv(64) == b"< ok >"
        sock.close()
        with pytest.raises(BusOpenError, match="error") as refused:
            socketcand_bus(host, port, "vcan0")
        assert isinstance(refused.value.__cause__, can.CanError)
        with socketcand_bus(host, port, "can0"):
            pass
    finally:
        stop()


def stream_numbered(host: str, port: int, stop, n: int, clients: int) -> tuple[list[int], dict, int]:
    """Send n numbered frames from one python-can client to another that reads them, once ``clients`` are in
    raw mode: (numbers received, the server's stats at the end, the most bytes it had queued at a check)."""
    with socketcand_bus(host, port) as tx, socketcand_bus(host, port) as rx:
        assert stop.wait_for_clients(clients)
        received = []

        def drain():
            while len(received) < n:
                msg = rx.recv(5.0)
                if msg is None:
                    return
                received.append(int.from_bytes(msg.data, "little"))

        reader = threading.Thread(target=drain)
        reader.start()
        queued = 0
        for i in range(n):
            tx.send(can.Message(arbitration_id=0x55, is_extended_id=False, data=i.to_bytes(4, "little")))
            if i % 100 == 0:  # a reading client keeps up: at most ~500 frames (20 KB) behind
                deadline = time.monotonic() + 5
                while len(received) < i - 400 and time.monotonic() < deadline:
                    time.sleep(0.001)
            if i % 2000 == 0:
                queued = max(queued, stop.stats()["bytes_queued"])
        reader.join(30)
        return received, stop.stats(), queued


def test_a_client_that_never_reads_does_not_stall_the_bus():
    host, port, stop = ss.start_in_thread(max_client_buffer=64 * 1024, sndbuf=16 * 1024)
    try:
        stuck = raw_client(host, port, rcvbuf=4096)  # connected, in raw mode, never reads
        n = 20_000
        received, s, _ = stream_numbered(host, port, stop, n, clients=3)
        stuck.close()
    finally:
        stop()
    assert received == list(range(n))  # the reading client lost nothing
    assert s["frames_dropped"] > 0  # the stuck client's overflow was dropped
    assert s["frames_out"] + s["frames_dropped"] == 2 * n


def test_connections_past_the_limit_are_refused_and_counted():
    host, port, stop = ss.start_in_thread(max_clients=3)
    try:
        first = [raw_client(host, port) for _ in range(3)]
        extra = socket.create_connection((host, port), timeout=5)
        assert extra.recv(64) == b"< error too many clients >"
        assert extra.recv(64) == b""  # and closed
        extra.close()
        with pytest.raises(BusOpenError, match="too many clients"):  # python-can's client says why
            socketcand_bus(host, port)
        first[0].close()
        deadline = time.monotonic() + 5
        while stop.stats()["clients"] > 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        again = raw_client(host, port)  # room again
        s = stop.stats()
        for sock in first[1:] + [again]:
            sock.close()
    finally:
        stop()
    assert s["clients_refused"] >= 2 and s["clients"] == 3 and s["clients_dropped"] == 0


def test_at_the_connection_limit_a_new_client_takes_the_place_of_a_stuck_one():
    host, port, stop = ss.start_in_thread(max_clients=3, sndbuf=16 * 1024)
    reading = threading.Event()
    reading.set()
    try:
        stuck = raw_client(host, port, rcvbuf=4096)  # never reads
        reader = raw_client(host, port)
        reader.settimeout(0.05)

        def keep_reading():  # the reader keeps up: nothing stays queued for it
            while reading.is_set():
                try:
                    if not reader.recv(65536):
                        return  # the server went (the test failed before its end): stop, do not spin
                except socket.timeout:
                    pass
                except OSError:
                    return

        drainer = threading.Thread(target=keep_reading, daemon=True)
        drainer.start()
        tx = raw_client(host, port)  # the third
        tx.sendall(b"".join(b"< send 55 4 %x %x 0 0 >" % (i & 0xFF, i >> 8) for i in range(20000)))
        deadline = time.monotonic() + 5
        while stop.stats()["bytes_queued"] == 0 and time.monotonic() < deadline:  # the stuck client's queue
            time.sleep(0.01)
        newcomer = raw_client(host, port)  # a fourth: the stuck one makes room
        stuck.settimeout(5)
        with pytest.raises(ConnectionResetError):  # reset: its unread bytes go with the connection
            while stuck.recv(65536):
                pass
        s = stop.stats()
        reading.clear()
        drainer.join(5)
        for sock in (stuck, reader, tx, newcomer):
            sock.close()
    finally:
        reading.clear()  # also when the test fails: a reader left spinning kept a failed run alive for an hour
        stop()
    assert s["clients_dropped"] == 1 and s["clients_refused"] == 0 and s["clients"] == 3


def test_many_clients_that_never_read_are_dropped_slowest_first_and_the_reader_loses_nothing():
    """A total budget: 30 clients that never read, 1 MiB for all their queues together; the server drops the
    slowest clients (most bytes queued) to stay within it, and a client that reads receives every frame."""
    budget = 1 << 20
    host, port, stop = ss.start_in_thread(max_buffer=budget, max_client_buffer=512 * 1024, sndbuf=16 * 1024)
    stuck = []
    try:
        stuck = [raw_client(host, port, rcvbuf=4096) for _ in range(30)]
        n = 40_000
        received, s, peak = stream_numbered(host, port, stop, n, clients=32)
        reset = ended = 0
        for sock in stuck:  # a dropped one is reset (not a FIN queued behind bytes it will never read)
            sock.settimeout(0.5)
            try:
                while sock.recv(65536):
                    pass
                ended += 1
            except ConnectionResetError:
                reset += 1
            except socket.timeout:  # still connected: nothing more comes
                pass
    finally:
        for sock in stuck:
            sock.close()
        stop()
    assert received == list(range(n))  # the reading client lost nothing
    assert s["clients_dropped"] >= 20  # most of the 30 went, one by one
    assert s["bytes_queued_peak"] <= budget + 64 * 1024  # over by one delivery at most, before a drop
    assert peak <= budget
    assert reset == s["clients_dropped"] and ended == 0 and s["clients"] == 2 + 30 - s["clients_dropped"]


def test_clients_joining_a_busy_bus_always_complete_the_handshake(thread_server):
    host, port, stop = thread_server
    running = threading.Event()
    running.set()

    def blast():
        with socketcand_bus(host, port) as tx:
            i = 0
            while running.is_set():
                tx.send(can.Message(arbitration_id=0x10, is_extended_id=False, data=bytes([i & 0xFF])))
                i += 1
                if i % 50 == 0:
                    time.sleep(0.001)

    sender = threading.Thread(target=blast)
    sender.start()
    try:
        for _ in range(15):  # "< ok >" must arrive alone after "< rawmode >"
            with socketcand_bus(host, port) as bus:
                assert bus.recv(2.0) is not None  # and frames do flow
    finally:
        running.clear()
        sender.join(5)


def test_dead_server_is_detected():
    host, port, stop = ss.start_in_thread()
    config = BusConfig("socketcand", "vcan0", {"host": host, "port": port})
    events = []
    watched = ReconnectingBus(config, on_event=events.append, min_backoff=5.0)
    bus = config.open()  # the server answers
    try:
        assert watched.open()
        assert watched.recv(0.05) is None and watched.errors == 0  # a quiet bus is not a dead one
        stop()
        deadline = time.monotonic() + 2
        while watched.errors == 0 and time.monotonic() < deadline:
            watched.recv(0.01)
        assert watched.errors == 1 and not watched.connected
        assert "connection closed by the server" in events[0] or "receive spins with no data" in events[0]
        with pytest.raises(BusOpenError, match="no socketcand server"):
            config.open()
        with pytest.raises(OSError):  # BrokenPipeError / ConnectionResetError
            for _ in range(5):
                bus.send(can.Message(arbitration_id=1, is_extended_id=False, data=b""))
                time.sleep(0.02)
    finally:
        bus.shutdown()
        watched.shutdown()
    with ReconnectingBus(BusConfig("virtual", "x")) as other:  # no TCP socket: never taken for a dead server
        assert other.open() and other.recv(0.05) is None and other.errors == 0


def test_only_loopback_addresses_are_accepted():
    with pytest.raises(ValueError, match="loopback"):
        ss.start_in_thread(host="0.0.0.0")
    with pytest.raises(ValueError, match="loopback"):
        ss.ServerThread(host="example.org")
    with pytest.raises(SystemExit, match="loopback"):
        main(["can-server", "--host", "0.0.0.0", "--port", "0"])


# --------------------------------------------------------------------------- real SocketCAN


def vcan0_unavailable() -> str | None:
    """Why vcan0 cannot be used here, or None when it can."""
    if not hasattr(socket, "AF_CAN"):
        return "no SocketCAN in this kernel: socket.AF_CAN does not exist on this platform"
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return f"no SocketCAN in this kernel: socket(AF_CAN, SOCK_RAW) failed: {exc}"
    try:
        sock.bind(("vcan0",))
    except OSError as exc:
        return f"no SocketCAN in this kernel: cannot bind a CAN_RAW socket to vcan0: {exc}"
    finally:
        sock.close()
    return None


def test_round_trip_over_real_vcan0():
    reason = vcan0_unavailable()
    if reason:
        pytest.skip(reason)
    kwargs = {"interface": "socketcan", "channel": "vcan0"}
    frames = sample_frames()
    with can.Bus(**kwargs) as bus:
        peer = start_peer(kwargs, "echo", len(frames))
        for msg in frames:
            bus.send(msg)
        echoed = [bus.recv(5.0) for _ in frames]
        finish_peer(peer)
    assert [msg_tuple(m) for m in echoed] == [msg_tuple(m) for m in frames]


def test_idle_connections_that_open_no_bus_cannot_lock_the_others_out(monkeypatch):
    """Connections that never open a bus (a port scanner, a hostile client) fill the limit: once they have been
    idle for OPEN_GRACE, a new client takes the place of the oldest (used to be refused for as long as they
    stayed)."""
    monkeypatch.setattr(ss, "OPEN_GRACE", 0.3)
    host, port, stop = ss.start_in_thread(max_clients=3)
    idle = []
    try:
        idle = [socket.create_connection((host, port), timeout=5) for _ in range(3)]
        for sock in idle:
            assert sock.recv(64) == b"< hi >"
        refused = socket.create_connection((host, port), timeout=5)  # within the grace: refused
        assert refused.recv(64) == b"< error too many clients >"
        refused.close()
        time.sleep(0.5)
        bus = socketcand_bus(host, port)  # past it: the oldest idle one makes room
        bus.shutdown()
        try:  # it was the one dropped (reset, as a dropped client is)
            gone = idle[0].recv(64) == b""
        except ConnectionResetError:
            gone = True
        assert gone
        s = stop.stats()
    finally:
        for sock in idle:
            sock.close()
        stop()
    assert s["clients_dropped"] >= 1 and s["clients_refused"] == 1
