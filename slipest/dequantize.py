"""A whole-count leg encoder's angle, interpolated between its count changes, online (pure computation).

A coarse encoder (a few hundred counts a revolution) reports the leg angle
in whole counts: the angle holds for tens of milliseconds, then steps by a
count. Cut into cycles on that staircase, the break-away angle and the leg
speed each cycle measures are off by up to half a count (0.012-0.025 rad at
128-256 counts), which moves the soil the estimator learns (development
draws: ``dphi`` intervals covering 53 %). For an encoder that rounds, the
true angle crossed the midpoint of two counts between the two samples where
the count changed; :class:`AngleDequantizer` puts a knot there (the
midpoint of the two samples' times, the midpoint of their angles) and
interpolates the samples of each count linearly between its two knots.
:func:`dequantize_log` does the same for a whole log (the diagnosis's
cycles): it detects on the whole log first, so the interpolation starts at
the log's first count change instead of after the detection's counts.

Online, a count's samples can only be interpolated once the next count
change has come, so they are **held** until then: the stream's samples come
out in order, each count's up to one count later (at 0.35 rad/s and 128
counts, 140 ms). A count held longer than :data:`MAX_HOLD` (a leg standing
still) is let through as reported, and interpolation resumes at the next
change.

**Detection.** The stream passes through untouched (the same arrays, no
delay) until the encoder is seen to count whole steps while the leg moves:
more than half of the last :data:`RUNS` counts lasting :data:`MIN_RUN`
samples or more (a count: from one count change to the next). A fine or
floating point angle changes every sample, and a leg standing still is one
long count among short ones, so neither starts it; once started it stays
on for the stream (:meth:`AngleDequantizer.reset` starts over). The first
:data:`RUNS` counts pass as reported.

Angles jumping by more than pi (and less than 3 pi) between consecutive
samples are taken as a wrap (the output is then unwrapped; :class:`slipest.segmentation.CycleSegmenter`
takes either). Samples with a non-finite angle keep it and keep their place;
so does a glitched angle, 3 pi or more from the previous valid one (a
corrupted value), unless :data:`~slipest.segmentation.JUMP_CONFIRM` come in a row: a new level
(a restart), from which the interpolation starts over.

Units: t [s], theta [rad]; az and the reference slip are carried through.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from slipest.segmentation import JUMP_CONFIRM

#: Counts (runs between count changes) the detection looks at [-].
RUNS = 16
#: Count length [samples] that more than half of the last RUNS counts must reach for whole steps.
MIN_RUN = 3
#: Longest a count is held [s] before its samples are let through as reported (a leg standing still).
MAX_HOLD = 0.5

# detection state (float64 vector): previous valid angle (unwrapped), have one, samples in the current count,
# counts recorded, ring position, active, counts in the ring lasting MIN_RUN samples or more, whole steps known
# beforehand (start at the first count change)
_PREV, _HAVE, _RUN, _NRING, _POS, _ACTIVE, _NLONG, _KNOWN = range(8)
_N_DETECT = 8
# interpolation state: previous valid sample's time, knot time and angle (the current count's start), the knot
# before it, knots known (0/1/2), stalled, the current count's first sample's time, unwrap offset [rad], samples
# let out interpolated
_PT, _KT, _KV, _KT0, _KV0, _NKNOT, _STALL, _T0, _WRAP, _NINT = range(_N_DETECT, _N_DETECT + 10)
# glitched angles in a row (a jump of 3 pi or more from the previous valid angle: not a wrap, not a count)
_JUMPS = _N_DETECT + 10
_N_STATE = _N_DETECT + 11
_JUMP = 3.0 * math.pi
_PLAIN, _GLITCH, _NEW_LEVEL = 0, 1, 2  # what _jump says of an angle


@numba.njit(cache=True)
def _unwrapped(state, theta):
    """``theta`` [rad] on the unwrapped scale of the previous valid angle (a jump beyond pi, and short of 3 pi, is
    a wrap: a wrapped angle never jumps further; a larger jump, a glitch or an unwrapped angle's outage, is
    left as it is)."""
    th = theta + state[_WRAP]
    if state[_HAVE] > 0.0:
        d = th - state[_PREV]
        if math.pi < d < 3.0 * math.pi:
            state[_WRAP] -= 2.0 * math.pi
            th -= 2.0 * math.pi
        elif -3.0 * math.pi < d < -math.pi:
            state[_WRAP] += 2.0 * math.pi
            th += 2.0 * math.pi
    return th


@numba.njit(cache=True)
def _jump(state, th):
    """What the angle ``th`` (unwrapped) is: ``_GLITCH`` when 3 pi or more from the previous valid angle, not yet
    :data:`~slipest.segmentation.JUMP_CONFIRM` in a row (counted in the state), ``_NEW_LEVEL`` for the one that
    makes that many, else ``_PLAIN`` (the count starts over)."""
    if state[_HAVE] > 0.0 and not abs(th - state[_PREV]) < _JUMP:
        state[_JUMPS] += 1.0
        if state[_JUMPS] < JUMP_CONFIRM:
            return _GLITCH
        state[_JUMPS] = 0.0
        return _NEW_LEVEL
    state[_JUMPS] = 0.0
    return _PLAIN


@numba.njit(cache=True)
def _observe(state, ring, t, theta):
    """Detection step on one sample (module docstring); True when the encoder is found to count whole steps at
    this sample (a count change: it starts the first interpolated count)."""
    if not math.isfinite(theta) or not math.isfinite(t):
        return False
    th = _unwrapped(state, theta)
    if _jump(state, th) == _GLITCH:
        return False
    started = False
    if state[_HAVE] > 0.0 and th == state[_PREV]:
        state[_RUN] += 1.0
    else:
        if state[_HAVE] > 0.0:
            if state[_RUN] > 0.0:
                pos = int(state[_POS])
                if state[_NRING] >= RUNS and ring[pos] >= MIN_RUN:
                    state[_NLONG] -= 1.0
                ring[pos] = state[_RUN]
                if state[_RUN] >= MIN_RUN:
                    state[_NLONG] += 1.0
                state[_POS] = (pos + 1) % RUNS
                state[_NRING] = min(state[_NRING] + 1.0, float(RUNS))
                if state[_KNOWN] > 0.0 or (state[_NRING] >= RUNS and 2.0 * state[_NLONG] > RUNS):
                    started = True
                    state[_ACTIVE] = 1.0
                    state[_KT] = 0.5 * (state[_PT] + t)
                    state[_KV] = 0.5 * (state[_PREV] + th)
                    state[_NKNOT] = 1.0
                    state[_STALL] = 0.0
                    state[_T0] = t
        state[_RUN] = 1.0
    state[_PREV] = th
    state[_PT] = t
    state[_HAVE] = 1.0
    return started


@numba.njit(cache=True)
def _observe_many(state, ring, t, theta):
    """:func:`_observe` over arrays: the index of the sample at which the encoder is found to count whole steps
    (-1: not in these samples; the samples after it are not looked at)."""
    for i in range(t.shape[0]):
        if _observe(state, ring, t[i], theta[i]):
            return i
    return -1


@numba.njit(cache=True)
def _interpolate(state, t, theta, out, start, stop):
    """Interpolation over buffers ``t, theta`` whose samples before ``start`` are held (looked at before; their
    angle as reported, unwrapped, in ``out``) and ``[start, stop)`` new: fills ``out`` and returns how many
    samples, from the buffers' first, are let out (their ``out`` final)."""
    released = 0
    for i in range(start, stop):
        ti = t[i]
        raw = theta[i]
        if not math.isfinite(raw) or not math.isfinite(ti):
            out[i] = raw
            if state[_STALL] > 0.0:
                released = i + 1
            continue
        th = _unwrapped(state, raw)
        jump = _jump(state, th)
        if jump == _GLITCH:  # kept as reported, and out of the interpolation, as a non-finite angle is
            out[i] = raw
            if state[_STALL] > 0.0:
                released = i + 1
            continue
        out[i] = th
        if jump == _NEW_LEVEL:  # let through, started over
            state[_STALL] = 1.0
            state[_PREV] = th
            state[_PT] = ti
            released = i + 1
            continue
        if th != state[_PREV]:  # a count change: the knot between the previous valid sample and this one
            kt = 0.5 * (state[_PT] + ti)
            kv = 0.5 * (state[_PREV] + th)
            if state[_STALL] == 0.0 and kt > state[_KT]:  # the held count, between its two knots
                slope = (kv - state[_KV]) / (kt - state[_KT])
                for j in range(released, i):
                    if math.isfinite(out[j]) and math.isfinite(t[j]) and abs(out[j] - state[_KV]) < _JUMP:
                        out[j] = state[_KV] + (t[j] - state[_KT]) * slope
                        state[_NINT] += 1.0
            # (else: a count let through, or no time between the knots: as reported)
            released = i
            state[_KT0] = state[_KT]
            state[_KV0] = state[_KV]
            state[_NKNOT] = 1.0 if state[_STALL] > 0.0 else min(state[_NKNOT] + 1.0, 2.0)
            state[_KT] = kt
            state[_KV] = kv
            state[_STALL] = 0.0
            state[_T0] = ti
        elif state[_STALL] > 0.0:
            released = i + 1
        elif ti - state[_T0] > MAX_HOLD:  # a leg standing still: its count let through as reported
            state[_STALL] = 1.0
            released = i + 1
        state[_PREV] = th
        state[_PT] = ti
    return released


class AngleDequantizer:
    """Streaming interpolation of a whole-count encoder's angle (see the module docstring).

    :meth:`feed` takes consecutive samples ``(t [s], az, theta [rad], ref)`` (arrays of one length; ``ref``
    optional) and returns the samples it lets out, in order, with their angle interpolated once the
    encoder is found to count whole steps; :meth:`flush` lets out what it holds at the end of a stream.
    Before that the very arrays given are returned (no copy, no delay).

    ``counts_known``: the encoder is known to count whole steps (a whole log was looked at first,
    :func:`dequantize_log`): interpolation starts at the first count change, without detection.
    """

    def __init__(self, counts_known: bool = False):
        self.counts_known = bool(counts_known)
        self._done = 0  # samples interpolated in the streams before this one
        self._state = np.zeros(_N_STATE)
        self.reset()

    def reset(self) -> None:
        """Forget the stream (detection included; :attr:`interpolated` kept)."""
        self._done = self.interpolated
        self._state = np.zeros(_N_STATE)
        self._state[_KNOWN] = 1.0 if self.counts_known else 0.0
        self._ring = np.zeros(RUNS)
        self._held: tuple | None = None  # (t, az, theta, ref) arrays of the held samples
        self._held_out = np.zeros(0)  # their angles as reported, unwrapped
        self.step = math.nan  # the count [rad], once found

    @property
    def interpolated(self) -> int:
        """Samples let out with an interpolated (or, at a stream's end, extrapolated) angle so far [-]."""
        return self._done + int(self._state[_NINT])

    @property
    def active(self) -> bool:
        """True once the encoder was found to count whole steps (the samples since are interpolated)."""
        return self._state[_ACTIVE] > 0.0

    @property
    def holding(self) -> int:
        """Samples held, waiting for the next count change [-]."""
        return 0 if self._held is None else int(self._held[0].size)

    def push(self, t: float, az: float, theta: float, ref: float = math.nan):
        """One sample: None while the stream passes through (use the sample as it is), else the samples let
        out, as :meth:`feed` returns them (the same, sample by sample, as :meth:`feed` on arrays)."""
        if self._state[_ACTIVE] == 0.0:
            if not _observe(self._state, self._ring, float(t), float(theta)):
                return None
            started = True
        else:
            started = False
        return self._active_feed(np.array([t], dtype=np.float64), np.array([az], dtype=np.float64),
                                 np.array([theta], dtype=np.float64), np.array([ref], dtype=np.float64), started)

    def feed(self, t, az, theta, ref=None):
        """The samples let out after these ones: ``(t, az, theta, ref)`` arrays, possibly empty; while the
        stream passes through, the arrays given (``ref`` as given, None included), else ``ref`` an array (NaN
        where none was given)."""
        t = np.asarray(t, dtype=np.float64)
        theta = np.asarray(theta, dtype=np.float64)
        if not self.active:
            i = _observe_many(self._state, self._ring, t, theta)
            if i < 0:
                return t, az, theta, ref
            az = np.asarray(az, dtype=np.float64)
            ref = np.full(t.size, np.nan) if ref is None else np.asarray(ref, dtype=np.float64)
            rest = self._active_feed(t[i:], az[i:], theta[i:], ref[i:], first_held=True)
            return tuple(np.concatenate([a[:i], b]) for a, b in zip((t, az, theta, ref), rest))
        return self._active_feed(t, az, theta, ref, False)

    def _active_feed(self, t, az, theta, ref, first_held: bool):
        """Interpolation over held + new samples; the first new sample is the count change that started it when
        ``first_held``."""
        ref = np.full(t.size, np.nan) if ref is None else np.asarray(ref, dtype=np.float64)
        new = (t, np.asarray(az, dtype=np.float64), theta, ref)
        n_old = 0 if self._held is None else self._held[0].size
        buf = new if self._held is None else tuple(np.concatenate([h, x]) for h, x in zip(self._held, new))
        out = np.empty(buf[0].size)
        out[:n_old] = self._held_out
        start = n_old
        if first_held:  # the change that started it (detection looked at it): the current count's first sample
            s = self._state
            out[n_old] = s[_PREV]
            self.step = 2.0 * abs(s[_PREV] - s[_KV])
            start = n_old + 1
        released = _interpolate(self._state, buf[0], buf[2], out, start, buf[0].size)
        self._held = tuple(a[released:].copy() for a in buf) if released < buf[0].size else None
        self._held_out = out[released:].copy()
        return buf[0][:released], buf[1][:released], out[:released], buf[3][:released]

    def flush(self):
        """The held samples, at the end of a stream: the last count's angles extrapolated along the previous
        two knots (as reported when there is only one); then the stream starts over."""
        held = self._held
        s = self._state
        if held is None:
            self.reset()
            return None
        t, az, theta, ref = held
        out = self._held_out
        ok = np.isfinite(out) & np.isfinite(t)
        if s[_NKNOT] >= 2.0 and s[_KT] > s[_KT0] and s[_STALL] == 0.0:
            slope = (s[_KV] - s[_KV0]) / (s[_KT] - s[_KT0])
            out[ok] = s[_KV] + (t[ok] - s[_KT]) * slope
            s[_NINT] += np.count_nonzero(ok)
        self.reset()
        return t, az, out, ref


def counts_whole_steps(t, theta) -> bool:
    """True when the encoder of a whole log is seen to count whole steps while the leg moves somewhere in it
    (the stream's detection rule, module docstring). ``t`` [s], ``theta`` [rad]: arrays of one length."""
    t = np.asarray(t, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    if t.shape != theta.shape:
        raise ValueError(f"t and theta must have the same length ({t.size} and {theta.size})")
    return _observe_many(np.zeros(_N_STATE), np.zeros(RUNS), t, theta) >= 0


def dequantize_log(t, theta) -> np.ndarray:
    """The angle [rad] of a whole log, unwrapped (a jump below -pi between valid samples is a wrap), and
    interpolated between its count changes when its encoder counts whole steps (:func:`counts_whole_steps`).

    The same interpolation as the stream's (:class:`AngleDequantizer`), started at the log's first count
    change; a whole log also knows its first count's end, so the samples before the first change are
    extrapolated back along the first two knots, as those after the last change are forward along the last
    two. A count held longer than :data:`MAX_HOLD` (a leg standing still, the first count included) is as
    reported. Non-finite angles keep their place. ``t`` [s], ``theta`` [rad]: arrays of one length (the
    array itself returned when there is nothing to change)."""
    t = np.asarray(t, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    if t.shape != theta.shape:
        raise ValueError(f"t and theta must have the same length ({t.size} and {theta.size})")
    ok = np.isfinite(t) & np.isfinite(theta)
    if np.any(np.diff(theta[ok]) < -math.pi):  # a wrapped angle ([-pi, pi) or [0, 2 pi)), unwrapped
        theta = theta.copy()
        theta[ok] = np.unwrap(theta[ok])
    if not counts_whole_steps(t, theta):
        return theta
    deq = AngleDequantizer(counts_known=True)
    parts = [deq.feed(t, np.zeros(t.size), theta)[2]]
    held = deq.flush()
    if held is not None:
        parts.append(held[2])
    out = np.concatenate(parts)
    ok = np.flatnonzero(ok)
    raw = theta[ok]  # as reported, unwrapped
    changes = np.flatnonzero(np.diff(raw) != 0) + 1  # positions in ``ok`` of the samples that start a count
    if changes.size >= 2 and t[ok[changes[0]]] - t[ok[0]] <= MAX_HOLD:
        # the first two knots (a count change: midpoint of the two samples' times and of their angles)
        kt = 0.5 * (t[ok[changes[:2] - 1]] + t[ok[changes[:2]]])
        kv = 0.5 * (raw[changes[:2] - 1] + raw[changes[:2]])
        if kt[1] > kt[0]:
            first = ok[: changes[0]]
            out[first] = kv[0] + (t[first] - kt[0]) * (kv[1] - kv[0]) / (kt[1] - kt[0])
    return out


__all__ = ["AngleDequantizer", "MAX_HOLD", "MIN_RUN", "RUNS", "counts_whole_steps", "dequantize_log"]
