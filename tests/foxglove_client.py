"""A Foxglove WebSocket client for the tests and benchmarks of the live view (websockets + protobuf).

It speaks the Foxglove WebSocket protocol as the Foxglove app does: it offers the subprotocols
``foxglove.websocket.v1`` and ``foxglove.sdk.v1`` (the name foxglove-sdk's server accepts), reads
the server's ``serverInfo`` and ``advertise`` messages, subscribes to every channel advertised
(as it is advertised; again when the server answers ``Unknown channel ID``: foxglove-sdk 0.30
can advertise a channel a moment before it accepts subscriptions to it), and keeps each Message Data frame (opcode 1: subscription id, log time
[ns], payload) with its topic.  :func:`decode` turns a payload into a dict (JSON channels) or a
protobuf message built from the schema the server advertised (a FileDescriptorSet).

It runs its asyncio loop in a thread of its own, so a synchronous test drives it.  ``stall``: once
subscribed to a topic containing ``stall``, it stops reading (a viewer that hangs) until
:meth:`resume`; ``rcvbuf`` [bytes] shrinks its socket's receive buffer so a stall is felt soon.
"""

from __future__ import annotations

import asyncio
import base64
import json
import re
import socket
import struct
import threading

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")


class FoxgloveClient:
    """Connects to ``ws://127.0.0.1:port`` in a thread (see the module docstring)."""

    def __init__(self, port: int, *, stall: str | None = None, rcvbuf: int | None = None):
        self.port = port
        self.stall = stall
        self.rcvbuf = rcvbuf
        self.channels: dict[int, dict] = {}
        self.subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self.messages: list[tuple[str, int, bytes]] = []  # (topic, log time [ns], payload)
        self.server_info: dict | None = None
        self.statuses: list[dict] = []
        self.resubscribed = 0
        self.subprotocol: str | None = None
        self.closed_by_server = False
        self.error: BaseException | None = None
        self.ready = threading.Event()
        self.stalled = threading.Event()
        self._resume = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)
        self._thread.start()

    def topics(self) -> set[str]:
        return {ch["topic"] for ch in self.channels.values()}

    def of(self, topic: str) -> list[tuple[int, bytes]]:
        """(log time, payload) of the messages received on ``topic``, in order."""
        return [(ts, data) for t, ts, data in self.messages if t == topic]

    def channel(self, topic: str) -> dict:
        return next(ch for ch in self.channels.values() if ch["topic"] == topic)

    def resume(self) -> None:
        self._resume.set()

    def close(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._thread.join(timeout)
        if self.error is not None:
            raise self.error

    def _stalling(self) -> bool:
        if self.stall is None or self._resume.is_set():
            return False
        if any(self.stall in self.channels[c]["topic"] for c in self.subscriptions.values()):
            self.stalled.set()
            return True
        return False

    async def _main(self) -> None:
        import websockets

        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            if self.rcvbuf:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.rcvbuf)
            sock.connect(("127.0.0.1", self.port))
            async with websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=list(SUBPROTOCOLS), sock=sock,
                                          max_size=None, max_queue=1 if self.stall else 16, ping_interval=None,
                                          proxy=None, compression=None) as ws:
                self.subprotocol = ws.subprotocol
                while not self._stop.is_set():
                    if self._stalling():
                        await asyncio.sleep(0.05)
                        continue
                    try:
                        msg = await asyncio.wait_for(ws.recv(), 0.05)
                        await self._handle(ws, msg)
                    except asyncio.TimeoutError:
                        continue
                    except websockets.ConnectionClosed:  # (also while subscribing: the server stopped)
                        self.closed_by_server = True
                        return
        except BaseException as exc:  # raised again by close()
            self.error = exc
            self.ready.set()

    async def _subscribe(self, ws, channel_ids) -> None:
        subs = []
        for channel_id in channel_ids:
            sub = len(self.subscriptions)
            self.subscriptions[sub] = channel_id
            subs.append({"id": sub, "channelId": channel_id})
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    async def _handle(self, ws, msg) -> None:
        if isinstance(msg, str):
            m = json.loads(msg)
            if m["op"] == "serverInfo":
                self.server_info = m
                self.ready.set()
            elif m["op"] == "advertise":
                for ch in m["channels"]:
                    self.channels[ch["id"]] = ch
                await self._subscribe(ws, [ch["id"] for ch in m["channels"]])
            else:
                self.statuses.append(m)
                unknown = re.fullmatch(r"Unknown channel ID: (\d+)", str(m.get("message", "")))
                if unknown and int(unknown.group(1)) in self.channels:
                    # foxglove-sdk 0.30 may advertise a new channel a moment before it takes subscriptions
                    # to it: subscribe again, as a viewer opening the topic a moment later would
                    self.resubscribed += 1
                    await asyncio.sleep(0.02)
                    await self._subscribe(ws, [int(unknown.group(1))])
            return
        if msg[0] == 1:  # Message Data: opcode, uint32 subscription id, uint64 log time, payload
            sub, log_time = struct.unpack_from("<IQ", msg, 1)
            self.messages.append((self.channels[self.subscriptions[sub]]["topic"], log_time, bytes(msg[13:])))


_PROTO_CLASSES: dict = {}


def decode(channel: dict, payload: bytes):
    """A message of ``channel`` (as advertised): a dict for JSON, a protobuf message for protobuf."""
    if channel["encoding"] == "json":
        return json.loads(payload)
    assert channel["encoding"] == "protobuf", channel
    key = (channel["schemaName"], channel["schema"])
    cls = _PROTO_CLASSES.get(key)
    if cls is None:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        pending = list(fds.file)
        while pending:  # dependencies first, whatever their order in the set
            left = []
            for f in pending:
                try:
                    pool.Add(f)
                except TypeError:
                    left.append(f)
            if len(left) == len(pending):
                raise ValueError(f"cannot build {channel['schemaName']} from its schema")
            pending = left
        cls = _PROTO_CLASSES[key] = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
    return cls.FromString(payload)
