"""From a device's per-wheel frames to the estimator's samples (pure computation).

A live device sends, per wheel-leg, samples with a sequence counter, a
timestamp and an angle it wraps to ``[-pi, pi)``.  :class:`WheelStream`
turns them into the continuous ``t, az, theta`` stream the estimator and the
log CSV take, and guarantees that nothing lost or corrupted is estimated
from.  Each frame goes through these rules, in arrival order:

* **Time.**  Absolute timestamps are taken as they are (shifted once the
  device's clock started again, below).  Wrapped ones (``time_modulus``,
  CAN's ``TimeMod``) advance by ``(t - last) mod M`` plus a whole number
  ``k`` of periods ``M``; the candidates are the steps within a second of
  host time of the arrival step (``time_scale`` device seconds at a
  sped-up device: a receiver is never a second behind), and the counter picks the ``k`` whose number of lost frames
  matches its own jump (a receiver that stalled and read a burst has a long
  arrival step but no lost frame), the arrival time breaking ties.  When
  none matches (within 2 frames) the device restarted: the step nearest
  the arrival step is taken.
* **Invalid frames.**  A frame whose time or angle is not a finite number
  (CAN's ``ThetaInvalid``: the device could not read its encoder) is not
  taken (``frames_invalid``): the next frame finds it lost, a NaN sample
  in its place.  A NaN ``az`` (``AzInvalid``) is taken as a NaN sample.
* **Out-of-order frames.**  A frame whose time is not after the last
  accepted one is a duplicate or a reordering when it is less than a
  second back and (with a counter) its counter went back as many frames as
  its time did (within 2): dropped (``out_of_order``).  Otherwise, with
  absolute timestamps, the device's clock started again (a restart, below).
  Wrapped times cannot go back, so there a frame whose counter went back
  (by less than half its range) as many periods as its wrapped time did
  (within 2) is the reordering (a frame sent late by a bus's arbitration
  or a logger's buffers), dropped too: the frame it came after has already
  counted it lost.  With ``reorder_window`` (CAN's sources set it), frames
  a few counter steps late are first put back in counter order
  (:class:`~slipest.io.counter_order.CounterOrder`, ``reordered``): only
  a frame later than the window is dropped so, and a lost frame delays the
  window's frames after it.
* **Lost frames.**  A forward jump of the counter by ``n + 1`` means ``n``
  frames were lost (dropped, corrupted, or sent while the link was down),
  when the time step says so too.  Once the sample period is learnt, the
  jump is read together with the time step: the counter's ``n`` plus the
  whole number of counter ranges that brings it closest to the time step
  (``time step / period - 1`` frames, the period being the average since
  the start or the last restart), so an outage longer than the counter's
  range is still counted right.  Without a counter (``seq_modulus=0``),
  losses are read from the time step alone.  For each lost frame a sample
  with ``az = NaN`` is inserted at its time (times and angles interpolated
  between the neighbours; ``filled``): the estimator leaves them out,
  bridges a few in a row (a cycle estimated so is ``"repaired"``) and
  flags a cycle with a longer run (``"nan"``; the rule is
  :class:`slipest.segmentation.CycleSegmenter`'s), never estimating from
  a lost sample.  One loss inserts at most ``max_fill`` evenly spaced
  samples (the rest shows as a time gap).
* **Time glitches.**  A frame (absolute times) whose counter is one step on
  from the last frame's but whose time disagrees with that (a corrupted
  timestamp: an hour off, 2**64 - 1 us) is held for one frame: when the
  next frame is two counter steps and about two periods on from the last
  one taken, the held frame's time alone was wrong, and it is dropped
  (``time_glitches``; the next frame finds it lost: a NaN sample in its
  place); otherwise it is taken as the rules below take it.  A device
  that restarts with its counter by chance one step on is thus seen a
  frame later.
* **Restarts.**  A device that starts again counts from scratch: its
  counter no longer follows its clock.  When the counter's jump and the time
  step disagree (by more than 2 frames + 100 ppm of the time step, modulo the
  counter's range), or the clock went back (above), the frame is a restart
  (``restarts``): taken, no sample inserted, nothing counted as lost (the
  segmenter flags a window the restart falls in: a time or angle gap).  A
  clock that went back is shifted to go on from the last time by the
  arrival step (times ``time_scale``; one period when unknown), so time
  keeps increasing in the samples and the recording.  A restart is told
  from an outage only as well as its counter disagrees: after a reboot
  that resets a 16-bit counter, but for (5 + 2e-4 x the time step in
  frames) chances in 65536; on CAN, whose 8-bit counter may agree by chance
  (within 2: 5 chances in 256) with one of the two or three steps within a
  second of the arrival step, a few restarts in a hundred are counted as an
  outage.
* **Late start.**  A device counts from 0 when it starts, so the first
  frame's counter is how many frames were sent before it: missed by a
  receiver that started after the device (``frames_missed_at_start``, also
  after each restart; modulo the counter's range, so at least that many).
* **Angle.**  Unwrapped, choosing the ``2 pi`` branch closest to the angle
  predicted from the recent leg speed (so an outage longer than half a turn
  is still unwrapped right when the speed is steady).
* **Learning.**  A step of one frame (no loss, no restart) whose angle step
  is under 1 rad updates the sample period (``0.9 p + 0.1 dt``) and the leg
  speed (``0.8 w + 0.2 dtheta/dt``); the first such step sets both.
* **Stuck sensor.**  ``az`` bit-identical over a run lasting ``stuck_time``
  (:data:`STUCK_TIME`, 20 ms: 20 samples at 1 kHz), never fewer than
  :data:`STUCK_MIN_SAMPLES` samples (a frozen sensor or a stuck driver) is
  replaced by NaN from its first repeat on.  Noisy data repeats far less:
  float32 values (serial) practically never; values in CAN's 0.005 m/s^2
  steps, or an IMU's own ADC steps, repeat a sample with probability ``p``
  of 0.01-0.15 (noise 10-1 mg), so a false alarm needs ``p**(n-1)``: never
  within years for 20 samples; the floor keeps slow IMUs from false alarms
  (``tools/stuck_threshold.py`` measures ``p`` and the false-alarm
  intervals, 120 s streams: at 100-1000 Hz with 10-3 mg of noise, and at
  1 kHz with 1 mg, one in more than 10,000 years on either link; over CAN
  at 100-200 Hz with 1 mg, one in 20-90 years driving and one in 4-8 months
  at rest, the worst case).
  Samples that repeat the previous ``az`` are held back until the run breaks
  (they are released unchanged) or reaches the threshold (released as NaN),
  so a stuck run is never handed on; normal data, which does not repeat, is
  not delayed.  An inserted (lost) sample breaks a run.
* **Reference slip.**  The last reference slip received for the wheel is
  attached to every following sample (NaN before the first).

The output depends only on the frames and their order, not on how they are
split between calls of :meth:`WheelStream.add`.  A call of 32 frames or more
(a burst after a stall, a device faster than real time) applies the same
rules with numpy to runs of plain frames (one counter step and about one
sample period apart, angle steps under 1 rad, ``az`` not repeating, or
repeating too few times to be stuck and released within the run), to the
bit the same samples, counters and state (``tests/test_live_serial.py``
states it as a property); the other frames go one by one.  Counters:
:meth:`WheelStream.counters`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slipest.io.counter_order import CounterOrder
from slipest.stuck import STUCK_MIN_SAMPLES, STUCK_TIME, stuck_run_length

__all__ = ["STUCK_MIN_SAMPLES", "STUCK_TIME", "SEQ_MODULUS", "WheelSamples", "WheelStream", "stuck_run_length"]

SEQ_MODULUS = 1 << 16
#: [s] no link reorders frames by this much: a frame further back is a restarted clock.
_REORDER_S = 1.0
#: [s of host time] wrapped times: a receiver is never this far behind the device, nor a frame this far ahead of
#: its arrival.
_MAX_LAG_S = 1.0
#: Counter and time steps agree within this many frames (+ 100 ppm of the time step: clock drift) for a loss.
_AGREE_FRAMES = 2
#: Steps since the start or a restart before the average period is used for the time step.
_LONG_MIN = 32
_TWO_PI = 2.0 * math.pi
_NAN = math.nan
_FIELDS = ("t", "az", "theta", "slip", "filled", "intake")
#: Calls with at least this many frames try the vectorised run of plain frames (bursts after a stall).
_RUN_MIN = 32
#: Most frames one vectorised run looks at (its cost grows with the frames it looks at, not those it takes).
_RUN_MAX = 2048


@dataclass
class WheelSamples:
    """Samples ready for the estimator and the log: ``t`` [s], ``az`` [m/s^2]
    (NaN where a frame was lost or the sensor stuck), ``theta`` [rad,
    unwrapped], ``slip`` [-] (reference; NaN when none), ``filled`` (True for
    samples inserted in place of lost frames), ``intake`` [s, host monotonic
    clock] when the sample's frame arrived (NaN for inserted samples)."""

    t: np.ndarray
    az: np.ndarray
    theta: np.ndarray
    slip: np.ndarray
    filled: np.ndarray
    intake: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)

    @staticmethod
    def empty() -> "WheelSamples":
        e = np.empty(0)
        return WheelSamples(e, e, e, e, np.empty(0, bool), e)

    @staticmethod
    def concatenate(parts) -> "WheelSamples":
        parts = [p for p in parts if len(p)]
        if not parts:
            return WheelSamples.empty()
        if len(parts) == 1:
            return parts[0]
        return WheelSamples(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))


class _Rows:
    """Output rows collected as Python lists (cheaper than arrays for a few rows)."""

    __slots__ = ("t", "az", "theta", "slip", "filled", "intake")

    def __init__(self):
        self.t, self.az, self.theta, self.slip, self.filled, self.intake = [], [], [], [], [], []

    def append(self, t, az, theta, slip, filled, intake) -> None:
        self.t.append(t)
        self.az.append(az)
        self.theta.append(theta)
        self.slip.append(slip)
        self.filled.append(filled)
        self.intake.append(intake)

    def samples(self) -> WheelSamples:
        if not self.t:
            return WheelSamples.empty()
        return WheelSamples(np.array(self.t), np.array(self.az), np.array(self.theta), np.array(self.slip),
                            np.array(self.filled, bool), np.array(self.intake))


def _column(values, n: int):
    """``values`` as a sequence of ``n`` Python numbers (ValueError on another length)."""
    if isinstance(values, np.ndarray):
        values = values.tolist()
    if len(values) != n:
        raise ValueError(f"got {len(values)} values for {n} frames")
    return values


class WheelStream:
    """One wheel-leg's frames -> samples (see the module docstring for the rules).

    ``seq_modulus``: the counter's modulus (2**16 on serial, 256 on CAN; 0:
    the frames carry no counter).  ``time_modulus``: [s] the timestamps wrap
    with this period (CAN: 0.65536 s); the arrival times (``intake``) must
    then be given to :meth:`add`.  None: timestamps are absolute.
    ``time_scale``: device seconds per host second (the device's speed-up),
    to compare device time steps with arrival steps.  ``max_fill``: most
    samples inserted for one loss.  ``stuck_time`` [s]: duration of a run of
    identical ``az`` taken as a stuck sensor (0: never; see the module
    docstring); ``stuck_samples``: a fixed run length in samples instead (0:
    never).  ``reorder_window``: frames up to this many counter steps late
    are put back in counter order first (0: none; needs a counter; see the
    module docstring).  :attr:`events` collects, for people, the restarts and late
    starts seen (the caller takes them).
    """

    def __init__(self, wheel: int = 0, *, seq_modulus: int = SEQ_MODULUS, time_modulus: float | None = None,
                 time_scale: float = 1.0, max_fill: int = 10000, stuck_samples: int | None = None,
                 stuck_time: float = STUCK_TIME, reorder_window: int = 0):
        self.wheel = wheel
        self.time_scale = time_scale
        self.seq_modulus = seq_modulus
        self.time_modulus = time_modulus
        self.max_fill = max_fill
        self.stuck_samples = stuck_samples
        self.stuck_time = stuck_time
        self._stuck_on = bool(stuck_samples) if stuck_samples is not None else bool(stuck_time)
        self.events: list[str] = []
        self._t_offset = 0.0  # added to absolute device times once the device's clock started again
        self._anchor_t = 0.0  # time of the first frame since the start or the last restart [s]
        self._anchor_steps = 0  # sample periods since then (received and lost frames)
        self._last_seq: int | None = None
        self._last_t: float | None = None
        self._last_theta: float | None = None  # unwrapped
        self._last_raw_t: float | None = None  # as received (wrapped when time_modulus)
        self._last_intake: float | None = None
        self._period: float | None = None  # sample period [s], learnt
        self._omega = 0.0  # recent leg speed [rad/s]
        self._slip = _NAN
        self._held: list[tuple] = []  # (t, az, theta, slip, intake) of a repeating run
        self._stuck = False
        self._prev_az = _NAN
        self._fast_frames = 0  # frames taken by the vectorised run (tests check it is exercised)
        self._suspect: tuple | None = None  # a frame whose time disagrees with its counter's step of one, held
        self._order = CounterOrder(seq_modulus, reorder_window) if reorder_window and seq_modulus else None
        self.c = {
            "samples_in": 0,
            "samples_out": 0,
            "frames_lost": 0,
            "loss_events": 0,
            "samples_filled": 0,
            "out_of_order": 0,
            "frames_invalid": 0,
            "restarts": 0,
            "time_glitches": 0,
            "frames_missed_at_start": 0,
            "stuck_runs": 0,
            "stuck_samples": 0,
            "references": 0,
        }

    # -- inputs ------------------------------------------------------------------
    def set_reference(self, slip: float) -> None:
        """A reference slip [-] for the samples that follow (NaN: none)."""
        self._slip = float(slip)
        self.c["references"] += 1

    def add(self, seq, t, az, theta, intake=None) -> WheelSamples:
        """Frames of this wheel in arrival order: ``seq`` counters (ignored when
        ``seq_modulus`` is 0), ``t`` [s], ``az`` [m/s^2], ``theta`` [rad,
        wrapped or not], ``intake`` [s, host monotonic] arrival times (None,
        a scalar for all, or one per frame; needed with ``time_modulus``).
        Returns the samples that are ready (held samples of a repeating run
        come later); ValueError on inputs of different lengths."""
        n = len(t)
        if n == 0:
            return WheelSamples.empty()
        if intake is None:
            if self.time_modulus:
                raise ValueError("wrapped timestamps need the arrival times (intake)")
            intakes = [_NAN] * n
        elif isinstance(intake, (float, int, np.number)):
            intakes = [float(intake)] * n
        else:
            intakes = _column(intake, n)
        seqs = _column(seq, n) if self.seq_modulus else [None] * n
        ts, azs, ths = _column(t, n), _column(az, n), _column(theta, n)
        self.c["samples_in"] += n
        if self._order is not None:
            seqs, (ts, azs, ths, intakes) = self._order.order(seqs, (ts, azs, ths, intakes))
            n = len(ts)
            if n == 0:
                return WheelSamples.empty()
        frame = self._frame
        if n < _RUN_MIN:  # a live source's usual call: one or two frames
            out = _Rows()
            for sq, tr, a, th, ti in zip(seqs, ts, azs, ths, intakes):
                frame(sq, float(tr), float(a), float(th), float(ti), out)
            self.c["samples_out"] += len(out.t)
            return out.samples()
        cols = (np.asarray(seqs if self.seq_modulus else np.zeros(n), np.int64), np.asarray(ts, np.float64),
                np.asarray(azs, np.float64), np.asarray(ths, np.float64), np.asarray(intakes, np.float64))
        parts = []
        i = 0
        odd = 1  # frames to take one by one after a run stops: 1 (the odd frame), doubling while runs fail at once
        while i < n:
            taken = self._run(*(c[i:i + _RUN_MAX] for c in cols)) if n - i >= _RUN_MIN else None
            if taken is not None:
                parts.append(taken)
                i += len(taken)
                odd = 1
                continue
            stop = n if n - i < 2 * _RUN_MIN else i + odd  # frame by frame past the odd one
            odd = min(2 * odd, _RUN_MIN)
            out = _Rows()
            for k in range(i, stop):
                frame(seqs[k], float(ts[k]), float(azs[k]), float(ths[k]), float(intakes[k]), out)
            parts.append(out.samples())
            i = stop
        s = WheelSamples.concatenate(parts)
        self.c["samples_out"] += len(s)
        return s

    def flush(self) -> WheelSamples:
        """Release held samples (end of stream): frames waiting for a late one, in counter order; a repeating
        run's samples unchanged, as their run was too short; a frame held as a suspected time glitch is taken
        as the rules take it without the frame after it (a restart)."""
        out = _Rows()
        if self._order is not None:
            seqs, fields = self._order.flush()
            for sq, tr, a, th, ti in zip(seqs, *fields):
                self._frame(sq, float(tr), float(a), float(th), float(ti), out)
        if self._suspect is not None:
            suspect, self._suspect = self._suspect, None
            self._frame(*suspect, out, judged=True)
        self._release(out, False)
        self.c["samples_out"] += len(out.t)
        return out.samples()

    def counters(self) -> dict:
        """The counters of the module docstring's rules; ``held``: frames held back now (a repeating run's,
        and those waiting for a late frame); ``reordered``: frames put back in counter order (a late frame's
        duplicate held counts as ``out_of_order``)."""
        c = dict(self.c)
        c["held"] = len(self._held)
        c["reordered"] = 0
        if self._order is not None:
            c["held"] += len(self._order)
            c["reordered"] = self._order.reordered
            c["out_of_order"] += self._order.duplicates
        return c

    # -- the rules, one frame at a time ---------------------------------------------
    def _frame(self, seq, t, az, theta, intake, out: _Rows, judged: bool = False) -> None:
        if not (math.isfinite(t) and math.isfinite(theta)):  # an invalid frame: as if it never came (lost)
            self.c["frames_invalid"] += 1
            return
        if self._suspect is not None:  # the frame after a suspected time glitch decides it
            suspect, self._suspect = self._suspect, None
            if self._follows_glitch(seq, t):
                self.c["time_glitches"] += 1  # dropped: this frame finds it lost (a NaN sample in its place)
            else:
                self._frame(*suspect, out, judged=True)
        elif not judged and self._time_glitch(seq, t):
            self._suspect = (seq, t, az, theta, intake)
            return
        if self.time_modulus:
            if self._late(seq, t):
                self.c["out_of_order"] += 1
                return
            t = self._unwrap_time(t, intake, seq)
        else:
            t += self._t_offset
        last_t = self._last_t
        if last_t is None:
            th = theta
            self._begin(seq, t, out, None)
        else:
            clock_restarted = False
            if t <= last_t:
                if self.time_modulus or not self._clock_restarted(seq, last_t - t):
                    self.c["out_of_order"] += 1
                    return
                t = self._shift_clock(t, intake)
                clock_restarted = True
            last_th = self._last_theta
            th = theta + _TWO_PI * round((last_th + self._omega * (t - last_t) - theta) / _TWO_PI)
            gap = None if clock_restarted else self._gap(seq, t - last_t)
            if gap is None:
                self.c["restarts"] += 1
                self._begin(seq, t, out, t - last_t)
            else:
                self._anchor_steps += gap + 1
                if gap:
                    self._fill(gap, t, th, out)
                elif -1.0 < th - last_th < 1.0:
                    self._learn(t - last_t, th - last_th)
        self._last_seq = seq
        self._last_t = t
        self._last_theta = th
        if intake == intake:
            self._last_intake = intake
        self._sample(t, az, th, intake, out)

    def _run(self, seq, traw, az, theta, intake) -> WheelSamples | None:
        """The rules for a run of plain frames at the start of these arrays, vectorised: each frame
        follows the last accepted one by one counter step and about one sample period, with an angle
        step under 1 rad, and its ``az`` does not repeat, or repeats the frames before it fewer times
        than a stuck run needs and a later frame of the run breaks the repeats (held, then released
        unchanged within the run, as :meth:`_sample` does).  Gives exactly (to the bit, state and
        counters included) what :meth:`_frame` gives for those frames one by one; returns their
        samples, or None when the first frame is not plain."""
        period, omega = self._period, self._omega
        last_t, last_th = self._last_t, self._last_theta
        m = self.time_modulus
        if period is None or last_t is None or self._held or self._stuck or self._suspect is not None:
            return None
        if not (math.isfinite(traw[0]) and math.isfinite(theta[0])):  # an invalid frame: one by one
            return None
        if m:
            if self._last_intake is None or self._last_raw_t is None:
                return None
            base = np.mod(np.diff(traw, prepend=self._last_raw_t), m)
            t_all = np.cumsum(np.concatenate(([last_t], base)))  # as _unwrap_time adds step after step
        else:
            t_all = np.concatenate(([last_t], traw + self._t_offset))
        t = t_all[1:]
        dt = np.diff(t_all)
        # the angle branches, supposing every frame plain; checked below with the leg speed _frame would use
        k0 = round((last_th + omega * float(dt[0]) - float(theta[0])) / _TWO_PI)
        branch = k0 + np.concatenate(([0.0], np.cumsum(np.round((theta[:-1] - theta[1:]) / _TWO_PI))))
        th = theta + _TWO_PI * branch
        th_all = np.concatenate(([last_th], th))
        dth = np.diff(th_all)
        # first the rules that need neither the learnt period nor the leg speed, over all the frames
        with np.errstate(invalid="ignore"):
            ok = (dt > 0) & (np.abs(dth) < 1.0)
            if self.seq_modulus:
                ok &= np.mod(np.diff(seq, prepend=self._last_seq), self.seq_modulus) == 1
            if m:  # _unwrap_time picks k = 0 at its first candidate
                arrival = np.diff(intake, prepend=self._last_intake) * self.time_scale
                ok &= np.isfinite(intake) & (np.abs(base - arrival) / m <= (base + m - arrival) / m)
        repeats = None
        if self._stuck_on:
            repeats = az == np.concatenate(([self._prev_az], az[:-1]))  # NaN never repeats
            if repeats.any():
                # the frames a repeat run started from (its last non-repeating one; -1: the one before these)
                start = np.maximum.accumulate(np.where(repeats, -1, np.arange(az.size)))
                shortest = self.stuck_samples if self.stuck_samples is not None else STUCK_MIN_SAMPLES
                # a run of h repeats is stuck once h + 1 reaches the stuck length: at most shortest - 2 are held
                ok &= ~repeats | (np.arange(az.size) - start <= shortest - 2)
            else:
                repeats = None
        n = int(ok.size if ok.all() else np.argmin(ok))
        if n == 0:
            return None
        # then the rules that need them, over the frames that passed, with what _learn computes frame by frame
        dt, dth = dt[:n], dth[:n]
        periods, omegas = [period], [omega]  # before each frame, then after the last
        for d, r in zip(dt.tolist(), (dth / dt).tolist()):
            period = 0.9 * period + 0.1 * d
            omega = 0.8 * omega + 0.2 * r
            periods.append(period)
            omegas.append(omega)
        p = np.array(periods[:-1])
        ok = (np.round(dt / p) == 1) & (np.round((th_all[:n] + np.array(omegas[:-1]) * dt - theta[:n]) / _TWO_PI)
                                        == branch[:n])
        if m:
            ok &= np.round(base[:n] / p) == 1
        n = int(ok.size if ok.all() else np.argmin(ok))
        if repeats is not None and n and repeats[n - 1]:  # a repeat run not broken within the run: left out
            n = int(start[n - 1]) + 1
        if n == 0:
            return None
        self._period, self._omega = periods[n], omegas[n]
        self._last_seq = int(seq[n - 1]) if self.seq_modulus else None
        self._last_t, self._last_theta, self._prev_az = float(t[n - 1]), float(th[n - 1]), float(az[n - 1])
        if m:
            self._last_raw_t = float(traw[n - 1])
        received = np.flatnonzero(np.isfinite(intake[:n]))
        if received.size:
            self._last_intake = float(intake[received[-1]])
        self._anchor_steps += n
        self._fast_frames += n
        return WheelSamples(t[:n], az[:n].copy(), th[:n], np.full(n, self._slip), np.zeros(n, bool),
                            intake[:n].copy())

    def _unwrap_time(self, traw: float, intake: float, seq) -> float:
        """A wrapped timestamp -> continuous time [s] (the rule in the module docstring)."""
        m = self.time_modulus
        last_raw, self._last_raw_t = self._last_raw_t, traw
        if last_raw is None or self._last_t is None:
            return traw
        base = (traw - last_raw) % m
        last_intake = self._last_intake
        arrival = (intake - last_intake) * self.time_scale if last_intake is not None else _NAN
        timed = arrival == arrival
        period = self._period
        counted = seq is not None and period is not None
        if counted:
            sm = self.seq_modulus
            gap = (seq - self._last_seq - 1) % sm
        max_lag = _MAX_LAG_S * max(1.0, self.time_scale)  # a receiver is never a (host) second behind
        best_score, best_step, k = math.inf, base, 0
        nearest_lag, nearest_step = math.inf, base  # the candidate closest to the arrival step
        while True:  # candidates k = 0, 1, ... up to what the arrival times allow
            step = base + k * m
            lag = abs(step - arrival) if timed else 0.0
            if lag < nearest_lag:
                nearest_lag, nearest_step = lag, step
            if lag <= max_lag:  # a receiver is never further behind (or a frame further ahead)
                score = lag / m if timed else float(k)
                if counted:
                    d = (round(step / period) - 1 - gap) % sm
                    score += 1000.0 * (d if d <= sm - d else sm - d)
                if score < best_score:
                    best_score, best_step = score, step
            # no later candidate can score lower: its time term alone is at least this
            if best_score <= ((step + m - arrival) / m if timed else k + 1.0):
                break
            k += 1
            if k > 1 + (int(max(0.0, arrival - base) // m) + 1 if timed else 0):
                break
        if timed and best_score > 1000.0 * (_AGREE_FRAMES + 0.5):
            # no step the arrival times allow agrees with the counter: a restart (see _gap), at the arrival step
            return self._last_t + nearest_step
        return self._last_t + best_step

    def _late(self, seq, traw: float) -> bool:
        """Whether a frame with a wrapped time is a reordered one: its counter went back (by less than half its
        range) as many periods as its wrapped time did, within 2. Changes no state."""
        if seq is None or self._period is None or self._last_raw_t is None:
            return False
        back = (self._last_seq - seq) % self.seq_modulus
        if back == 0 or back >= self.seq_modulus // 2:
            return False
        went_back = ((self._last_raw_t - traw) % self.time_modulus) / self._period
        return abs(went_back - back) <= _AGREE_FRAMES

    def _time_glitch(self, seq, traw: float) -> bool:
        """Whether a frame is a suspected time glitch: absolute times, a learnt period, its counter one step on
        from the last frame's, and its time disagreeing with that (a restart by the rules). Changes no state."""
        if self.time_modulus or seq is None or self._period is None or self._last_t is None:
            return False
        if (seq - self._last_seq) % self.seq_modulus != 1:
            return False
        dt = traw + self._t_offset - self._last_t
        if dt <= 0.0:
            return self._clock_restarted(seq, -dt)
        return self._gap(seq, dt) is None

    def _follows_glitch(self, seq, traw: float) -> bool:
        """Whether a frame, the one after a suspected time glitch, is two counter steps and about two periods on
        from the last frame taken: then the suspect's time alone was wrong. Changes no state."""
        if (seq - self._last_seq) % self.seq_modulus != 2:
            return False
        dt = traw + self._t_offset - self._last_t
        return dt > 0.0 and self._gap(seq, dt) == 1

    def _gap(self, seq, dt: float) -> int | None:
        """Frames lost before this one, ``dt`` [s] after the last (None: a restart, not a loss).
        Changes no state (the vectorised run skips it for plain frames, where it gives 0)."""
        period = self._period
        if seq is None:
            return 0 if period is None else max(0, round(dt / period) - 1)
        m = self.seq_modulus
        gap = (seq - self._last_seq - 1) % m
        if period is None:
            return None if gap >= m // 2 else gap
        steps = self._anchor_steps
        if steps >= _LONG_MIN:  # the average period since the start: exact over long outages
            average = (self._last_t - self._anchor_t) / steps
            if abs(average - period) <= 0.05 * period:  # else the rate changed: the recent period
                period = average
        by_time = round(dt / period) - 1
        k = max(0, round((by_time - gap) / m))  # counter ranges that went by unseen
        if abs(by_time - gap - k * m) <= min(_AGREE_FRAMES + 1e-4 * abs(by_time), m / 4):
            return gap + k * m
        return None  # the counter and the clock disagree: the device started again

    def _clock_restarted(self, seq, back: float) -> bool:
        """Whether a frame ``back`` [s] before the last one (absolute times) comes from a clock that
        started again, rather than being a duplicate or a reordering."""
        if back >= _REORDER_S:
            return True
        if seq is None or self._period is None:
            return False
        went_back = (self._last_seq - seq) % self.seq_modulus
        return abs(went_back - round(back / self._period)) > _AGREE_FRAMES

    def _shift_clock(self, t: float, intake: float) -> float:
        """The time [s] of the first frame of a restarted clock: the last time plus the arrival step
        (one period when unknown); the frames that follow are shifted by as much."""
        step = self._period or 1e-6
        if intake == intake and self._last_intake is not None:
            step = max(step, (intake - self._last_intake) * self.time_scale)
        shifted = self._last_t + step
        self._t_offset += shifted - t
        return shifted

    def _begin(self, seq, t: float, out: _Rows, after: float | None) -> None:
        """The first frame of the stream (``after`` None) or of a restart, ``after`` [s] after the last."""
        self._anchor_t, self._anchor_steps = t, 0
        missed = seq or 0  # frames the device counted before this one
        self.c["frames_missed_at_start"] += missed
        before = f": at least {missed} frame(s) were sent before it, missed" if missed else ""
        if after is None:
            if missed:
                self.events.append(f"first frame has counter {seq}{before} (started after the device)")
            return
        self._release(out, False)  # a repeating run does not go on across a restart
        self._stuck = False
        self._prev_az = _NAN
        self.events.append(f"the device restarted (counter {seq} {after:.3g} s after the last frame{before}); "
                           "not counted as lost")

    def _learn(self, dt: float, dtheta: float) -> None:
        if self._period is None:
            self._period, self._omega = dt, dtheta / dt
        else:
            self._period = 0.9 * self._period + 0.1 * dt
            self._omega = 0.8 * self._omega + 0.2 * (dtheta / dt)

    def _fill(self, lost: int, t: float, th: float, out: _Rows) -> None:
        c = self.c
        c["frames_lost"] += lost
        c["loss_events"] += 1
        k = min(lost, self.max_fill)
        c["samples_filled"] += k
        frac = np.arange(1, k + 1) / (k + 1)
        last_t, last_th = self._last_t, self._last_theta
        ft = (last_t + frac * (t - last_t)).tolist()
        fth = (last_th + frac * (th - last_th)).tolist()
        self._release(out, False)  # an inserted sample breaks a repeating run
        self._stuck = False
        self._prev_az = _NAN
        slip = self._slip
        out.t += ft
        out.az += [_NAN] * k
        out.theta += fth
        out.slip += [slip] * k
        out.filled += [True] * k
        out.intake += [_NAN] * k

    def _sample(self, t: float, az: float, th: float, intake: float, out: _Rows) -> None:
        """A received sample through the stuck-sensor rule."""
        if not self._stuck_on or az != self._prev_az:
            if self._held:
                self._release(out, False)
            self._stuck = False
            self._prev_az = az
            out.append(t, az, th, self._slip, False, intake)
        elif self._stuck:
            self.c["stuck_samples"] += 1
            out.append(t, _NAN, th, self._slip, False, intake)
        else:
            self._held.append((t, az, th, self._slip, intake))
            if len(self._held) + 1 >= self._stuck_length():  # the first of the run was already released
                self._stuck = True
                self.c["stuck_runs"] += 1
                self.c["stuck_samples"] += len(self._held)
                self._release(out, True)

    def _stuck_length(self) -> int:
        if self.stuck_samples is not None:
            return self.stuck_samples
        return stuck_run_length(self.stuck_time, self._period)

    def _release(self, out: _Rows, as_nan: bool) -> None:
        for t, az, th, slip, intake in self._held:
            out.append(t, _NAN if as_nan else az, th, slip, False, intake)
        self._held = []
