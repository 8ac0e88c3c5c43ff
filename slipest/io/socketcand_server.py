"""A shared virtual CAN bus over TCP, speaking the socketcand protocol.

There is no SocketCAN in some kernels (no ``vcan0``), and python-can's
``virtual`` interface only connects buses inside one process.  This small
asyncio server lets any number of processes share a bus through python-can's
``socketcand`` client (``can.Bus(interface="socketcand", host=..., port=...,
channel="vcan0")``), and so also ``python -m can.logger``, ``can.player`` and
``can.viewer``.  Every frame one client sends is delivered to every *other*
client that opened the same channel (like SocketCAN without
``CAN_RAW_RECV_OWN_MSGS``).  Nothing is read from or written to a real bus.
It binds loopback addresses only.

Protocol (ASCII, no line ends; what python-can 4.x's client does)::

    server -> client   < hi >                        on connect
    client -> server   < open vcan0 >                channel name, 1..15 chars
    server -> client   < ok >
    client -> server   < rawmode >
    server -> client   < ok >
    client -> server   < send 123 3 11 2 a3 >        ID (3 hex digits: 11-bit,
                                                     8 hex digits: 29-bit), DLC
                                                     0..8 in hex, one hex token
                                                     per data byte (1-2 digits)
    server -> clients  < frame 123 1700000000.123456 1102A3 >
                                                     ID as received (3 or 8
                                                     digits: the client tells
                                                     standard from extended by
                                                     the digit count), server
                                                     time sec.usec, data hex
    either way         < echo >                      answered with < echo >

Also accepted: ``< bcmmode >`` (back to the state after ``open``; frames are
then not delivered to that client).  Anything else is counted and ignored:
bytes outside ``< >`` (``garbage_bytes``, whitespace excepted), unknown or
invalid commands (``bad_commands``: bad ID, DLC > 8 (no CAN FD), wrong number
of data bytes, ``send`` before ``open``...), a command longer than
:data:`MAX_COMMAND_LEN` bytes.  TCP may split or merge messages anywhere;
a client that disconnects mid-message loses only that message.

Delivery: one write per receiving client per received TCP chunk.  A client
that does not read fills its kernel send buffer (``sndbuf``, 256 KiB) and
then the server's queue for it; beyond ``max_client_buffer`` bytes (4 MiB)
it loses frames (``frames_dropped``), like a CAN controller's receive
overflow, so one stuck client never stalls the bus.  Memory has a total
budget too:

* at most ``max_buffer`` bytes (32 MiB) queued for all clients together;
  past it the client with the most bytes queued (the slowest) is
  disconnected (``clients_dropped``; reset, so the bytes the kernel held
  for it go too), then the next, until the queues fit;
* at most ``max_clients`` connections (256); past it a new one takes the
  place of the slowest client if one has bytes queued (dropped), else of the
  oldest connection that opened no bus in :data:`OPEN_GRACE` seconds (5: an
  idle or hostile client never locks the others out), else it is answered
  ``< error too many clients >`` and closed (``clients_refused``).

A client that reads keeps an empty queue and is never the one dropped: with
200 clients that never read, the server stays within its budget and the
others lose nothing (``tools/bench_can_clients.py``; the process's memory
grows by about 2.5 times the bytes queued plus 20 MB: the allocator's
overhead).  The
python-can client compares its whole first ``recv`` with ``< ok >`` after
``< rawmode >``, so a frame glued to that ``ok`` would make its constructor
fail; frames for a new raw-mode client are therefore held for ``join_grace``
seconds (default 0.02) and then delivered, none lost.

Pitfalls of python-can's socketcand client (4.x), measured here:

* it logs ``Got incomplete message => waiting for more data`` (WARNING) on an
  ordinary TCP split; harmless.
* when the server goes away, its ``recv`` returns None at once, again and
  again (spinning a CPU until the timeout), and ``send`` raises
  ``BrokenPipeError`` (or ``ConnectionResetError``).

The client side is :mod:`slipest.io.bus_args` (``BusConfig("socketcand",
channel, {"host": ..., "port": ...}).open()``, and ``ReconnectingBus``),
which deals with both.

API: :class:`SocketcandServer` (asyncio), :func:`run_server` (blocking; the
``slipest can-server`` command), :class:`ServerThread` /
:func:`start_in_thread` (in a background thread of this process).
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import re
import signal
import socket
import struct
import threading
import time
from typing import Callable, Iterable

__all__ = [
    "DEFAULT_PORT",
    "DEFAULT_CHANNEL",
    "DEFAULT_MAX_BUFFER",
    "DEFAULT_MAX_CLIENTS",
    "MAX_COMMAND_LEN",
    "SocketcandServer",
    "ServerThread",
    "run_server",
    "start_in_thread",
]

log = logging.getLogger(__name__)

#: TCP port the CLI listens on by default (socketcand's own default).
DEFAULT_PORT = 29536
#: Channel name python-can users usually open.
DEFAULT_CHANNEL = "vcan0"
#: Longest ``< ... >`` command accepted [bytes]; longer ones are dropped.
MAX_COMMAND_LEN = 256
_DEFAULT_MAX_CLIENT_BUFFER = 4 * 1024 * 1024  # [bytes]
#: Bytes queued for all clients together, by default (see the module docstring).
DEFAULT_MAX_BUFFER = 32 * 1024 * 1024
#: Connections at once, by default.
DEFAULT_MAX_CLIENTS = 256
#: [s] a connection that opened no bus for this long may be dropped to make room for a new one.
OPEN_GRACE = 5.0
_DEFAULT_JOIN_GRACE = 0.02  # [s]
_DEFAULT_SNDBUF = 256 * 1024  # [bytes]

_CHANNEL_RE = re.compile(rb"[A-Za-z0-9_.:-]{1,15}\Z")
_HEX_RE = re.compile(rb"[0-9A-Fa-f]+\Z")
_WHITESPACE = b" \t\r\n"

_NO_BUS, _BCM, _RAW = "no-bus", "bcm", "raw"


def _loopback_host(host: str) -> str:
    if host == "localhost":
        return "127.0.0.1"
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        raise ValueError(f"host must be a loopback IP address, got {host!r}") from None
    if not address.is_loopback:
        raise ValueError(f"refusing to listen on {host!r}: only loopback addresses (127.0.0.1) are allowed")
    return host


def _reset_on_close(transport) -> None:
    """Make the transport's close a reset (SO_LINGER 0): the kernel sends RST at once and frees the bytes still
    in its send buffer.  A plain close would queue its FIN behind them, and a client that does not read (a zero
    window) would hold that buffer and its connection open until the kernel gives up, minutes later."""
    sock = transport.get_extra_info("socket")
    if sock is None:
        return
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    except OSError as exc:  # already closed: the abort that follows has nothing left to free
        log.debug("SO_LINGER on a dropped client failed: %s", exc)


class _Client(asyncio.Protocol):
    """One TCP connection: parses commands, forwards frames to the server."""

    def __init__(self, server: "SocketcandServer") -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.state = _NO_BUS
        self.channel: str | None = None
        self.peer = "?"
        self._buf = bytearray()
        self._pending: list[tuple[bytes, int]] | None = None  # held frames during join_grace
        self._pending_bytes = 0
        self._join_timer: asyncio.TimerHandle | None = None
        self.accepted = False  # counted among the clients (not refused)
        self.connected_at = time.monotonic()  # host monotonic time of the connection [s]
        self.queued = 0  # bytes queued for it in the server, as last seen [bytes]

    # -- asyncio callbacks -----------------------------------------------------
    def connection_made(self, transport) -> None:
        self.transport = transport
        peer = transport.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if peer else "?"
        if not self.server._connected(self):
            transport.write(b"< error too many clients >")
            transport.close()
            return
        sock = transport.get_extra_info("socket")
        if sock is not None and self.server.sndbuf:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.server.sndbuf)
        transport.write(b"< hi >")

    def data_received(self, data: bytes) -> None:
        if not self.accepted:
            return
        buf = self._buf
        buf += data
        out: list[bytes] = []
        c = self.server.counters
        pos, n = 0, len(buf)
        while pos < n:
            start = buf.find(b"<", pos)
            if start < 0:
                c["garbage_bytes"] += _garbage(buf, pos, n)
                pos = n
                break
            if start > pos:
                c["garbage_bytes"] += _garbage(buf, pos, start)
            end = buf.find(b">", start)
            if end < 0:
                if n - start > MAX_COMMAND_LEN:
                    c["bad_commands"] += 1
                    c["garbage_bytes"] += n - start
                    pos = n
                else:
                    pos = start  # incomplete: wait for the rest
                break
            last = buf.rfind(b"<", start, end)  # "< a < b >": "< a " is garbage
            if last > start:
                c["garbage_bytes"] += _garbage(buf, start, last)
            self._command(bytes(buf[last + 1:end]), out)
            pos = end + 1
        del buf[:pos]
        if out:
            self.server._broadcast(self, b"".join(out), len(out))

    def eof_received(self):
        return False  # close our side too

    def connection_lost(self, exc) -> None:
        if self._join_timer is not None:
            self._join_timer.cancel()
        self._pending = None
        self.server._disconnected(self)
        self.transport = None

    # -- commands --------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(data)

    def _bad(self, why: str, body: bytes) -> None:
        self.server.counters["bad_commands"] += 1
        log.debug("%s: %s: %r", self.peer, why, body[:80])

    def _command(self, body: bytes, out: list) -> None:
        parts = body.split()
        if not parts:
            return self._bad("empty command", body)
        cmd = parts[0]
        if cmd == b"send":
            if self.state == _NO_BUS:
                return self._bad("send before open", body)
            line = _frame_line(parts)
            if line is None:
                return self._bad("invalid send", body)
            out.append(line)
        elif cmd == b"echo" and len(parts) == 1:
            self._write(b"< echo >")
        elif cmd == b"open" and len(parts) == 2 and self.state == _NO_BUS:
            name = parts[1]
            allowed = self.server.channels
            if not _CHANNEL_RE.match(name) or (allowed is not None and name.decode() not in allowed):
                self._bad("cannot open channel", body)
                self._write(b"< error could not open bus >")
                return
            self.channel = name.decode()
            self.state = _BCM
            self._write(b"< ok >")
        elif cmd == b"rawmode" and len(parts) == 1 and self.state == _BCM:
            self.state = _RAW
            self._write(b"< ok >")
            self.server._join(self)
        elif cmd == b"bcmmode" and len(parts) == 1 and self.state == _RAW:
            self.server._leave(self)
            self.state = _BCM
            self._write(b"< ok >")
        else:
            self._bad("unknown or unexpected command", body)

    # -- delivery --------------------------------------------------------------
    def _start_grace(self, grace: float) -> None:
        if grace > 0:
            self._pending = []
            self._join_timer = asyncio.get_running_loop().call_later(grace, self._end_grace)

    def _end_grace(self) -> None:
        self._join_timer = None
        pending, self._pending, self._pending_bytes = self._pending, None, 0
        if pending:
            self._write(b"".join(p for p, _ in pending))
        self._requeue()

    def _requeue(self) -> None:
        """Tell the server how many bytes wait for this client now (its queue and held frames)."""
        t = self.transport
        size = self._pending_bytes + (t.get_write_buffer_size() if t is not None and not t.is_closing() else 0)
        self.server._queued(self, size)

    def deliver(self, data: bytes, n_frames: int) -> bool:
        """Queue frames for this client; False when dropped (client too slow)."""
        limit = self.server.max_client_buffer
        if self._pending is not None:
            if self._pending_bytes + len(data) > limit:
                return False
            self._pending.append((data, n_frames))
            self._pending_bytes += len(data)
            self._requeue()
            return True
        t = self.transport
        if t is None or t.is_closing() or t.get_write_buffer_size() + len(data) > limit:
            return False
        t.write(data)  # sent at once when the kernel takes it: nothing stays queued for a client that reads
        self._requeue()
        return True


def _garbage(buf: bytearray, a: int, b: int) -> int:
    """Number of non-whitespace bytes in buf[a:b]."""
    return len(bytes(buf[a:b]).translate(None, _WHITESPACE))


def _frame_line(parts: list[bytes]) -> bytes | None:
    """``send ID LEN b..`` tokens -> ``< frame ... >`` line, or None if invalid."""
    if len(parts) < 3:
        return None
    id_s, len_s, data_s = parts[1], parts[2], parts[3:]
    if not _HEX_RE.match(id_s) or not _HEX_RE.match(len_s) or len(len_s) > 2:
        return None
    can_id, dlc = int(id_s, 16), int(len_s, 16)
    if len(id_s) <= 3 and can_id <= 0x7FF:
        id_out = b"%03X" % can_id
    elif len(id_s) == 8 and can_id <= 0x1FFFFFFF:
        id_out = b"%08X" % can_id
    else:
        return None
    if dlc > 8 or len(data_s) != dlc:
        return None
    for tok in data_s:
        if len(tok) > 2 or not _HEX_RE.match(tok):
            return None
    data = bytes(int(tok, 16) for tok in data_s)
    now = time.time()
    sec = int(now)
    return b"< frame %s %d.%06d %s >" % (id_out, sec, int((now - sec) * 1e6), data.hex().upper().encode())


class SocketcandServer:
    """The shared-bus server (asyncio).  Use :meth:`start` / :meth:`close` in
    a running event loop, or :func:`run_server` / :func:`start_in_thread`.

    :param channels: channel names clients may open (None: any valid name).
    :param join_grace: [s] frames for a client that just entered raw mode are
        held this long (see the module docstring).
    :param max_client_buffer: [bytes] data per client queued in the server
        above which frames for that client are dropped and counted.
    :param sndbuf: [bytes] kernel send buffer (``SO_SNDBUF``) of each client
        socket, so that a stuck client holds at most about ``sndbuf +
        max_client_buffer`` bytes (Linux otherwise lets it grow to ~4 MB);
        None leaves the kernel's autotuning.
    :param max_clients: connections at once; more are refused.
    :param max_buffer: [bytes] data queued in the server for all clients
        together, above which the slowest clients are disconnected.
    """

    def __init__(self, *, channels: Iterable[str] | None = None, join_grace: float = _DEFAULT_JOIN_GRACE,
                 max_client_buffer: int = _DEFAULT_MAX_CLIENT_BUFFER,
                 sndbuf: int | None = _DEFAULT_SNDBUF, max_clients: int = DEFAULT_MAX_CLIENTS,
                 max_buffer: int = DEFAULT_MAX_BUFFER) -> None:
        if int(max_clients) < 1 or int(max_buffer) < 1 or int(max_client_buffer) < 1:
            raise ValueError(f"max_clients={max_clients}, max_buffer={max_buffer} and "
                             f"max_client_buffer={max_client_buffer} must be positive")
        self.channels = None if channels is None else frozenset(channels)
        self.join_grace = float(join_grace)
        self.max_client_buffer = int(max_client_buffer)
        self.sndbuf = None if sndbuf is None else int(sndbuf)
        self.max_clients = int(max_clients)
        self.max_buffer = int(max_buffer)
        self.counters = {
            "clients": 0, "clients_total": 0, "frames_in": 0, "frames_out": 0,
            "frames_dropped": 0, "bad_commands": 0, "garbage_bytes": 0,
            "clients_refused": 0, "clients_dropped": 0, "bytes_queued": 0, "bytes_queued_peak": 0,
        }
        self._clients: set[_Client] = set()
        self._raw: dict[str, set[_Client]] = {}
        self._server: asyncio.base_events.Server | None = None
        self.address: tuple[str, int] | None = None

    async def start(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> tuple[str, int]:
        """Listen on ``host:port`` (loopback only; port 0 picks a free port).

        :returns: the (host, port) actually listened on.
        :raises ValueError: non-loopback host.  :raises OSError: port in use.
        """
        host = _loopback_host(host)
        self._server = await asyncio.get_running_loop().create_server(
            lambda: _Client(self), host, port, reuse_address=True)
        sockname = self._server.sockets[0].getsockname()
        self.address = (sockname[0], sockname[1])
        return self.address

    async def close(self) -> None:
        """Stop listening and disconnect every client."""
        if self._server is not None:
            self._server.close()
        for client in list(self._clients):
            if client.transport is not None:
                client.transport.abort()
        if self._server is not None:
            await self._server.wait_closed()
            self._server = None
        await asyncio.sleep(0)  # let connection_lost callbacks run

    def stats(self) -> dict:
        """Counters plus ``raw_clients`` per channel (call in the loop's thread)."""
        snap = dict(self.counters)
        snap["raw_clients"] = {ch: len(cl) for ch, cl in self._raw.items() if cl}
        return snap

    # -- called by _Client -----------------------------------------------------
    def _connected(self, client: _Client) -> bool:
        """Count a new connection; False when it is one too many (refused).  At the limit it takes the
        place of the slowest client if one has bytes queued (that one is dropped)."""
        if len(self._clients) >= self.max_clients:
            slowest = max(self._clients, key=lambda cl: cl.queued, default=None)
            if slowest is None or slowest.queued == 0:
                # else the oldest connection that never opened a bus within OPEN_GRACE (an idle or hostile
                # client must not lock the others out)
                now = time.monotonic()
                idle = [cl for cl in self._clients if cl.state == _NO_BUS and now - cl.connected_at > OPEN_GRACE]
                if not idle:
                    self.counters["clients_refused"] += 1
                    log.info("client %s refused: %d clients already", client.peer, len(self._clients))
                    return False
                slowest = min(idle, key=lambda cl: cl.connected_at)
            self._drop(slowest, f"to make room for {client.peer} ({self.max_clients} clients at most)")
        client.accepted = True
        self._clients.add(client)
        self.counters["clients"] += 1
        self.counters["clients_total"] += 1
        log.info("client %s connected", client.peer)
        return True

    def _disconnected(self, client: _Client) -> None:
        self._forget(client)
        log.info("client %s disconnected", client.peer)

    def _forget(self, client: _Client) -> None:
        self._leave(client)
        self._queued(client, 0)
        if client in self._clients:
            self._clients.discard(client)
            self.counters["clients"] -= 1

    def _drop(self, client: _Client, why: str) -> None:
        """Disconnect a slow client now (its queue goes with the connection), counted."""
        log.info("client %s dropped with %d bytes queued: %s", client.peer, client.queued, why)
        self.counters["clients_dropped"] += 1
        self._forget(client)
        if client.transport is not None:
            _reset_on_close(client.transport)
            client.transport.abort()

    def _queued(self, client: _Client, size: int) -> None:
        c = self.counters
        c["bytes_queued"] += size - client.queued
        client.queued = size
        if c["bytes_queued"] > c["bytes_queued_peak"]:
            c["bytes_queued_peak"] = c["bytes_queued"]

    def _shed(self) -> None:
        """Disconnect the clients with the most bytes queued until the queues fit ``max_buffer``."""
        c = self.counters
        while c["bytes_queued"] > self.max_buffer:
            slowest = max(self._clients, key=lambda cl: cl.queued, default=None)
            if slowest is None or slowest.queued == 0:
                return
            self._drop(slowest, f"over the budget of {self.max_buffer} bytes queued for all clients")

    def _join(self, client: _Client) -> None:
        client._start_grace(self.join_grace)
        self._raw.setdefault(client.channel, set()).add(client)

    def _leave(self, client: _Client) -> None:
        members = self._raw.get(client.channel)
        if members is not None:
            members.discard(client)

    def _broadcast(self, sender: _Client, data: bytes, n_frames: int) -> None:
        c = self.counters
        c["frames_in"] += n_frames
        members = self._raw.get(sender.channel, ())
        for peer in list(members):
            if peer is sender or peer not in members:  # (dropped for the budget meanwhile)
                continue
            if peer.deliver(data, n_frames):
                c["frames_out"] += n_frames
            else:
                c["frames_dropped"] += n_frames
            if c["bytes_queued"] > self.max_buffer:  # over by one delivery at most
                self._shed()


async def _serve(host: str, port: int, stop: asyncio.Event, on_ready: Callable | None, server: SocketcandServer):
    address = await server.start(host, port)
    if on_ready is not None:
        on_ready(*address)
    try:
        await stop.wait()
    finally:
        await server.close()
    return server.stats()


def run_server(host: str = "127.0.0.1", port: int = DEFAULT_PORT, *,
               on_ready: Callable[[str, int], None] | None = None, **server_kwargs) -> dict:
    """Run the server in this thread until SIGINT/SIGTERM (or KeyboardInterrupt).

    :param on_ready: called with (host, port) once listening.
    :param server_kwargs: passed to :class:`SocketcandServer`.
    :returns: the final :meth:`SocketcandServer.stats`.
    """
    server = SocketcandServer(**server_kwargs)

    plain: dict = {}  # signal -> previous handler, where the loop cannot take signals itself

    async def _main():
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                try:
                    loop.add_signal_handler(sig, stop.set)
                except NotImplementedError:  # Windows' event loops: a plain handler that wakes the loop
                    plain[sig] = signal.signal(sig, lambda signum, frame: loop.call_soon_threadsafe(stop.set))
        return await _serve(host, port, stop, on_ready, server)

    try:
        return asyncio.run(_main())
    except KeyboardInterrupt:
        return server.stats()
    finally:
        for sig, handler in plain.items():
            signal.signal(sig, handler)


class ServerThread:
    """A :class:`SocketcandServer` running in a background thread.

    Calling the object (or :meth:`stop`) stops the server; it is also a
    context manager.  ``host`` / ``port`` are where it listens.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, **server_kwargs) -> None:
        self.server = SocketcandServer(**server_kwargs)
        self._host, self._port = _loopback_host(host), port
        self.host: str | None = None
        self.port: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="socketcand-server", daemon=True)

    def start(self, timeout: float = 5.0) -> "ServerThread":
        self._thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError("socketcand server thread did not start")
        if self._error is not None:
            raise self._error
        return self

    def _run(self) -> None:
        async def _main():
            self._loop = asyncio.get_running_loop()
            self._stop_event = asyncio.Event()

            def ready(host, port):
                self.host, self.port = host, port
                self._ready.set()

            await _serve(self._host, self._port, self._stop_event, ready, self.server)

        try:
            asyncio.run(_main())
        except BaseException as exc:  # reported to start()
            self._error = exc
            self._ready.set()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the server and wait for the thread (idempotent)."""
        if self._loop is not None and self._thread.is_alive():
            try:
                self._loop.call_soon_threadsafe(self._stop_event.set)
            except RuntimeError:  # loop already closed
                pass
        if self._thread.ident is not None:  # started
            self._thread.join(timeout)

    __call__ = stop

    def stats(self, timeout: float = 5.0) -> dict:
        """Snapshot of the server's :meth:`SocketcandServer.stats` (also after stop)."""
        if not self._thread.is_alive():
            return self.server.stats()

        async def _get():
            return self.server.stats()
        return asyncio.run_coroutine_threadsafe(_get(), self._loop).result(timeout)

    def wait_for_clients(self, n: int, channel: str = DEFAULT_CHANNEL, timeout: float = 10.0) -> bool:
        """Wait until at least ``n`` clients are in raw mode on ``channel``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.stats()["raw_clients"].get(channel, 0) >= n:
                return True
            time.sleep(0.01)
        return False

    def __enter__(self) -> "ServerThread":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def start_in_thread(port: int = 0, host: str = "127.0.0.1", **server_kwargs) -> tuple[str, int, ServerThread]:
    """Start a server in a daemon thread: returns ``(host, port, stop)``.

    ``stop()`` stops it; ``stop`` is the :class:`ServerThread`, so
    ``stop.stats()`` and ``stop.wait_for_clients(n)`` are there too.
    """
    thread = ServerThread(host, port, **server_kwargs).start()
    return thread.host, thread.port, thread
