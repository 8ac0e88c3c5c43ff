"""The seam between the virtual device and its links: :class:`Link`, :class:`LinkDown`, frame tables.

The device (:class:`firmware_sim.device.Device`) hands each burst of due
frames to a :class:`Link` as rows of a *frame table*: a numpy structured
array of dtype :data:`FRAME_TABLE_DTYPE`, one row per frame, in send order.
A link turns rows into wire items (:meth:`Link.encode`) and sends them.
Implementations: :class:`firmware_sim.serial_link.PtyLink`,
:class:`firmware_sim.serial_link.PortLink` (serial frames of
:mod:`slipest.io.serial_frames`) and :class:`firmware_sim.can_link.CanLink`
(the DBC's CAN messages).
"""

from __future__ import annotations

import abc
from typing import Callable

import numpy as np

from slipest.io.serial_frames import FRAME_IMU_SAMPLE, FRAME_SLIP_REFERENCE

#: Frame kind of a table row: an IMU sample, or a reference slip (the serial frame type bytes).
KIND_IMU = FRAME_IMU_SAMPLE
KIND_REF = FRAME_SLIP_REFERENCE

#: One frame per row.  ``kind`` :data:`KIND_IMU` or :data:`KIND_REF`; ``wheel``
#: 0..5; ``seq`` the per-(kind, wheel) counter before a link reduces it (mod
#: 2**16 on serial, 2**8 on CAN); ``t`` scenario time [s]; ``az`` [m/s^2] and
#: ``theta`` [rad, wrapped to [-pi, pi)] are NaN in reference rows; ``slip``
#: [-] the true slip of the row's leg cycle (in every row); ``cycle`` that
#: leg cycle's index.
FRAME_TABLE_DTYPE = np.dtype([
    ("kind", "u1"),
    ("wheel", "u1"),
    ("seq", "i8"),
    ("t", "f8"),
    ("az", "f8"),
    ("theta", "f8"),
    ("slip", "f8"),
    ("cycle", "i8"),
])


class LinkDown(Exception):
    """A link could not send: the peer or the medium went away."""


class Link(abc.ABC):
    """The device's side of one link (a pseudo-terminal, a serial port, a CAN bus).

    The device calls a link from one thread: :meth:`open` once, then for each
    burst :meth:`ready`, :meth:`encode` and :meth:`send`; :meth:`disconnect`
    and later :meth:`reconnect` for a planned outage; :meth:`send_unknown`
    for an unknown-message fault; :meth:`close` at the end.  After
    :meth:`send` raised :class:`LinkDown`, or while :meth:`ready` says False,
    the link recovers by itself: the device asks :meth:`ready` again before
    the next burst.

    Wire items are what :meth:`encode_imu` and :meth:`encode_reference`
    return (``bytes`` for serial frames, ``can.Message`` for CAN).
    """

    #: Whether wire items are ``bytes`` that the device's byte faults may corrupt.
    corrupts: bool = False

    def __init__(self, announce: Callable[[str], None] | None = None):
        #: ``announce(text)``: where the link reports events (where to connect, reconnections).
        self.announce = announce or (lambda text: None)

    @property
    @abc.abstractmethod
    def name(self) -> str:
        """Where a peer connects (a path, a port, a bus description), for messages."""

    @abc.abstractmethod
    def open(self) -> None:
        """Create or open the link; may announce where to connect.

        :raises OSError: the link cannot be opened.
        """

    @abc.abstractmethod
    def ready(self) -> bool:
        """Whether a peer is there and frames can be sent now; never raises, never blocks for long."""

    @abc.abstractmethod
    def encode_imu(self, wheel: int, seq: int, t_us: int, az: float, theta: float):
        """One IMU sample as a wire item: ``wheel`` 0..5, ``seq`` counter (reduced by the
        link), ``t_us`` device time [us], ``az`` [m/s^2], ``theta`` [rad]."""

    @abc.abstractmethod
    def encode_reference(self, wheel: int, seq: int, t_us: int, slip: float):
        """One reference slip [-] as a wire item (arguments as :meth:`encode_imu`)."""

    @abc.abstractmethod
    def send(self, items: list) -> int:
        """Send wire items, in order; return the bytes written (0 where the medium counts no bytes).

        :raises LinkDown: the peer or the medium went away (items may be lost).
        """

    @abc.abstractmethod
    def send_unknown(self, n: int, rng: np.random.Generator) -> int:
        """Send a burst of ``n`` messages the receiver does not know; return how many went out.

        :raises LinkDown: as :meth:`send`.
        """

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Planned outage: the link goes down (:meth:`ready` False) until :meth:`reconnect`.

        Items already sent are delivered as far as the medium allows (a
        pseudo-terminal first lets its reader drain them)."""

    @abc.abstractmethod
    def reconnect(self) -> None:
        """End a planned outage: open again; :meth:`ready` says when a peer is back."""

    @abc.abstractmethod
    def close(self) -> None:
        """End of the run: the link goes, items already sent delivered as in :meth:`disconnect`;
        a second call does nothing."""

    def describe(self) -> dict:
        """JSON-ready facts about the link for the device's report (at least ``type``)."""
        return {"type": type(self).__name__}

    def encode(self, table: np.ndarray, t_us: np.ndarray, idx) -> list:
        """One wire item per row ``idx`` of a frame table, in that order; ``t_us`` [us] per table row."""
        rows = table[idx]
        columns = (rows["kind"].tolist(), rows["wheel"].tolist(), rows["seq"].tolist(), t_us[idx].tolist(),
                   rows["az"].tolist(), rows["theta"].tolist(), rows["slip"].tolist())
        imu, ref = self.encode_imu, self.encode_reference
        return [imu(w, s, tu, az, th) if k == KIND_IMU else ref(w, s, tu, sl)
                for k, w, s, tu, az, th, sl in zip(*columns)]
