"""CAN link of the virtual device: any python-can bus.

The bus is described as on every slipest command line (interface, channel,
``--bus-option k=v``: :mod:`slipest.io.bus_args`): SocketCAN's ``vcan0``
where the kernel has it, ``virtual`` within one process, ``socketcand``
(``slipest can-server``) across processes, ``slcan`` on a serial adapter...
Messages are those of the DBC (:mod:`slipest.io.can_messages`): one
ImuSample per sample, one SlipReference per leg cycle with
``--send-reference``; the wheel index is in the ID and the Wheel signal.

The link keeps its bus alive with :class:`~slipest.io.bus_args.ReconnectingBus`
(a dead socketcand server is reconnected when it is back) and drains what
others send on the bus (the estimator's estimates) in a thread, so that a
TCP-based bus never backs up.  A planned disconnection shuts the bus down
and opens it again after the outage.
"""

from __future__ import annotations

import threading
from typing import Callable

import can
import numpy as np

from firmware_sim.link import Link, LinkDown
from slipest.io.bus_args import BusConfig, ReconnectingBus
from slipest.io.can_messages import base_id, encode_imu, encode_slip_reference, load_tables

#: 11-bit IDs the DBC uses (0x110-0x135); unknown-ID bursts avoid them.
_OUR_IDS = range(0x110, 0x136)


def unknown_messages(n: int, rng: np.random.Generator) -> list[can.Message]:
    """``n`` standard-ID messages whose IDs are not in the DBC."""
    out = []
    while len(out) < n:
        arb = int(rng.integers(0, 0x800))
        if arb in _OUR_IDS:
            continue
        size = int(rng.integers(0, 9))
        out.append(can.Message(arbitration_id=arb, is_extended_id=False,
                               data=rng.integers(0, 256, size, dtype=np.uint8).tobytes()))
    return out


class CanLink(Link):
    """The device's side of a CAN bus (see the module docstring); items are ``can.Message`` s.

    ``wait``: seconds :meth:`open` waits for the bus; ``drain``: read and count
    what others send, in a thread."""

    corrupts = False  # the bus's own CRC protects frames; corruption is a serial fault

    def __init__(self, config: BusConfig, announce: Callable[[str], None] | None = None, wait: float = 10.0,
                 drain: bool = True):
        super().__init__(announce)
        self.config = config
        self.wait = wait
        self.drain = drain
        self.bus = ReconnectingBus(config, on_event=self.announce)
        load_tables()  # not on the first frame's pacing
        self.received = 0  # messages others sent (drained)
        self._down = False
        self._stop = threading.Event()
        self._drainer: threading.Thread | None = None
        self._recv_lock = threading.Lock()  # a planned disconnection waits for the drainer to leave recv

    @property
    def name(self) -> str:
        return self.config.describe()

    def open(self) -> None:
        if not self.bus.open(wait=self.wait):
            raise OSError(self.bus.last_error or f"cannot open CAN bus {self.config.describe()}")
        self.announce(f"CAN bus {self.config.describe()}")
        if self.drain and self._drainer is None:
            self._drainer = threading.Thread(target=self._drain, name="firmware-sim-can-drain", daemon=True)
            self._drainer.start()

    def _drain(self) -> None:
        while not self._stop.is_set():
            with self._recv_lock:
                got = None if self._down else self.bus.recv(0.05)
            if got is not None:
                self.received += 1
            elif self._down:
                self._stop.wait(0.05)

    def ready(self) -> bool:
        return not self._down and self.bus.open()

    def encode_imu(self, wheel: int, seq: int, t_us: int, az: float, theta: float) -> can.Message:
        return encode_imu(wheel, seq, az, theta, t_us * 1e-6)

    def encode_reference(self, wheel: int, seq: int, t_us: int, slip: float) -> can.Message:
        return encode_slip_reference(wheel, seq, slip, t_us * 1e-6)

    def send(self, items) -> int:
        for msg in items:
            if not self.bus.send(msg):
                raise LinkDown(self.bus.last_error or "send failed")
        return 0

    def send_unknown(self, n: int, rng: np.random.Generator) -> int:
        sent = 0
        for msg in unknown_messages(n, rng):
            if self.bus.send(msg):
                sent += 1
        return sent

    def disconnect(self) -> None:
        """Drop the bus (planned outage)."""
        with self._recv_lock:
            self._down = True
            old = self.bus
            self.bus = ReconnectingBus(self.config, on_event=self.announce)
        old.shutdown()

    def reconnect(self) -> None:
        self._down = False
        self.bus.open()

    def close(self) -> None:
        self._stop.set()
        if self._drainer is not None:
            self._drainer.join(timeout=1.0)
            self._drainer = None
        self.bus.shutdown()

    def describe(self) -> dict:
        return {"type": "can", "bus": self.config.describe(), "imu_base_id": base_id("ImuSample"),
                "received_from_others": self.received, **self.bus.counters()}
