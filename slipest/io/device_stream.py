"""From a device's per-wheel frames to the estimator's samples (pure computation).

A live device sends, per wheel-leg, samples with a 16-bit sequence counter,
a timestamp and an angle it wraps to ``[-pi, pi)``.  :class:`WheelStream`
turns them into the continuous ``t, az, theta`` stream the estimator and the
log CSV take, and guarantees that nothing lost or corrupted is estimated
from:

* **Lost frames.**  A forward jump of the sequence counter by ``n + 1``
  means ``n`` frames were lost (dropped, corrupted, or sent while the link
  was down).  For each lost frame a sample with ``az = NaN`` is inserted at
  its timestamp (timestamps and angles interpolated between the neighbours),
  so the segmenter flags a cycle whose feature window lost even one sample
  (quality ``"nan"``) and never estimates from it.  A long outage is filled
  with at most ``max_fill`` evenly spaced samples (their spacing then also
  shows as a time gap).
* **Out-of-order frames.**  A backward jump of the counter (serial-number
  arithmetic, RFC 1982) or a timestamp not after the previous one is a
  duplicate, a reordering or a restart: a frame whose timestamp is not after
  the last one is dropped (counted); a frame with a later timestamp after a
  backward jump is a device restart: taken, counted, no fill.
* **Angle.**  Unwrapped, choosing the ``2 pi`` branch closest to the angle
  predicted from the recent leg speed (so an outage longer than half a turn
  is still unwrapped right when the speed is steady).
* **Stuck sensor.**  ``az`` bit-identical over ``stuck_samples`` consecutive
  samples (a frozen sensor or a stuck driver; real noisy data never repeats
  that long) is replaced by NaN from its first repeat on.  Samples
  that repeat the previous ``az`` are held back until the run breaks (they
  are released unchanged) or reaches the threshold (released as NaN), so a
  stuck run is never handed on; normal data, which does not repeat, is not
  delayed.
* **Reference slip.**  The last reference slip received for the wheel is
  attached to every following sample (NaN before the first).

Counters: :meth:`WheelStream.counters`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["WheelSamples", "WheelStream", "SEQ_MODULUS"]

SEQ_MODULUS = 1 << 16
_HALF = SEQ_MODULUS // 2
_TWO_PI = 2.0 * math.pi


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
        return WheelSamples(*(np.concatenate([getattr(p, f) for p in parts])
                              for f in ("t", "az", "theta", "slip", "filled", "intake")))


class WheelStream:
    """One wheel-leg's frames -> samples (see the module docstring).

    ``seq_modulus``: the counter's modulus (2**16 on serial, 256 on CAN; 0:
    the frames carry no counter, losses then show only as time gaps).  When
    the sample period is known (learnt from the stream), a counter jump is
    read together with the time step, so an outage longer than the
    counter's range is still counted right.
    ``time_modulus``: [s] the timestamps wrap with this period (CAN's
    ``TimeMod``: 0.65536 s); they are unwrapped with the counter and the
    arrival times (``intake``, which must then be given; ``time_scale``:
    device seconds per host second, the device's speed-up).  None:
    timestamps are absolute.
    ``max_fill``: most samples inserted for one loss.  ``stuck_samples``:
    run length of identical ``az`` taken as a stuck sensor (0: never).
    """

    def __init__(self, wheel: int = 0, *, seq_modulus: int = SEQ_MODULUS, time_modulus: float | None = None,
                 time_scale: float = 1.0, max_fill: int = 10000, stuck_samples: int = 50):
        self.wheel = wheel
        self.time_scale = time_scale
        self.seq_modulus = seq_modulus
        self.time_modulus = time_modulus
        self.max_fill = max_fill
        self.stuck_samples = stuck_samples
        self._last_seq: int | None = None
        self._last_t: float | None = None
        self._last_theta: float | None = None  # unwrapped
        self._last_raw_t: float | None = None  # as received (wrapped when time_modulus)
        self._last_intake: float | None = None
        self._period: float | None = None  # sample period [s], learnt
        self._omega = 0.0  # recent leg speed [rad/s]
        self._slip = math.nan
        self._held: list[tuple] = []
        self._stuck = False
        self._prev_az: float | None = None
        self.c = {
            "samples_in": 0,
            "samples_out": 0,
            "frames_lost": 0,
            "loss_events": 0,
            "samples_filled": 0,
            "out_of_order": 0,
            "restarts": 0,
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
        wrapped or not], ``intake`` [s, host monotonic] arrival times (a
        scalar for all, or one per frame).  Returns the samples that are
        ready (held samples of a repeating run come later)."""
        if len(t) <= 16:
            small = self._add_small(seq, t, az, theta, intake)
            if small is not None:
                return small
        t = np.asarray(t, np.float64)
        az = np.asarray(az, np.float64)
        theta = np.asarray(theta, np.float64)
        n = t.size
        if n == 0:
            return WheelSamples.empty()
        self.c["samples_in"] += n
        seq = np.asarray(seq, np.int64) if self.seq_modulus else None
        if intake is None:
            if self.time_modulus:
                raise ValueError("wrapped timestamps need the arrival times (intake)")
            intake = np.full(n, np.nan)
        else:
            intake = np.array(np.broadcast_to(np.asarray(intake, np.float64), (n,)))
        traw = t
        if self.time_modulus:
            t = self._unwrap_time(traw, intake) if self._last_raw_t is not None else None
            if t is None:  # first frame, or an ambiguous step: frame by frame
                return self._slow(seq, traw, az, theta, intake, wrapped=True)
        if self._fast_ok(seq, t):
            th = self._unwrap_fast(theta, t)
            if th is not None:
                out = WheelSamples(t, az.copy(), th, np.full(n, self._slip), np.zeros(n, bool), intake)
                self._last_seq = int(seq[-1]) if seq is not None else None
                self._last_t = float(t[-1])
                self._last_intake = float(intake[-1])
                if self.time_modulus:
                    self._last_raw_t = float(traw[-1])
                return self._stuck_filter(out)
        return self._slow(seq, traw, az, theta, intake, wrapped=bool(self.time_modulus))

    # -- internals ---------------------------------------------------------------
    def _add_small(self, seq, t, az, theta, intake):
        """A few plain frames (consecutive counters, one period apart, small
        angle steps, no repeated az) in plain Python: a live source delivers
        one or two frames at a time, for which numpy costs more than it saves.
        None (nothing changed) when a frame is not plain."""
        period = self._period
        if period is None or self._last_t is None or self._last_theta is None or self._held or self._stuck:
            return None
        n = len(t)
        if n == 0:
            return None
        m = self.seq_modulus
        tm = self.time_modulus
        if intake is None:
            intakes = [math.nan] * n
        elif isinstance(intake, (int, float)):
            intakes = [float(intake)] * n
        else:
            intakes = [float(x) for x in intake]
        last_t, last_th, last_seq, last_raw = self._last_t, self._last_theta, self._last_seq, self._last_raw_t
        prev_az = self._prev_az
        omega = self._omega
        check_stuck = bool(self.stuck_samples)
        ts, ths, azs = [], [], []
        for i in range(n):
            tr = float(t[i])
            if tm:
                if last_raw is None:
                    return None
                step = (tr - last_raw) % tm
                ti = last_t + step
                last_raw = tr
            else:
                ti = tr
                step = ti - last_t
            if not 0.0 < step < 1.5 * period:
                return None
            if m:
                si = int(seq[i])
                if (si - last_seq) % m != 1:
                    return None
                last_seq = si
            a = float(az[i])
            if check_stuck and a == prev_az:
                return None
            d = float(theta[i]) - last_th
            d -= _TWO_PI * round(d / _TWO_PI)
            if abs(d) > 1.0:
                return None
            period = 0.95 * period + 0.05 * step
            omega = 0.95 * omega + 0.05 * (d / step)
            last_th += d
            last_t = ti
            prev_az = a
            ts.append(ti)
            ths.append(last_th)
            azs.append(a)
        self._period, self._omega = period, omega
        self._last_t, self._last_theta, self._last_seq, self._prev_az = last_t, last_th, last_seq, prev_az
        if tm:
            self._last_raw_t = last_raw
        if intakes[-1] == intakes[-1]:
            self._last_intake = intakes[-1]
        self.c["samples_in"] += n
        self.c["samples_out"] += n
        return WheelSamples(np.array(ts), np.array(azs), np.array(ths), np.full(n, self._slip),
                            np.zeros(n, bool), np.array(intakes))

    def _slow(self, seq, traw, az, theta, intake, wrapped: bool) -> WheelSamples:
        parts = []
        for i in range(traw.size):
            t_i = float(traw[i])
            s_i = None if seq is None else int(seq[i])
            if wrapped:
                t_i = self._unwrap_time_one(t_i, float(intake[i]), s_i)
            parts.append(self._one(s_i, t_i, float(az[i]), float(theta[i]), float(intake[i])))
        return self._stuck_filter(WheelSamples.concatenate(parts))

    def _unwrap_time(self, traw, intake):
        """Vectorised unwrapping of wrapped timestamps when every step is one plain sample period."""
        if self._period is None:
            return None
        prev = np.concatenate([[self._last_raw_t], traw[:-1]])
        step = np.mod(traw - prev, self.time_modulus)
        if not ((step > 0) & (step < 1.5 * self._period)).all():
            return None
        return self._last_t + np.cumsum(step)

    def _unwrap_time_one(self, traw: float, intake: float, seq: int | None) -> float:
        """A wrapped timestamp -> continuous time.

        The step is ``(traw - last) mod M`` plus some whole number ``k`` of
        wraps ``M``.  Candidates ``k`` run up to what the arrival times allow
        (scaled by ``time_scale``); the counter then picks the one whose
        number of lost frames matches the counter's jump (a receiver that
        stalled and read a burst has a long arrival step but no lost frame),
        the arrival time breaking ties."""
        m = self.time_modulus
        if self._last_raw_t is None or self._last_t is None:
            self._last_raw_t = traw
            return traw
        base = (traw - self._last_raw_t) % m
        arrival = (intake - self._last_intake) * self.time_scale if self._last_intake is not None else math.nan
        k_max = 1 + (int(max(0.0, arrival - base) // m) + 1 if arrival == arrival else 0)
        best = None
        for k in range(0, k_max + 1):
            step = base + k * m
            score = abs(step - arrival) / m if arrival == arrival else float(k)
            if seq is not None and self._period is not None:
                lost = round(step / self._period) - 1
                gap = (seq - self._last_seq - 1) % self.seq_modulus
                d = (lost - gap) % self.seq_modulus
                d = min(d, self.seq_modulus - d)
                score += 1000.0 * d
            if best is None or score < best[0]:
                best = (score, step)
        self._last_raw_t = traw
        return self._last_t + best[1]

    def _fast_ok(self, seq, t) -> bool:
        if self._last_t is None or t[0] <= self._last_t or (t.size > 1 and not (np.diff(t) > 0).all()):
            return False
        if self._period is not None and (t[0] - self._last_t) > 1.5 * self._period:
            return False  # a time gap: let the careful path count it
        if seq is None:
            return True
        m = self.seq_modulus
        if (int(seq[0]) - self._last_seq) % m != 1:
            return False
        return seq.size == 1 or bool(((np.diff(seq) % m) == 1).all())

    def _unwrap_fast(self, theta, t):
        prev = self._last_theta
        steps = np.diff(np.concatenate([[prev], theta]))
        steps -= _TWO_PI * np.round(steps / _TWO_PI)
        if (np.abs(steps) > 1.0).any():  # not a small step: the careful path
            return None
        dt = np.diff(np.concatenate([[self._last_t], t]))
        th = prev + np.cumsum(steps)
        self._learn(dt, steps)
        self._last_theta = float(th[-1])
        return th

    def _learn(self, dt, steps) -> None:
        """Update the sample period and leg speed from plain consecutive steps."""
        if dt.size >= 5:
            period = float(np.median(dt))
            omega = float(np.median(steps / dt))
        else:
            period = float(dt[-1])
            omega = float(steps[-1] / dt[-1])
        if self._period is None:
            self._period, self._omega = period, omega
        else:
            self._period = 0.9 * self._period + 0.1 * period
            self._omega = 0.8 * self._omega + 0.2 * omega

    def _unwrap_angle(self, theta: float, t: float) -> float:
        if self._last_theta is None:
            return theta
        predicted = self._last_theta + self._omega * (t - self._last_t)
        return theta + _TWO_PI * round((predicted - theta) / _TWO_PI)

    def _gap(self, seq, t) -> int | None:
        """Frames lost before this one (None: a restart, not a loss)."""
        if seq is None:
            if self._period is None:
                return 0
            return max(0, round((t - self._last_t) / self._period) - 1)
        m = self.seq_modulus
        gap = (seq - self._last_seq - 1) % m
        if self._period is not None:
            by_time = round((t - self._last_t) / self._period) - 1
            k = round((by_time - gap) / m)
            if k >= 1:
                return gap + k * m  # the counter wrapped during the outage
            if gap >= m // 2 and by_time < m // 4:
                return None
            return gap
        return None if gap >= m // 2 else gap

    def _one(self, seq, t, az, theta, intake) -> WheelSamples:
        c = self.c
        fill = 0
        if self._last_t is not None:
            if t <= self._last_t:
                c["out_of_order"] += 1
                return WheelSamples.empty()
            gap = self._gap(seq, t)
            if gap is None:
                c["restarts"] += 1  # counter backwards with a later time: the device restarted
            else:
                fill = gap
        th = self._unwrap_angle(theta, t)
        parts = []
        if fill:
            c["frames_lost"] += fill
            c["loss_events"] += 1
            k = min(fill, self.max_fill)
            frac = np.arange(1, k + 1) / (k + 1)
            ft = self._last_t + frac * (t - self._last_t)
            fth = self._last_theta + frac * (th - self._last_theta)
            c["samples_filled"] += k
            parts.append(WheelSamples(ft, np.full(k, np.nan), fth, np.full(k, self._slip),
                                      np.ones(k, bool), np.full(k, np.nan)))
        elif self._last_t is not None and abs(th - self._last_theta) < 1.0:
            self._learn(np.array([t - self._last_t]), np.array([th - self._last_theta]))
        parts.append(WheelSamples(np.array([t]), np.array([az]), np.array([th]), np.array([self._slip]),
                                  np.zeros(1, bool), np.array([intake])))
        self._last_seq = seq
        self._last_t = t
        self._last_theta = th
        if intake == intake:
            self._last_intake = intake
        return WheelSamples.concatenate(parts)

    def _stuck_filter(self, s: WheelSamples) -> WheelSamples:
        """Hold back repeating ``az`` runs; NaN the ones that reach the threshold."""
        limit = self.stuck_samples
        n = len(s)
        if not limit or n == 0:
            self.c["samples_out"] += n
            return s
        az = s.az
        prev = np.concatenate([[np.nan if self._prev_az is None else self._prev_az], az[:-1]])
        repeat = (az == prev) & ~s.filled
        if not repeat.any() and not self._held and not self._stuck:
            self._prev_az = float(az[-1])
            self.c["samples_out"] += n
            return s
        # slow path, sample by sample (only while az repeats)
        rows = []  # (i, nan): sample i of s; ("held", nan, row): a held sample
        for i in range(n):
            a = float(az[i])
            rep = bool(repeat[i])
            if rep and not s.filled[i]:
                if self._stuck:
                    self.c["stuck_samples"] += 1
                    rows.append((i, True))
                    continue
                self._held.append(_held_row(s, i))
                if len(self._held) + 1 >= limit:  # the first of the run was already released
                    self._stuck = True
                    self.c["stuck_runs"] += 1
                    self.c["stuck_samples"] += len(self._held)
                    rows.extend(("held", True, h) for h in self._held)
                    self._held = []
                continue
            # the run (if any) is broken
            if self._held:
                rows.extend(("held", False, h) for h in self._held)
                self._held = []
            self._stuck = False
            rows.append((i, False))
            self._prev_az = a
        if repeat.any():
            self._prev_az = float(az[np.flatnonzero(~s.filled)[-1]]) if (~s.filled).any() else self._prev_az
        out = _assemble(s, rows)
        self.c["samples_out"] += len(out)
        return out

    def flush(self) -> WheelSamples:
        """Release held samples (end of stream): unchanged, as their run was too short."""
        rows = [("held", False, h) for h in self._held]
        self._held = []
        out = _assemble(WheelSamples.empty(), rows)
        self.c["samples_out"] += len(out)
        return out

    def counters(self) -> dict:
        c = dict(self.c)
        c["held"] = len(self._held)
        return c


def _held_row(s: WheelSamples, i: int) -> tuple:
    return (float(s.t[i]), float(s.az[i]), float(s.theta[i]), float(s.slip[i]), float(s.intake[i]))


def _assemble(s: WheelSamples, rows: list) -> WheelSamples:
    """Rows: ``(i, nan)`` a sample of ``s``; ``("held", nan, row)`` a held row."""
    if not rows:
        return WheelSamples.empty()
    m = len(rows)
    t = np.empty(m)
    az = np.empty(m)
    th = np.empty(m)
    sl = np.empty(m)
    filled = np.zeros(m, bool)
    intake = np.empty(m)
    for j, r in enumerate(rows):
        if r[0] == "held":
            _, nan, (rt, ra, rth, rsl, rin) = r
        else:
            i, nan = r
            rt, ra, rth, rsl, rin = s.t[i], s.az[i], s.theta[i], s.slip[i], s.intake[i]
            filled[j] = s.filled[i]
        t[j], az[j], th[j], sl[j], intake[j] = rt, (math.nan if nan else ra), rth, rsl, rin
    return WheelSamples(t, az, th, sl, filled, intake)
