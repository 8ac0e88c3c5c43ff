"""Faults the virtual device injects on demand, and the tally of what it injected.

A :class:`FaultPlan` is pure data, parsed from the command line:

* rates, drawn independently for every frame or byte:
  ``corrupt_rate`` (probability that a byte on the serial wire is corrupted:
  XORed with a random non-zero byte; the frame's delimiter included) and
  ``drop_rate`` (probability that a frame is not sent);
* scheduled faults ``KIND@T[:k=v,...]``, ``T`` in seconds of scenario time
  (the device's clock, whatever ``--speed``):

  ==============================  ==================================================
  ``drop@T:n=N,wheel=W``          N consecutive frames of wheel W (default 0;
                                  ``wheel=all``: of any wheel) are not sent
  ``corrupt@T:n=N,wheel=W``       one byte of each of N consecutive frames is
                                  corrupted (serial)
  ``stuck@T:n=N,wheel=W``         the sensor is stuck: az frozen at one value
                                  for N samples of wheel W
  ``disconnect@T:down=S``         the link goes down for S seconds of scenario time
                                  and until the peer is back (serial: the pty master
                                  is closed and a new one created, or the port is
                                  closed and reopened; CAN: the bus is shut down and
                                  reconnected)
  ``unknown-ids@T:n=N``           a burst of N messages the receiver does not know
                                  (CAN: IDs not in the DBC; serial: CRC-valid frames
                                  of an unknown type)
  ==============================  ==================================================

:class:`FaultInjector` applies a plan to the device's frames and keeps the
counts (:class:`FaultTally`) that the device's report carries, so that a
receiver's counters can be reconciled with what was injected.  Pure
computation: no ports, no clocks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Kinds of scheduled fault and their parameters (name -> default).
SCHEDULED_KINDS: dict[str, dict[str, object]] = {
    "drop": {"n": 1, "wheel": 0},
    "corrupt": {"n": 1, "wheel": 0},
    "stuck": {"n": 200, "wheel": 0},
    "disconnect": {"down": 0.5},
    "unknown-ids": {"n": 20},
}


@dataclass(frozen=True)
class ScheduledFault:
    """One fault at scenario time ``at`` [s]; ``params`` as in :data:`SCHEDULED_KINDS`
    (``wheel`` is an int, or ``None`` for any wheel)."""

    kind: str
    at: float
    params: dict

    def describe(self) -> str:
        opts = ",".join(f"{k}={'all' if v is None else v}" for k, v in self.params.items())
        return f"{self.kind}@{self.at:g}" + (f":{opts}" if opts else "")


def parse_fault(text: str) -> ScheduledFault:
    """Parse ``KIND@T[:k=v,...]`` (see the module docstring); ValueError naming the problem."""
    spec, _, opts = text.strip().partition(":")
    kind, at_sign, at_text = spec.partition("@")
    kind = kind.strip().replace("_", "-")
    if kind not in SCHEDULED_KINDS:
        raise ValueError(f"unknown fault {kind!r} in {text!r}; known: {', '.join(SCHEDULED_KINDS)}")
    if not at_sign:
        raise ValueError(f"fault {text!r}: expected {kind}@T (T: scenario time [s])")
    try:
        at = float(at_text)
    except ValueError:
        raise ValueError(f"fault {text!r}: time {at_text!r} is not a number") from None
    if not np.isfinite(at) or at < 0:
        raise ValueError(f"fault {text!r}: time must be a number >= 0 [s]")
    params = dict(SCHEDULED_KINDS[kind])
    for item in filter(None, (s.strip() for s in opts.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or key not in params:
            raise ValueError(f"fault {text!r}: expected k=v with k in {', '.join(params)}, got {item!r}")
        value = value.strip()
        try:
            if key == "wheel":
                params[key] = None if value == "all" else int(value)
                if params[key] is not None and params[key] < 0:
                    raise ValueError
            elif key == "n":
                params[key] = int(value)
                if params[key] < 1:
                    raise ValueError
            else:
                params[key] = float(value)
                if not params[key] >= 0:
                    raise ValueError
        except ValueError:
            raise ValueError(f"fault {text!r}: bad value {value!r} for {key}") from None
    if kind == "stuck" and params["wheel"] is None:
        raise ValueError(f"fault {text!r}: a stuck sensor belongs to one wheel (wheel=N)")
    return ScheduledFault(kind, at, params)


@dataclass(frozen=True)
class FaultPlan:
    """Everything the device is asked to inject (pure data)."""

    corrupt_rate: float = 0.0
    drop_rate: float = 0.0
    scheduled: tuple[ScheduledFault, ...] = ()
    seed: int | None = None

    def __post_init__(self):
        for name in ("corrupt_rate", "drop_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name}={value} must be a probability in [0, 1]")

    @property
    def empty(self) -> bool:
        return not (self.corrupt_rate or self.drop_rate or self.scheduled)

    def of_kind(self, *kinds: str) -> list[ScheduledFault]:
        return sorted((f for f in self.scheduled if f.kind in kinds), key=lambda f: f.at)

    def describe(self) -> list[str]:
        out = []
        if self.corrupt_rate:
            out.append(f"corrupt-rate={self.corrupt_rate:g}")
        if self.drop_rate:
            out.append(f"drop-rate={self.drop_rate:g}")
        out += [f.describe() for f in self.scheduled]
        return out


_BY_WHEEL = {
    "frames_dropped": "dropped_by_wheel",
    "frames_corrupted": "corrupted_by_wheel",
    "frames_lost_disconnected": "lost_disconnected_by_wheel",
}


@dataclass
class FaultTally:
    """What was injected (counts); ``*_by_wheel`` lists are indexed by wheel.

    Frame counts cover IMU and reference frames alike."""

    n_wheels: int
    frames_dropped: int = 0  #: frames not sent (drop rate and drop@)
    frames_corrupted: int = 0  #: frames lost to corruption: a corrupted byte, or a corrupted delimiter before them
    bytes_corrupted: int = 0
    stuck_samples: int = 0
    stuck_runs: int = 0
    disconnects: int = 0
    reconnects: int = 0
    frames_lost_disconnected: int = 0  #: frames due while the link was down (not sent)
    unknown_sent: int = 0  #: messages/frames of unknown ID/type sent
    dropped_by_wheel: list = field(default_factory=list)
    corrupted_by_wheel: list = field(default_factory=list)
    lost_disconnected_by_wheel: list = field(default_factory=list)

    def __post_init__(self):
        for name in _BY_WHEEL.values():
            if not getattr(self, name):
                setattr(self, name, [0] * self.n_wheels)

    def count_lost(self, name: str, wheels: np.ndarray) -> None:
        """Add frames (one ``wheels`` entry per frame) to counter ``name`` and its per-wheel list."""
        wheels = np.asarray(wheels)
        if not wheels.size:
            return
        setattr(self, name, getattr(self, name) + int(wheels.size))
        per = np.bincount(wheels.astype(np.int64), minlength=self.n_wheels)
        acc = getattr(self, _BY_WHEEL[name])
        for w in range(self.n_wheels):
            acc[w] += int(per[w])

    @property
    def frames_lost(self) -> int:
        """Frames the receiver cannot get: dropped, corrupted or due while disconnected."""
        return self.frames_dropped + self.frames_corrupted + self.frames_lost_disconnected

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["frames_lost"] = self.frames_lost
        return d


class FaultInjector:
    """Applies a :class:`FaultPlan` to the device's frames, chunk after chunk.

    Data faults (``stuck``) change the samples before they are encoded;
    frame faults (drops, ``corrupt@``) choose frames; byte faults change the
    encoded bytes (:meth:`corrupt_bytes`); link faults (disconnect, unknown
    IDs) are handed to the device as they fall due (:meth:`link_faults_due`).
    """

    def __init__(self, plan: FaultPlan, n_wheels: int):
        self.plan = plan
        self.n_wheels = n_wheels
        self.rng = np.random.default_rng(plan.seed)
        self.tally = FaultTally(n_wheels)
        self._pending_frame = [[f, f.params["n"]] for f in plan.of_kind("drop", "corrupt")]
        self._pending_stuck = [[f, f.params["n"], None] for f in plan.of_kind("stuck")]
        self._link = plan.of_kind("disconnect", "unknown-ids")
        self._delimiter_carry = False

    # -- data faults --------------------------------------------------------
    def apply_stuck(self, t: np.ndarray, wheel: np.ndarray, az: np.ndarray, is_imu: np.ndarray) -> None:
        """Freeze ``az`` (in place) of the IMU samples under a ``stuck`` fault."""
        for entry in self._pending_stuck:
            fault, left, value = entry
            if left <= 0:
                continue
            sel = np.flatnonzero(is_imu & (t >= fault.at) & (wheel == fault.params["wheel"]))[:left]
            if not sel.size:
                continue
            if value is None:
                value = float(az[sel[0]])  # frozen at the first value of the run
                self.tally.stuck_runs += 1
            az[sel] = value
            entry[1] = left - sel.size
            entry[2] = value
            self.tally.stuck_samples += int(sel.size)

    # -- frame faults -------------------------------------------------------
    def frame_faults(self, t: np.ndarray, wheel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(drop, corrupt_one)`` boolean masks over a chunk's frames (in send order)."""
        n = t.size
        drop = np.zeros(n, bool)
        corrupt = np.zeros(n, bool)
        if self.plan.drop_rate:
            drop |= self.rng.random(n) < self.plan.drop_rate
        for entry in self._pending_frame:
            fault, left = entry
            if left <= 0:
                continue
            cand = (t >= fault.at) & ~drop & ~corrupt
            if fault.params["wheel"] is not None:
                cand &= wheel == fault.params["wheel"]
            sel = np.flatnonzero(cand)[:left]
            (drop if fault.kind == "drop" else corrupt)[sel] = True
            entry[1] = left - sel.size
        return drop, corrupt

    def corrupt_bytes(self, frames: list[bytes], force_one: np.ndarray) -> tuple[list[bytes], np.ndarray]:
        """Corrupt serial frames: every byte with probability ``corrupt_rate``,
        plus one byte of each frame where ``force_one``.

        Returns the frames (changed ones replaced) and a mask of the frames the
        receiver cannot get: those with a changed byte, and those that follow
        a corrupted delimiter (the receiver sees the two as one bad segment;
        across calls too).  ``bytes_corrupted`` is tallied here; the caller
        counts the lost frames once they are sent."""
        n = len(frames)
        lost = np.zeros(n, bool)
        if not frames:
            return frames, lost
        carry, self._delimiter_carry = self._delimiter_carry, False
        if carry:
            lost[0] = True
        rate = self.plan.corrupt_rate
        if not rate and not force_one.any():
            return frames, lost
        lengths = np.fromiter((len(f) for f in frames), np.int64, n)
        buf = bytearray(b"".join(frames))
        flat = np.frombuffer(buf, np.uint8)
        hit = self.rng.random(flat.size) < rate if rate else np.zeros(flat.size, bool)
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        forced = np.flatnonzero(force_one)
        if forced.size:
            hit[starts[forced] + self.rng.integers(0, lengths[forced] - 1)] = True  # not the delimiter
        idx = np.flatnonzero(hit)
        if not idx.size:
            return frames, lost
        flat[idx] ^= self.rng.integers(1, 256, idx.size).astype(np.uint8)
        self.tally.bytes_corrupted += int(idx.size)
        owner = np.searchsorted(starts, idx, side="right") - 1
        touched = np.zeros(n, bool)
        touched[owner] = True
        ends = starts + lengths - 1
        delimiter_hit = hit[ends]
        lost |= touched
        lost[1:] |= delimiter_hit[:-1]
        self._delimiter_carry = bool(delimiter_hit[-1])
        out = [
            bytes(buf[s : s + k]) if touched[j] else frames[j]
            for j, (s, k) in enumerate(zip(starts.tolist(), lengths.tolist()))
        ]
        return out, lost

    @property
    def corruption_pending(self) -> bool:
        """A corrupted delimiter takes the next frame sent with it."""
        return self._delimiter_carry

    # -- link faults --------------------------------------------------------
    def next_link_fault_time(self) -> float:
        """Scenario time [s] of the next link fault (inf: none left)."""
        return self._link[0].at if self._link else float("inf")

    def link_faults_due(self, t: float) -> list[ScheduledFault]:
        """Link faults whose time has come by scenario time ``t`` (each returned once)."""
        due = []
        while self._link and self._link[0].at <= t:
            due.append(self._link.pop(0))
        return due
