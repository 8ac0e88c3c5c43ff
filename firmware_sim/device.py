"""The virtual IMU device: a scenario's sample stream, paced in real time, sent over a link.

:class:`ScenarioFeed` turns one scenario per wheel-leg into *frame tables*:
every IMU sample of every wheel (and, with ``send_reference``, one
reference-slip frame per wheel at the start of each leg cycle), in send
order, with per-(type, wheel) sequence counters and the angle wrapped to
``[-pi, pi)`` as a device reports it.

:class:`Device` paces the tables: the frame of scenario time ``t`` is due at
``start + t / speed`` on the host's monotonic clock (``speed`` 1.0 = real
time; 0 = as fast as possible), hands the due frames to a :class:`~firmware_sim.link.Link`
(:mod:`firmware_sim.serial_link`, :mod:`firmware_sim.can_link`), applies the
faults of :mod:`firmware_sim.faults`, and tallies what it sent, lost and
injected (:meth:`Device.report`).

Device clock.  Frames carry a timestamp ``t_us`` [us].  With
``clock="monotonic"`` (the default) ``t_us = scale * start_us + t * 1e6``
with ``scale = speed`` (1 when ``speed`` is 0) and ``start_us`` the host's
monotonic clock at the start [us]: timestamps advance at the scenario's pace
(the estimator sees the physics unchanged) and ``t_us / scale`` is the
instant the frame was due on the host's monotonic clock, from which a
receiver on the same host can measure its latency knowing only ``speed``.
With ``clock="zero"`` ``t_us = t * 1e6``.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from typing import Callable, Iterator, Sequence

import numpy as np

from firmware_sim.faults import FaultInjector, FaultPlan
from firmware_sim.link import FRAME_TABLE_DTYPE, KIND_IMU, KIND_REF, Link, LinkDown
from slipest.latency import latency_summary
from slipest.model.scenario import Scenario
from slipest.model.stream import cycle_starts, iter_stream

#: Send-log status of a frame.
SENT, DROPPED, CORRUPTED, LOST_DISCONNECTED, UNSENT_NO_PEER, UNSENT_LINK_ERROR = range(6)
STATUS_NAMES = ("sent", "dropped", "corrupted", "lost_disconnected", "unsent_no_peer", "unsent_link_error")


def wrap_angle(theta):
    """Angle [rad] wrapped to ``[-pi, pi)``, as the device reports it."""
    return np.mod(np.asarray(theta, dtype=np.float64) + math.pi, 2 * math.pi) - math.pi


class ScenarioFeed:
    """Frame tables of ``len(scenarios)`` wheel-legs, merged in time order.

    Every wheel's scenario must have the same rate, leg count and leg
    speeds, cycle by cycle (they share the timeline); seeds and slips may
    differ.  ``duration``
    [s] (> 0) stops the stream early.  Iterating yields frame tables (structured
    arrays of dtype :data:`~firmware_sim.link.FRAME_TABLE_DTYPE`) of
    ``chunk_cycles`` leg cycles."""

    def __init__(
        self,
        scenarios: Sequence[Scenario],
        send_reference: bool = False,
        duration: float | None = None,
        chunk_cycles: int = 1,
    ):
        if not scenarios:
            raise ValueError("a device needs at least one wheel")
        if duration is not None and not (duration > 0 and math.isfinite(duration)):
            raise ValueError(f"duration={duration} must be a number of seconds > 0")
        first = scenarios[0]
        starts = cycle_starts(first)
        for w, sc in enumerate(scenarios):
            same = (sc.rate, sc.n_legs, len(sc.cycles)) == (first.rate, first.n_legs, len(first.cycles))
            if not (same and np.allclose(cycle_starts(sc), starts, rtol=0.0, atol=1e-9)):
                raise ValueError(f"wheel {w}: every wheel's scenario needs the same rate, legs, leg speeds and cycles")
        self.scenarios = list(scenarios)
        self.send_reference = send_reference
        self.duration = duration
        self.chunk_cycles = chunk_cycles
        self.n_wheels = len(scenarios)
        n_cycles = len(first.cycles)
        if duration is not None:  # the cycles that start before it
            n_cycles = min(n_cycles, max(1, int(np.searchsorted(starts, duration, side="left"))))
        #: mean leg-cycle duration of the stream [s]
        self.period = float(starts[n_cycles] / n_cycles)
        self.n_cycles = n_cycles
        #: frames the whole stream holds (an estimate of the IMU part is exact)
        self.expected_imu_frames = math.ceil(starts[n_cycles] * first.rate - 1e-9) * self.n_wheels
        if duration is not None:
            by_duration = math.ceil(duration * first.rate - 1e-9) * self.n_wheels
            self.expected_imu_frames = min(self.expected_imu_frames, by_duration)

    def __iter__(self) -> Iterator[np.ndarray]:
        n = self.n_wheels
        streams = [iter_stream(sc, self.chunk_cycles) for sc in self.scenarios]
        sample0 = 0
        last_cycle = -1
        cycles_done = 0
        while cycles_done < self.n_cycles:
            try:
                chunks = [next(s) for s in streams]
            except StopIteration:
                return
            cycles_done += self.chunk_cycles
            t = chunks[0].t
            keep = t.size
            if self.duration is not None:
                keep = int(np.searchsorted(t, self.duration, side="left"))
            if cycles_done > self.n_cycles:  # the last chunk may hold cycles past the end
                keep = min(keep, int(np.searchsorted(chunks[0].cycle, self.n_cycles, side="left")))
            if keep == 0:
                return
            t = t[:keep]
            m = t.size
            idx = np.arange(m)
            # IMU rows, sample-major then wheel
            imu_sample = np.repeat(idx, n)
            imu_wheel = np.tile(np.arange(n), m)
            cyc = chunks[0].cycle[:keep]
            rows = {
                "kind": np.full(m * n, KIND_IMU, np.uint8),
                "wheel": imu_wheel.astype(np.uint8),
                "seq": (sample0 + imu_sample).astype(np.int64),
                "t": t[imu_sample],
                "az": np.stack([c.az[:keep] for c in chunks], axis=1).reshape(-1),
                "theta": wrap_angle(np.stack([c.theta[:keep] for c in chunks], axis=1).reshape(-1)),
                "slip": np.stack([c.slip[:keep] for c in chunks], axis=1).reshape(-1),
                "cycle": cyc[imu_sample],
            }
            order_key = imu_sample * (2 * n) + n + imu_wheel
            if self.send_reference:
                starts = np.flatnonzero(np.diff(np.concatenate([[last_cycle], cyc])) != 0)
                if starts.size:
                    rs = np.repeat(starts, n)
                    rw = np.tile(np.arange(n), starts.size)
                    ref = {
                        "kind": np.full(rs.size, KIND_REF, np.uint8),
                        "wheel": rw.astype(np.uint8),
                        "seq": cyc[rs].astype(np.int64),
                        "t": t[rs],
                        "az": np.full(rs.size, np.nan),
                        "theta": np.full(rs.size, np.nan),
                        "slip": np.stack([c.slip[:keep] for c in chunks], axis=1)[rs, rw],
                        "cycle": cyc[rs],
                    }
                    rows = {k: np.concatenate([rows[k], ref[k]]) for k in rows}
                    order_key = np.concatenate([order_key, rs * (2 * n) + rw])
            order = np.argsort(order_key, kind="stable")
            table = np.empty(order.size, FRAME_TABLE_DTYPE)
            for name, column in rows.items():
                table[name] = column[order]
            yield table
            last_cycle = int(cyc[-1])
            sample0 += m
            if keep < chunks[0].t.size:
                return


class _Prefetch:
    """Runs a feed in a thread ahead of the pacing loop (bounded queue)."""

    _END = object()

    def __init__(self, feed, max_items: int):
        self._q: queue.Queue = queue.Queue(maxsize=max(1, max_items))
        self.error: BaseException | None = None
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(feed,), name="firmware-sim-feed", daemon=True)
        self._thread.start()

    def _run(self, feed):
        try:
            for table in feed:
                while not self._stop.is_set():
                    try:
                        self._q.put(table, timeout=0.2)
                        break
                    except queue.Full:
                        continue
                if self._stop.is_set():
                    return
        except BaseException as exc:  # handed to the consumer
            self.error = exc
        finally:
            self.done.set()
            try:
                self._q.put(self._END, timeout=0.5)
            except queue.Full:
                pass

    def wait_filled(self, stop: threading.Event) -> None:
        """Block until the feed is exhausted or the queue is full."""
        while not stop.is_set() and not self.done.is_set() and not self._q.full():
            time.sleep(0.02)

    def get(self, stop: threading.Event):
        while not stop.is_set():
            try:
                item = self._q.get(timeout=0.2)
            except queue.Empty:
                continue
            if item is self._END:
                if self.error is not None:
                    raise self.error
                return None
            return item
        return None

    def close(self):
        self._stop.set()


class Device:
    """Paces a :class:`ScenarioFeed` over a link, injecting faults.

    ``speed``: 1.0 real time, 10 ten times faster, 0 as fast as possible.
    ``announce(text)``: where the device reports events (link paths,
    disconnects); ``stop``: a :class:`threading.Event` that ends the run.
    ``wait_peer``: seconds (> 0) to wait for a peer before starting the clock
    (``None`` forever).  ``linger``: seconds (>= 0) to keep the link open after
    the last frame, so the peer can drain it.  ``send_log``: keep one row per
    frame (kind, wheel, seq, t_us, send time, status, cycle, slip, and the
    values before any corruption: az, theta) for :meth:`send_log`.
    ``max_prefetch_frames``: frames generated ahead of time; a run with
    fewer frames is generated whole before the clock starts, so the
    simulator's compiled kernel (which holds the GIL) never delays a frame.
    """

    def __init__(
        self,
        feed: ScenarioFeed,
        link: Link,
        plan: FaultPlan | None = None,
        *,
        speed: float = 1.0,
        clock: str = "monotonic",
        announce: Callable[[str], None] | None = None,
        stop: threading.Event | None = None,
        wait_peer: float | None = None,
        linger: float = 0.5,
        send_log: bool = False,
        max_prefetch_frames: int = 2_000_000,
    ):
        if not (speed >= 0 and math.isfinite(speed)):
            raise ValueError(f"speed={speed} must be >= 0 (0: as fast as possible)")
        if wait_peer is not None and not (wait_peer > 0 and math.isfinite(wait_peer)):
            raise ValueError(f"wait_peer={wait_peer} must be a number of seconds > 0 (None: wait)")
        if not (linger >= 0 and math.isfinite(linger)):
            raise ValueError(f"linger={linger} must be a number of seconds >= 0")
        if clock not in ("monotonic", "zero"):
            raise ValueError(f"clock={clock!r}: expected 'monotonic' or 'zero'")
        if not isinstance(link, Link):
            raise TypeError(f"link must be a firmware_sim.link.Link, got {type(link).__name__}")
        self.feed = feed
        self.link = link
        self.plan = plan or FaultPlan()
        self.injector = FaultInjector(self.plan, feed.n_wheels)
        self.speed = float(speed)
        self.clock = clock
        self.announce = announce or (lambda text: None)
        self.stop = stop or threading.Event()
        self.wait_peer = wait_peer
        self.linger = linger
        self.keep_send_log = send_log
        self.max_prefetch_frames = max_prefetch_frames
        n = feed.n_wheels
        self.counts = {
            "imu_frames_generated": 0,
            "ref_frames_generated": 0,
            "imu_frames_sent": 0,
            "ref_frames_sent": 0,
            "bytes_sent": 0,
            "frames_unsent_no_peer": 0,
            "frames_unsent_link_error": 0,
            "link_errors": 0,
            "imu_sent_by_wheel": [0] * n,
            "last_imu_seq_by_wheel": [None] * n,
            "last_ref_seq_by_wheel": [None] * n,
            "cycles_started": 0,
        }
        self._lateness: list[np.ndarray] = []  # send lateness [s] per table, float32
        self._log_parts: list[dict] = []
        self.start_mono: float | None = None
        self.t0_us = 0
        self.elapsed = 0.0
        self.finished = False
        self._down_until: float | None = None  # planned outage in progress: until this scenario time [s]
        self._reconnect_called = False

    # -- clock ----------------------------------------------------------------
    @property
    def clock_scale(self) -> float:
        return self.speed if self.speed > 0 else 1.0

    def _due(self, t: np.ndarray) -> np.ndarray:
        if self.speed == 0:
            return np.full(t.size, -np.inf)
        return self.start_mono + t / self.speed

    # -- main loop ------------------------------------------------------------
    def run(self) -> dict:
        """Stream the whole feed (or until ``stop``); return :meth:`report`."""
        self.link.open()
        frames_total = self.feed.expected_imu_frames
        per_table = self.feed.period * self.feed.scenarios[0].rate * self.feed.n_wheels * self.feed.chunk_cycles
        prefetch = _Prefetch(self.feed, max_items=max(2, int(self.max_prefetch_frames // max(1.0, per_table))))
        try:
            if frames_total <= self.max_prefetch_frames:
                prefetch.wait_filled(self.stop)
            self._wait_for_peer()
            if self.stop.is_set():
                return self.report()
            self.start_mono = time.monotonic()
            if self.clock == "monotonic":
                self.t0_us = int(round(self.clock_scale * self.start_mono * 1e6))
            self.announce(f"streaming {self.feed.n_wheels} wheel(s), speed {self.speed:g}, t0_us {self.t0_us}")
            while not self.stop.is_set():
                table = prefetch.get(self.stop)
                if table is None:
                    break
                self._send_table(table)
            self.finished = not self.stop.is_set()
            self.elapsed = time.monotonic() - self.start_mono
            if self.finished and self.linger > 0:
                self.stop.wait(self.linger)
        finally:
            prefetch.close()
            self.link.close()
        return self.report()

    def _wait_for_peer(self) -> None:
        deadline = None if self.wait_peer is None else time.monotonic() + self.wait_peer
        since, said = time.monotonic(), False
        while not self.stop.is_set() and not self.link.ready():
            if not said and time.monotonic() - since > 5.0:  # no peer (a pty's reader gone or not come, a bus down)
                self.announce(f"ready to stream; waiting for a peer on {self.link.name}")
                said = True
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"no peer connected to {self.link.name} within {self.wait_peer:g} s")
            time.sleep(0.01)

    def _send_table(self, table: np.ndarray) -> None:
        n = len(table)
        is_imu = table["kind"] == KIND_IMU
        self.counts["imu_frames_generated"] += int(np.count_nonzero(is_imu))
        self.counts["ref_frames_generated"] += int(n - np.count_nonzero(is_imu))
        self.injector.apply_stuck(table["t"], table["wheel"], table["az"], is_imu)
        drop, corrupt_one = self.injector.frame_faults(table["t"], table["wheel"])
        t_us = self.t0_us + np.rint(table["t"] * 1e6).astype(np.int64)
        due = self._due(table["t"])
        due_list = due.tolist()
        t_list = table["t"].tolist()
        drop_list = drop.tolist()
        any_corrupt = bool(self.plan.corrupt_rate) or bool(corrupt_one.any())
        status = np.full(n, SENT, np.uint8)
        send_ns = np.full(n, -1, np.int64)
        batch = 256 if self.speed == 0 else 64  # bounded bursts: a late device still re-checks the clock
        i = 0
        while i < n and not self.stop.is_set():
            now = time.monotonic()
            wait = due_list[i] - now
            if wait > 0:
                if wait > 0.002:
                    self.stop.wait(wait)
                else:
                    time.sleep(wait)
                now = time.monotonic()
            self._link_faults(t_list[i])
            # a burst never straddles a link fault or the end of an outage
            split = min(self.injector.next_link_fault_time(),
                        self._down_until if self._down_until is not None else math.inf)
            j = i + 1
            while j < n and due_list[j] <= now and j - i < batch and t_list[j] < split:
                j += 1
            self._send_range(table, t_us, i, j, drop_list, corrupt_one, any_corrupt, status, send_ns, t_list[i])
            i = j
        if i < n:  # stopped mid-table: the rest was never due
            table = table[:i]
            status, send_ns, t_us, due = status[:i], send_ns[:i], t_us[:i], due[:i]
        self._account(table, status, send_ns, due)
        if self.keep_send_log:
            self._log_parts.append(
                {"kind": table["kind"], "wheel": table["wheel"], "seq": table["seq"], "t_us": t_us,
                 "send_ns": send_ns, "status": status, "cycle": table["cycle"], "slip": table["slip"],
                 "az": table["az"], "theta": table["theta"]}
            )

    def _link_faults(self, t: float) -> None:
        for fault in self.injector.link_faults_due(t):
            if fault.kind == "disconnect":
                if self._down_until is None:
                    self.link.disconnect()
                    self.injector.tally.disconnects += 1
                    self.announce(f"fault: disconnect for {fault.params['down']:g} s")
                self._down_until = fault.at + fault.params["down"]  # scenario time
                self._reconnect_called = False
            elif fault.kind == "unknown-ids":
                if self._down_until is None and self.link.ready():
                    try:
                        sent = self.link.send_unknown(fault.params["n"], self.injector.rng)
                    except LinkDown:
                        sent = 0
                    self.injector.tally.unknown_sent += sent
                    self.announce(f"fault: {sent} unknown message(s)")

    def _link_up(self, t: float) -> bool:
        """Whether frames can go out now (``t``: scenario time of the next
        frame); drives a planned outage's reconnection: the link stays down
        until scenario time ``at + down`` (so a device running late loses the
        same frames as a punctual one), then until the peer is back."""
        if self._down_until is not None:
            if t < self._down_until:
                return False
            if not self._reconnect_called:
                self.link.reconnect()
                self._reconnect_called = True
            if not self.link.ready():
                return False
            self._down_until = None
            self.injector.tally.reconnects += 1
            self.announce("fault: link back")
            return True
        return self.link.ready()

    def _send_range(self, table, t_us, i, j, drop_list, corrupt_one, any_corrupt, status, send_ns, t_first) -> None:
        if not self._link_up(t_first):
            status[i:j] = LOST_DISCONNECTED if self._down_until is not None else UNSENT_NO_PEER
            return
        keep = [k for k in range(i, j) if not drop_list[k]]
        if j - i != len(keep):
            status[[k for k in range(i, j) if drop_list[k]]] = DROPPED
        if not keep:
            return
        items = self.link.encode(table, t_us, keep)
        touched = None
        if (any_corrupt or self.injector.corruption_pending) and self.link.corrupts:
            items, touched = self.injector.corrupt_bytes(items, corrupt_one[keep])
        try:
            nbytes = self.link.send(items)
        except LinkDown as exc:
            self.counts["link_errors"] += 1
            status[keep] = UNSENT_LINK_ERROR
            self.announce(f"link error: {exc}")
            return
        send_ns[keep] = time.monotonic_ns()
        self.counts["bytes_sent"] += int(nbytes or 0)
        if touched is not None and touched.any():
            status[np.asarray(keep)[touched]] = CORRUPTED

    def _account(self, table: np.ndarray, status, send_ns, due) -> None:
        """Fold one table's per-frame outcome into the counters."""
        tally = self.injector.tally
        nw = self.feed.n_wheels
        imu = table["kind"] == KIND_IMU
        wheel = table["wheel"]
        out = (status == SENT) | (status == CORRUPTED)
        tally.count_lost("frames_dropped", wheel[status == DROPPED])
        tally.count_lost("frames_corrupted", wheel[status == CORRUPTED])
        tally.count_lost("frames_lost_disconnected", wheel[status == LOST_DISCONNECTED])
        c = self.counts
        c["frames_unsent_no_peer"] += int(np.count_nonzero(status == UNSENT_NO_PEER))
        c["frames_unsent_link_error"] += int(np.count_nonzero(status == UNSENT_LINK_ERROR))
        c["imu_frames_sent"] += int(np.count_nonzero(out & imu))
        c["ref_frames_sent"] += int(np.count_nonzero(out & ~imu))
        c["cycles_started"] += int(np.count_nonzero(out & ~imu))
        per = np.bincount(wheel[out & imu].astype(np.int64), minlength=nw)
        for w in range(nw):
            c["imu_sent_by_wheel"][w] += int(per[w])
            for kind_imu, key in ((True, "last_imu_seq_by_wheel"), (False, "last_ref_seq_by_wheel")):
                sel = np.flatnonzero(out & (imu == kind_imu) & (wheel == w))
                if sel.size:
                    c[key][w] = int(table["seq"][sel[-1]])
        if np.isfinite(due).any():
            sent = send_ns >= 0
            self._lateness.append((send_ns[sent] * 1e-9 - due[sent]).astype(np.float32))

    # -- results -----------------------------------------------------------------
    def report(self) -> dict:
        """What the device did: counts, injected faults, lateness, clock."""
        return {
            "device": "firmware-sim",
            "link": self.link.describe(),
            "wheels": self.feed.n_wheels,
            "speed": self.speed,
            "clock": self.clock,
            "clock_scale": self.clock_scale,
            "t0_us": self.t0_us,
            "start_monotonic": self.start_mono,
            "elapsed_s": self.elapsed,
            "finished": self.finished,
            "faults_requested": self.plan.describe(),
            "sent": dict(self.counts),
            "injected": self.injector.tally.as_dict(),
            "lateness": latency_summary(self._lateness),
        }

    def send_log(self) -> dict[str, np.ndarray]:
        """One row per frame handled (see the status codes :data:`STATUS_NAMES`)."""
        if not self._log_parts:
            return {}
        return {k: np.concatenate([p[k] for p in self._log_parts]) for k in self._log_parts[0]}
