"""Helpers of the hardware-in-the-loop tests: real subprocesses, their output lines.

:class:`Proc` runs a command (``python -m firmware_sim ...``, ``python -m
slipest ...``) and collects its stdout and stderr lines in threads, so a
test can wait for an announcement (the pty path, the server's port) without
blocking on a pipe.  Every process is stopped by its own id at the end.
"""

from __future__ import annotations

import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time

PY = sys.executable


#: What a firmware-sim device prints once it streams, and how long it may take to get there [s]: it simulates its
#: whole run first, and on a cold numba cache (a fresh install, CI) compiles the simulator's kernels, which took
#: more than 60 s on a loaded 2-core machine (slipest demo waits as long: ``slipest/cli/demo.py``).
DEVICE_READY = "firmware-sim: streaming"
DEVICE_READY_TIMEOUT = 300.0


class Proc:
    """A subprocess with its output lines collected (``lines``, ``err_lines``).

    ``ready``: a stdout text the process prints once its work starts (None: from the start); :meth:`wait`
    counts its timeout from then, after up to ``ready_timeout`` [s] of preparation."""

    def __init__(self, args: list[str], ready: str | None = None, ready_timeout: float = DEVICE_READY_TIMEOUT,
                 **kwargs):
        self.args = args
        self.ready = ready
        self.ready_timeout = ready_timeout
        self.p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1, **kwargs)
        self.lines: list[str] = []
        self.err_lines: list[str] = []
        self._q: queue.Queue = queue.Queue()
        self._threads = [
            threading.Thread(target=self._pump, args=(self.p.stdout, self.lines, True), daemon=True),
            threading.Thread(target=self._pump, args=(self.p.stderr, self.err_lines, False), daemon=True),
        ]
        for t in self._threads:
            t.start()

    def _pump(self, stream, sink, notify):
        for line in stream:
            line = line.rstrip("\n")
            sink.append(line)
            if notify:
                self._q.put(line)
        if notify:
            self._q.put(None)

    def wait_line(self, pattern: str, timeout: float = 20.0) -> re.Match:
        """The first new stdout line matching the regex ``pattern``."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no line matching {pattern!r} from {self.args[:4]}; "
                                   f"stdout {self.lines[-5:]}, stderr {self.err_lines[-10:]}")
            try:
                line = self._q.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                raise RuntimeError(f"{self.args[:4]} ended (rc={self.p.wait()}) before {pattern!r}; "
                                   f"stderr: {self.err_lines[-10:]}")
            m = rx.search(line)
            if m:
                return m

    def wait_err(self, text: str, timeout: float = 20.0) -> None:
        """Wait until ``text`` appears on stderr."""
        deadline = time.monotonic() + timeout
        while text not in self.stderr:
            if time.monotonic() > deadline or self.p.poll() is not None:
                raise TimeoutError(f"{text!r} not on the stderr of {self.args[:4]}: {self.err_lines[-10:]}")
            time.sleep(0.02)

    def wait(self, timeout: float = 60.0) -> int:
        """The exit status, within ``timeout`` [s] of the ``ready`` text (see the class docstring)."""
        if self.ready is not None:
            deadline = time.monotonic() + self.ready_timeout
            while (self.p.poll() is None and time.monotonic() < deadline
                   and not any(self.ready in line for line in list(self.lines))):
                time.sleep(0.02)
        rc = self.p.wait(timeout)
        for t in self._threads:
            t.join(timeout=5)
        return rc

    def signal(self, sig=signal.SIGTERM) -> None:
        if self.p.poll() is None:
            self.p.send_signal(sig)

    def stop(self) -> None:
        """Stop this process (SIGTERM, then SIGKILL) by its own id."""
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(5)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        for t in self._threads:
            t.join(timeout=5)

    @property
    def stderr(self) -> str:
        return "\n".join(self.err_lines)


def said_in_order(text: str, *parts: str) -> bool:
    """Whether ``parts`` stand in ``text`` in this order (each after the end of the previous one)."""
    at = 0
    for part in parts:
        at = text.find(part, at)
        if at < 0:
            return False
        at += len(part)
    return True


def stop_once_said(proc: Proc, *texts: str, timeout: float = 30.0) -> None:
    """SIGTERM ``proc`` (a live run) once ``texts`` stand on its stderr in this order, e.g. its serial device's
    disconnection after the device exited: everything the device sent has been read by then, so the run can
    stop there (a normal stop: the last cycles, the counters, the report) instead of waiting out an idle
    timeout.  A process that has exited already is left alone; TimeoutError when they are not said within
    ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not said_in_order(proc.stderr, *texts) and proc.p.poll() is None:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{texts!r} not in this order on the stderr of {proc.args[:4]}: {proc.err_lines[-10:]}")
        time.sleep(0.02)
    proc.signal(signal.SIGTERM)


class Stopping(list):
    """The processes of a ``with`` block, each stopped by its own id at the end, whatever happens."""

    def add(self, proc: Proc) -> Proc:
        self.append(proc)
        return proc

    def __enter__(self) -> "Stopping":
        return self

    def __exit__(self, *exc) -> None:
        for proc in reversed(self):
            proc.stop()


def firmware_sim(*args: str) -> Proc:
    """``python -m firmware_sim ARGS``; :meth:`Proc.wait` gives it its timeout from when it streams."""
    return Proc([PY, "-m", "firmware_sim", *args], ready=DEVICE_READY)


def slipest_cmd(*args: str) -> Proc:
    return Proc([PY, "-m", "slipest.cli.main", *args])


def serial_device(proc: Proc, timeout: float = 30.0) -> str:
    """The pty path a ``firmware-sim serial`` process announced."""
    return proc.wait_line(r"firmware-sim: serial device (\S+)", timeout).group(1)


def can_server(*options: str) -> tuple[Proc, int]:
    """``slipest can-server --port 0 [options]`` in its own process: (process, port)."""
    proc = slipest_cmd("can-server", "--port", "0", *options)
    port = int(proc.wait_line(r"listening on [\d.]+:(\d+)", 20).group(1))
    return proc, port


def socketcand_args(port: int, channel: str = "vcan0") -> list[str]:
    return ["-i", "socketcand", "-c", channel, "--bus-option", "host=127.0.0.1", "--bus-option", f"port={port}"]


def vcan0_available() -> tuple[bool, str]:
    """Whether SocketCAN's vcan0 can be used here (and why not)."""
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except (AttributeError, OSError) as exc:
        return False, f"no SocketCAN in this kernel (socket(AF_CAN) failed: {exc})"
    try:
        sock.bind(("vcan0",))
    except OSError as exc:
        return False, f"SocketCAN present but vcan0 is not up ({exc})"
    finally:
        sock.close()
    return True, ""
