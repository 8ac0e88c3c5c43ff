"""The one way slipest builds a python-can bus from command-line arguments.

Every command that talks CAN (``slipest can``, ``firmware-sim can``, the
benchmarks in ``tools/``) takes the same options, as python-can's own tools
do::

    -i/--interface NAME        python-can interface (socketcan, socketcand, virtual, slcan, ...)
    -c/--channel CHANNEL       its channel (vcan0, can0, /dev/ttyACM0, ...)
    -b/--bitrate BPS
    --bus-option KEY=VALUE     any keyword of the interface's Bus class, repeatable;
                               values are parsed as int (also 0x..), float, bool
                               (true/false/yes/no/on/off), none, else kept as text
    --bus-kwargs KEY=VALUE...  the same, as python-can's tools spell it (several after one flag)

e.g. ``--interface socketcand --channel can0 --bus-option host=127.0.0.1
--bus-option port=29536`` for slipest's own server (``slipest can-server``).
What the command line leaves out comes from python-can's own configuration
(:func:`can.util.load_config`: ``$CAN_INTERFACE``, ``$CAN_CHANNEL``,
``$CAN_BITRATE``, then the ``[default]`` section of ``~/can.conf``,
``/etc/can.conf``, ``~/.can``, ``~/.canrc``), as python-can's tools do;
options on the command line win.  With no interface anywhere, the error
says where to give one.
For socketcand, ``tcp_tune`` (TCP_NODELAY) is on unless told otherwise: at
1 kHz, Nagle's algorithm with delayed ACKs held frames back for up to 40 ms.

:class:`BusConfig` opens the bus and turns the ways a bus fails to open into
one :class:`BusOpenError` with a message that says what to do.
:class:`ReconnectingBus` keeps a bus alive: it reports and survives errors,
and recognises a dead socketcand server (python-can's client then returns
``None`` from ``recv`` forever while spinning, and ``send`` raises
``BrokenPipeError``), shutting the bus down and opening it again, with
back-off, until the server is back.
"""

from __future__ import annotations

import argparse
import logging
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can

from slipest.io.source import one_line

__all__ = [
    "BusOpenError",
    "BusConfig",
    "ReconnectingBus",
    "add_bus_arguments",
    "bus_config_from_args",
    "resolve_bus_config",
    "parse_bus_option",
    "parse_bus_value",
]

log = logging.getLogger(__name__)

_TRUE = {"true", "yes", "on"}
_FALSE = {"false", "no", "off"}


class BusOpenError(RuntimeError):
    """A CAN bus could not be opened (the message says why and what to try)."""


def parse_bus_value(text: str) -> Any:
    """``"500000"`` -> 500000, ``"0x1F"`` -> 31, ``"1.5"`` -> 1.5, ``"true"`` -> True,
    ``"none"`` -> None; anything else stays text."""
    s = text.strip()
    low = s.lower()
    if low in _TRUE:
        return True
    if low in _FALSE:
        return False
    if low in ("none", "null"):
        return None
    try:
        return int(s, 0)
    except ValueError:
        pass
    try:
        return float(s)
    except ValueError:
        return s


def parse_bus_option(text: str) -> tuple[str, Any]:
    """``KEY=VALUE`` -> ``(key, parsed value)``; ValueError naming the problem."""
    key, eq, value = text.partition("=")
    key = key.strip()
    if not eq or not key or not key.replace("_", "").isalnum():
        raise ValueError(f"--bus-option {text!r}: expected KEY=VALUE (e.g. port=29536)")
    return key, parse_bus_value(value)


def add_bus_arguments(parser: argparse.ArgumentParser, *, default_interface: str | None = None,
                      default_channel: str | None = None) -> None:
    """Add the bus options (see the module docstring) to ``parser``."""
    g = parser.add_argument_group("CAN bus (python-can)")
    configured = "python-can's configuration ($CAN_INTERFACE, $CAN_CHANNEL, ~/.canrc, /etc/can.conf)"
    g.add_argument("-i", "--interface", default=default_interface,
                   help="python-can interface: socketcan, socketcand, virtual, slcan, serial, ... (default: "
                   + (default_interface or configured) + ")")
    g.add_argument("-c", "--channel", default=default_channel,
                   help="channel of the interface, e.g. vcan0, can0, /dev/ttyACM0 (default: "
                   + (default_channel or configured) + ")")
    g.add_argument("-b", "--bitrate", type=int, default=None, help="bit rate [bit/s], where the interface needs one")
    g.add_argument("--bus-option", action="append", default=[], metavar="KEY=VALUE",
                   help="keyword argument of the interface's Bus, repeatable; e.g. --bus-option host=127.0.0.1 "
                   "--bus-option port=29536 for socketcand, --bus-option sleep_after_open=0 for slcan")
    g.add_argument("--bus-kwargs", action="extend", nargs="+", dest="bus_option", metavar="KEY=VALUE",
                   help="the same as --bus-option, spelt as python-can's tools do: --bus-kwargs host=127.0.0.1 "
                   "port=29536")


@dataclass
class BusConfig:
    """How to open one bus: python-can interface, channel and keyword options."""

    interface: str | None
    channel: str | None
    options: dict = field(default_factory=dict)

    def kwargs(self) -> dict:
        kw = dict(self.options)
        if self.interface == "socketcand":
            # small frames at 1 kHz: without TCP_NODELAY, Nagle's algorithm and delayed
            # ACKs hold some frames back for up to 40 ms (measured); --bus-option
            # tcp_tune=false restores python-can's default
            kw.setdefault("tcp_tune", True)
        if self.interface is not None:
            kw["interface"] = self.interface
        if self.channel is not None:
            kw["channel"] = self.channel
        return kw

    def describe(self) -> str:
        opts = ", ".join(f"{k}={v}" for k, v in self.options.items())
        return f"{self.interface or '(configured)'}:{self.channel or '-'}" + (f" ({opts})" if opts else "")

    def _probe_socketcand(self) -> None:
        host = self.options.get("host")
        port = self.options.get("port")
        if host is None or port is None:
            raise BusOpenError("socketcand needs --bus-option host=H --bus-option port=P "
                               "(slipest can-server prints them)")
        try:
            with socket.create_connection((str(host), int(port)), timeout=1.0):
                pass
        except OSError as exc:
            raise BusOpenError(f"no socketcand server at {host}:{port} ({exc.strerror or exc}); "
                               "start one with `slipest can-server --port P`") from None

    def open(self) -> can.BusABC:
        """Open the bus; :class:`BusOpenError` with a helpful message when it cannot be."""
        if self.interface == "socketcand":
            # python-can's client retries for 10 s in a busy loop when nobody
            # listens; probe first so an absent server fails at once.
            self._probe_socketcand()
            _quiet_socketcand_splits()
        try:
            return can.Bus(**self.kwargs())
        except (can.CanError, OSError, ValueError, TypeError, ImportError, NotImplementedError) as exc:
            hint = ""
            if self.interface == "socketcan":
                hint = ("; SocketCAN needs a Linux kernel with CAN support and the interface up "
                        "(e.g. `ip link add vcan0 type vcan && ip link set up vcan0`); without it, use "
                        "`slipest can-server` and --interface socketcand")
            raise BusOpenError(f"cannot open CAN bus {self.describe()}: {type(exc).__name__}: {exc}{hint}") from exc


class _DropIncompleteWarning(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Got incomplete message")


_SPLIT_FILTER = _DropIncompleteWarning()


def _quiet_socketcand_splits() -> None:
    """python-can's socketcand client warns "Got incomplete message" on every
    ordinary TCP split; drop that one warning (others stay)."""
    logger = logging.getLogger("can.interfaces.socketcand.socketcand")
    if _SPLIT_FILTER not in logger.filters:
        logger.addFilter(_SPLIT_FILTER)


def bus_config_from_args(args: argparse.Namespace) -> BusConfig:
    """The :class:`BusConfig` the bus options of ``args`` describe, completed from python-can's
    configuration (:func:`resolve_bus_config`); ValueError on a bad option or no interface at all."""
    options: dict = {}
    for text in getattr(args, "bus_option", None) or []:
        key, value = parse_bus_option(text)
        options[key] = value
    if getattr(args, "bitrate", None) is not None:
        options["bitrate"] = args.bitrate
    return resolve_bus_config(args.interface, args.channel, options)


def _configured_interface() -> str | None:
    """The interface python-can's configuration names, if any (can.rc, environment, files)."""
    for cfg in (can.rc, can.util.load_environment_config(), can.util.load_file_config()):
        name = cfg.get("interface") or cfg.get("bustype")
        if name:
            return str(name)
    return None


def resolve_bus_config(interface: str | None = None, channel: str | None = None,
                       options: dict | None = None) -> BusConfig:
    """A :class:`BusConfig` with what is not given taken from python-can's configuration.

    ``interface``, ``channel`` and ``options`` (keywords of the Bus) win over
    the configuration (:func:`can.util.load_config`: ``$CAN_INTERFACE``,
    ``$CAN_CHANNEL``, ``$CAN_BITRATE``, the ``[default]`` section of
    ``~/can.conf``, ``/etc/can.conf``, ``~/.can``, ``~/.canrc``), which fills
    the rest.  ValueError when no interface is given or configured, when it
    is not one python-can knows, or when a configured value is invalid.
    """
    given = dict(options or {})
    if interface is not None:
        given["interface"] = interface
    if channel is not None:
        given["channel"] = channel
    if "interface" not in given and _configured_interface() is None:
        raise ValueError("no CAN interface: give -i/--interface (and -c/--channel), or configure python-can: "
                         "CAN_INTERFACE and CAN_CHANNEL in the environment, or a [default] section with "
                         "interface = ... and channel = ... in ~/.canrc or /etc/can.conf")
    try:
        cfg = dict(can.util.load_config(config=given))
    except can.CanInterfaceNotImplementedError as exc:
        raise ValueError(f"{exc} (python-can knows: {', '.join(sorted(can.VALID_INTERFACES))})") from None
    except (ValueError, TypeError) as exc:
        raise ValueError(f"python-can's configuration: {exc}") from None
    resolved_interface = cfg.pop("interface")
    resolved_channel = cfg.pop("channel", None)
    return BusConfig(resolved_interface, resolved_channel, cfg)


def _socket_of(bus) -> socket.socket | None:
    for name in ("_SocketCanDaemonBus__socket", "socket", "_socket"):
        sock = getattr(bus, name, None)
        if isinstance(sock, socket.socket):
            return sock
    return None


def _peer_closed(bus) -> bool:
    """True when the bus's TCP socket (socketcand) has reached end of file or is unusable (closed
    here, or an error); peeks without consuming data.  False for a bus without a TCP socket."""
    sock = _socket_of(bus)
    if sock is None or sock.type != socket.SOCK_STREAM:
        return False
    if sock.fileno() < 0:
        return True
    try:
        return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True


def _shutdown_quietly(bus) -> None:
    try:
        bus.shutdown()
    except Exception:  # a dead bus may fail to shut down; it is gone either way
        pass


class ReconnectingBus:
    """A bus that survives its own failures.

    :meth:`recv` and :meth:`send` never raise for a failing bus: an error is
    counted (``errors``), the bus is shut down and reopened (``reconnects``)
    with back-off between ``min_backoff`` and ``max_backoff`` seconds; while
    it is down, :meth:`recv` returns None after the timeout and :meth:`send`
    returns False (counted in ``send_failed``).  A dead socketcand server is
    recognised (end of file on its socket, or ``recv`` spinning: returning
    None having used most of its time on the CPU).  Thread-safe: one thread
    may receive while another sends.  ``on_event(text)`` hears every
    error and reconnection.
    """

    def __init__(self, config: BusConfig, *, on_event=None, min_backoff: float = 0.1, max_backoff: float = 0.5,
                 bus: can.BusABC | None = None):
        self.config = config
        self.on_event = on_event or (lambda text: None)
        self.min_backoff = min_backoff
        self.max_backoff = max_backoff
        self._lock = threading.RLock()
        self._bus = bus
        self._backoff = min_backoff
        self._next_try = 0.0
        self._closed = False
        self.errors = 0
        self.reconnects = 0
        self.send_failed = 0
        self.last_error: str | None = None
        self._was_open = bus is not None
        self._receiving = None  # the bus a thread is receiving on
        self._dead = None  # a failed bus to shut down once that thread is out of recv

    # -- state -------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._bus is not None

    def open(self, wait: float = 0.0) -> bool:
        """Open now (or within ``wait`` seconds of retries); True when open."""
        deadline = time.monotonic() + wait
        while True:
            if self._ensure():
                return True
            if self._closed or time.monotonic() >= deadline:
                return False
            time.sleep(min(self._backoff, max(0.0, deadline - time.monotonic())))

    def _ensure(self) -> bool:
        with self._lock:
            if self._bus is not None:
                return True
            if self._closed:
                return False
            now = time.monotonic()
            if now < self._next_try:
                return False
            try:
                self._bus = self.config.open()
            except BusOpenError as exc:
                self.last_error = one_line(str(exc))
                self._next_try = now + self._backoff
                self._backoff = min(self.max_backoff, self._backoff * 2)
                return False
            self._backoff = self.min_backoff
            if self._was_open:
                self.reconnects += 1
                self.on_event(f"CAN bus {self.config.describe()} reconnected")
            self._was_open = True
            return True

    def _fail(self, bus, why: str) -> None:
        with self._lock:
            if self._bus is not bus or bus is None:
                return  # another thread already handled it
            self.errors += 1
            why = one_line(why)
            self.last_error = why
            self.on_event(f"CAN bus {self.config.describe()}: {why}; reconnecting")
            self._bus = None
            self._next_try = time.monotonic() + self._backoff
            if self._receiving is bus:
                self._dead = bus  # the receiving thread shuts it down when it leaves recv
                return
        _shutdown_quietly(bus)

    # -- I/O -----------------------------------------------------------------------
    def recv(self, timeout: float = 0.1) -> can.Message | None:
        if not self._ensure():
            if timeout:
                wait = timeout if self._closed else min(timeout, max(0.01, self._next_try - time.monotonic()))
                time.sleep(wait)
            return None
        with self._lock:
            bus = self._bus
            if bus is None:
                return None
            self._receiving = bus
        cpu0 = time.thread_time()
        wall0 = time.monotonic()
        failed = False
        try:
            msg = bus.recv(timeout)
        except (can.CanError, OSError, ValueError) as exc:
            msg = None
            failed = True
            self._fail(bus, f"receive failed: {type(exc).__name__}: {exc}")
        finally:
            with self._lock:
                self._receiving = None
                dead, self._dead = self._dead, None
        if dead is not None:
            _shutdown_quietly(dead)
            return None
        if failed:
            return None
        if msg is None and timeout:
            wall = time.monotonic() - wall0
            spinning = wall >= 0.5 * timeout and time.thread_time() - cpu0 >= 0.7 * wall
            if _peer_closed(bus) or spinning:
                self._fail(bus, "connection closed by the server" if not spinning else "receive spins with no data")
        return msg

    def send(self, msg: can.Message, timeout: float | None = 0.05) -> bool:
        if not self._ensure():
            self.send_failed += 1
            return False
        bus = self._bus
        if bus is None:
            self.send_failed += 1
            return False
        try:
            bus.send(msg, timeout)
            return True
        except (can.CanError, OSError, ValueError) as exc:
            self.send_failed += 1
            self._fail(bus, f"send failed: {type(exc).__name__}: {exc}")
            return False

    def counters(self) -> dict:
        return {"bus_errors": self.errors, "bus_reconnects": self.reconnects, "send_failed": self.send_failed}

    def shutdown(self) -> None:
        with self._lock:
            self._closed = True
            bus, self._bus = self._bus, None
            if bus is not None and self._receiving is bus:
                self._dead, bus = bus, None  # shut down by the receiving thread
        if bus is not None:
            _shutdown_quietly(bus)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()
