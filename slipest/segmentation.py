"""Streaming leg-cycle segmentation of an IMU + wheel-leg angle stream.

Pure computation: no files, no ports, no clocks. Feed samples one at a time
(:meth:`CycleSegmenter.push`) or in chunks (:meth:`CycleSegmenter.push_many`);
both paths give identical cycles.

Conventions (SI throughout)
---------------------------
``t`` [s] sample time; ``az`` [m/s^2] vertical specific force as the IMU
reports it (gravity included, +9.81 at rest); ``theta`` [rad] wheel-leg
rotation angle, 0 at a midstance, increasing when driving forward. With
``nL`` legs the midstances are ``m_k = 2*pi*k/nL`` and leg cycle ``k`` (one
leg's stance) is the phase ``theta - m_k`` in ``[-pi/nL, pi/nL)``. The
features are computed on a *window* of phases ``[w0, w1)`` relative to the
midstance, by default the propulsive half ``[0, pi/nL)``. A cycle closes, and
is emitted, when the first sample with phase ``>= pi/nL`` arrives; that
sample opens the next cycle.

How the stream is interpreted
-----------------------------
* **Wrapping.** ``theta_wrap="auto"`` (default) unwraps internally: a jump
  between consecutive valid samples within ``wrap_tol`` of +-2*pi is a wrap
  (so wrapped angles in [-pi, pi) or [0, 2*pi) and unwrapped angles give the
  same cycles). ``"none"`` takes theta as already unwrapped (a 2*pi jump is
  then a real jump, flagged as a gap).
* **Progress is the running maximum of theta.** Entering and leaving the
  window and closing the cycle happen when the running maximum crosses
  ``m_k + w0``, ``m_k + w1`` and ``m_k + pi/nL``, so encoder jitter cannot
  make a sample leave and re-enter the window. ``theta_phase`` stores the
  measured angle minus ``m_k``.
* **Reverse.** A sample more than ``reverse_tol`` below the running maximum
  means the rover drives backwards: the current cycle is emitted at once with
  quality ``"reverse"`` and the samples are dropped (counted) until theta
  rises ``reverse_tol`` above its running minimum; the segmenter then
  re-synchronises on that sample (its first cycle may be ``"partial"``).
* **Partial.** The first cycle after the stream starts (or re-synchronises)
  on a sample (a sample less than 1e-4 rad before a cycle's start, as an
  angle rounded in a log or a CAN frame (0.1 mrad) may be, starts that cycle)
  is emitted with quality ``"partial"`` when its window was not observed from
  its start (the first sample was already at or past ``m_k + complete_from``,
  by default ``m_k + w0``).
* **Missing samples and holes.** A sample with a non-finite ``t`` or
  ``theta`` cannot be placed: it is dropped and counted.
* **Theta jumps.** A sample whose (unwrapped) angle lies further from the
  last one taken than ``max_speed`` (50 rad/s, tens of times any
  wheel-leg's) times the time between them, plus 0.5 rad, is a glitch of
  the encoder or the link (a corrupted value, 1e3 or 3e38 rad): dropped and
  counted (``samples_jump``), so its cycle loses one sample, not its
  numbering. Five such samples in a row that agree with each other are a
  new level (a restart, a re-zeroed encoder): taken from the fifth on, as
  any jump is (a ``"gap"``, or ``"reverse"`` backwards). A window sample
  whose ``az`` is NaN, at or beyond ``full_scale`` (inf included) (default 16 g) or
  equal to one of ``clip_values`` is *unusable*: kept in the arrays, never
  to be estimated from. Over the window plus its two neighbour samples (the
  one before the first window sample and the one after the last), a *hole*
  is the time between two consecutive usable samples; a hole longer than
  ``max_gap`` flags the cycle ``"nan"`` when a NaN ``az`` lies in it,
  ``"saturated"`` when a saturated one does, else ``"gap"``; shorter holes
  are left for the estimator to bridge. ``max_gap=None`` (default) means
  ``gap_factor`` (5) times the median time step of the span (5 ms at 1 kHz:
  up to four samples in a row may be missing). ``n_missing`` counts the
  unusable samples and the rows missing from the span (a time step of
  ``m`` median steps is ``m - 1`` missing rows, dropped samples included).
  A theta step larger than ``max_dtheta`` flags ``"gap"`` (``None``: a tenth
  of the window width). A step that large which lands in a later cycle lands
  there as a first sample does: less than 1e-4 rad before a cycle's start
  (a device's float32 angle after a restart), it starts that cycle, and the
  cycle it would otherwise open with this one sample at its very end is
  counted skipped (``cycles_skipped``), not emitted.
* **Time.** A timestamp not after the previous one (backwards or duplicated)
  is counted; a window containing one is flagged ``"time"``.
* **Stops.** No cycle can be emitted while theta does not advance. A window
  in which theta advanced less than ``stop_dtheta`` during more than
  ``stop_time`` is flagged ``"stopped"``.
* **Bounded memory.** The window buffers start at ``initial_capacity`` and
  grow up to ``max_samples``; a window with more samples is flagged
  ``"too_long"``, its extra samples dropped (counted) and it is emitted with
  empty arrays. A rover stopped inside a window forever therefore holds at
  most ``max_samples`` samples.
* ``"sparse"``: fewer than ``min_samples`` samples in the window.
* **End of stream.** The last cycle has no closing sample: :meth:`CycleSegmenter.finish`
  says the stream ended and emits it, ``"ok"`` (after the usual checks)
  when its window was observed to within ``max_dtheta`` of its end, else
  ``"partial"``. Pushing on after :meth:`~CycleSegmenter.finish` starts a
  new stream (the counters go on).

A cycle may have several flags (``LegCycle.flags``); ``quality`` is the first
of them in the order of :data:`QUALITY_PRIORITY`, or ``"ok"``. Only ``"ok"``
cycles may be estimated from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from .units import G

__all__ = ["JUMP_CONFIRM", "QUALITIES", "QUALITY_PRIORITY", "LegCycle", "CycleSegmenter", "usable"]

#: Flags in the order used to pick a cycle's ``quality`` (first present wins).
QUALITY_PRIORITY = (
    "reverse",
    "too_long",
    "partial",
    "time",
    "gap",
    "stopped",
    "nan",
    "saturated",
    "sparse",
)
#: Every possible ``LegCycle.quality``.
QUALITIES = ("ok",) + QUALITY_PRIORITY

_TWO_PI = 2.0 * math.pi
_INIT, _FORWARD, _REVERSE = 0, 1, 2  # modes; _INIT (a fresh state) until the first valid sample
_CLOSE_EPS = 1e-6  # rad; pre-check margin before the exact floor() test
_SYNC_EPS = 1e-4  # rad; a first sample this close before a cycle's start starts that cycle (a rounded angle)
_JUMP_SLACK = 0.5  # rad; a theta step this much beyond max_speed times the time step is a jump
#: Jumped samples in a row that agree with each other make a new level (a restart, a re-zeroed encoder), taken from
#: the last of them (here and in :mod:`slipest.dequantize`'s interpolation).
JUMP_CONFIRM = 5
# a cycle's flags as bits, bit b standing for QUALITY_PRIORITY[b]
_F_REVERSE, _F_TOO_LONG, _F_PARTIAL, _F_TIME, _F_GAP, _F_STOPPED, _F_NAN, _F_SATURATED, _F_SPARSE = (
    1 << b for b in range(len(QUALITY_PRIORITY)))
#: flags tuple (in priority order) of every combination of bits
_FLAGS = tuple(tuple(f for b, f in enumerate(QUALITY_PRIORITY) if bits >> b & 1)
               for bits in range(1 << len(QUALITY_PRIORITY)))
# what _advance stopped for
_DONE, _EMITTED, _FULL = 0, 1, 2


@numba.njit(cache=True, inline="always")
def _hole_flags(why):
    """The flags of a hole made by unusable samples of the kinds ``why`` (bit 0: NaN ``az``, bit 1: saturated)."""
    return (_F_NAN if why & 1 else 0) | (_F_SATURATED if why & 2 else 0)


@numba.njit(cache=True)
def _window_checks(t, az, ph, has_pre, pre_t, pre_ph, has_post, post_t, post_ph, max_gap, gap_factor, max_dtheta,
                   stop_dtheta, stop_time, full_scale, clip_values):
    """The sample checks of a closed window, one pass each (the cycle-close cost): ``(bits, n_missing)``,
    the flags as bits ``_F_*`` and the samples missing or unusable (see "Missing samples and holes" in
    the module docstring).

    ``t`` [s], ``az`` [m/s^2], ``ph`` [rad]: the window's samples (at least
    one); the span checked for time order, holes and stops is the window plus
    its neighbours ``(pre_t, pre_ph)`` and ``(post_t, post_ph)`` when
    ``has_pre`` / ``has_post`` (taken as usable). ``max_gap`` [s]: NaN adapts
    it (``gap_factor`` times the median positive time step of the span).
    ``max_dtheta``, ``stop_dtheta`` [rad], ``stop_time`` [s], ``full_scale``
    [m/s^2], ``clip_values`` [m/s^2]: see :class:`CycleSegmenter`.
    """
    n = t.size
    a0 = 1 if has_pre else 0
    m = n + a0 + (1 if has_post else 0)
    ts = np.empty(m)
    ps = np.empty(m)
    bad = np.zeros(m, np.int64)  # 0 usable, 1 NaN az, 2 saturated (inf included)
    ts[a0:a0 + n] = t
    ps[a0:a0 + n] = ph
    if has_pre:
        ts[0] = pre_t
        ps[0] = pre_ph
    if has_post:
        ts[m - 1] = post_t
        ps[m - 1] = post_ph
    n_bad = 0
    for i in range(n):
        a = az[i]
        if a != a:
            bad[a0 + i] = 1
        elif abs(a) >= full_scale:
            bad[a0 + i] = 2
        else:
            for c in clip_values:
                if a == c:
                    bad[a0 + i] = 2
        if bad[a0 + i]:
            n_bad += 1
    bits = 0
    n_missing = n_bad
    if m >= 2:
        pos = np.empty(m - 1)
        npos = 0
        pmax = 0.0
        pmin = np.inf
        jump = False
        for i in range(1, m):
            d = ts[i] - ts[i - 1]
            if d > 0:
                pos[npos] = d
                npos += 1
                if d > pmax:
                    pmax = d
                if d < pmin:
                    pmin = d
            else:
                bits |= _F_TIME
            if abs(ps[i] - ps[i - 1]) > max_dtheta:
                jump = True
        if jump:
            bits |= _F_GAP
        # the median step is needed only when some step or some unusable sample may make a hole or a missing row
        # (steps all alike are no hole unless a given max_gap is shorter than them)
        if npos and (n_bad or pmax > 1.5 * pmin or pmax > max_gap):
            med = np.median(pos[:npos])
            limit = max_gap if not math.isnan(max_gap) else gap_factor * med
            for i in range(1, m):  # rows missing from the stream
                d = ts[i] - ts[i - 1]
                if d > 1.5 * med:
                    n_missing += int(round(d / med)) - 1
            last = -1  # the last usable sample
            why = 0  # the kinds (bits 1 << (bad - 1)) of the unusable samples since it
            for i in range(m):
                if bad[i]:
                    why |= 1 << (bad[i] - 1)
                    continue
                if last >= 0 and ts[i] - ts[last] > limit:
                    bits |= _hole_flags(why) if why else _F_GAP
                last = i
                why = 0
            if last >= 0 and why:  # unusable samples to the end of the span: a hole from the last usable one
                if ts[m - 1] - ts[last] > limit:
                    bits |= _hole_flags(why)
            elif last < 0:  # nothing usable
                bits |= _hole_flags(why)
        elif n_bad == n:  # nothing usable in the window
            for i in range(n):
                bits |= _hole_flags(1 << (bad[a0 + i] - 1))
        # stopped: from a sample, theta's running maximum takes more than stop_time to rise by stop_dtheta
        thr = np.empty(m)
        run = -np.inf
        for i in range(m):
            if ps[i] > run:
                run = ps[i]
            thr[i] = run
        jj = 0
        for i in range(m):
            v = thr[i] + stop_dtheta
            while jj < m and thr[jj] < v:  # first jj with thr[jj] >= v
                jj += 1
            if ts[jj - 1] - ts[i] > stop_time:
                bits |= _F_STOPPED
                break
    elif n_bad:  # one sample, unusable
        bits |= _hole_flags(1 << (bad[a0] - 1))
    return bits, n_missing


_f8, _i8, _b1 = np.float64, np.int64, np.bool_
#: A segmenter's whole state, one record read and written by the compiled :func:`_advance`.
_STATE = np.dtype([
    # settings (see CycleSegmenter; h = pi/nL, P = 2h, max_gap NaN: adaptive)
    ("h", _f8), ("P", _f8), ("invP", _f8), ("close_ph", _f8), ("w0", _f8), ("w1", _f8), ("complete_from", _f8),
    ("unwrap", _b1),
    ("wlo", _f8), ("whi", _f8), ("reverse_tol", _f8), ("max_gap", _f8), ("gap_factor", _f8), ("max_dtheta", _f8),
    ("stop_dtheta", _f8), ("stop_time", _f8), ("full_scale", _f8), ("min_samples", _i8), ("max_samples", _i8),
    ("max_speed", _f8),
    # the stream: mode, unwrapping, time order, progress (running max / min of theta), current cycle k
    ("mode", _i8), ("resume", _b1), ("th_resume", _f8), ("have_raw", _b1), ("last_raw", _f8), ("nwrap", _i8),
    ("last_t", _f8), ("has_prev", _b1), ("prev_t", _f8), ("prev_th", _f8), ("tmax", _f8), ("tmin", _f8),
    ("k", _i8), ("mk", _f8), ("t_open", _f8), ("synced_here", _b1), ("sync_ph", _f8),
    # the last angle taken (theta jumps are judged from it) and a run of jumped samples that agree (a new level)
    ("have_ok", _b1), ("ok_t", _f8), ("ok_th", _f8), ("cand_n", _i8), ("cand_t", _f8), ("cand_th", _f8),
    # the open cycle's window: samples stored (n) and seen (nwin), its neighbour samples, NaN seen
    ("n", _i8), ("nwin", _i8), ("overflow", _b1), ("has_pre", _b1), ("pre_t", _f8), ("pre_ph", _f8),
    ("has_post", _b1), ("post_t", _f8), ("post_ph", _f8),
    # counters
    ("samples_seen", _i8), ("samples_invalid", _i8), ("samples_reverse", _i8), ("samples_overflow", _i8),
    ("time_backwards", _i8), ("time_duplicate", _i8), ("wraps", _i8), ("reversals", _i8), ("resyncs", _i8),
    ("cycles_skipped", _i8), ("samples_jump", _i8),
    # the cycle just emitted (its window is buf[:, :e_n] until _advance runs again)
    ("e_k", _i8), ("e_t_open", _f8), ("e_t_end", _f8), ("e_n", _i8), ("e_nwin", _i8), ("e_bits", _i8),
    ("e_missing", _i8),
])

#: What :meth:`CycleSegmenter.resync` keeps of the state: the counters, the unwrapping, the last time.
_KEPT_ON_RESYNC = ("have_raw", "last_raw", "nwrap", "last_t", "samples_seen", "samples_invalid", "samples_reverse",
                   "samples_overflow", "time_backwards", "time_duplicate", "wraps", "reversals", "resyncs",
                   "cycles_skipped", "samples_jump", "have_ok", "ok_t", "ok_th")


@numba.njit(cache=True)
def _open_cycle(s):
    """Empty the window of the cycle now open."""
    s.n = 0
    s.nwin = 0
    s.overflow = False
    s.has_pre = False
    s.has_post = False


@numba.njit(cache=True)
def _emit(s, buf, clip_values, t_end, reason):
    """Describe the open cycle, ending at ``t_end`` [s], in ``s.e_*``; ``reason``: flags to add (0,
    ``_F_REVERSE``, or ``_F_PARTIAL`` for a window cut short by the end of the stream)."""
    n = s.n
    bits = reason
    missing = 0
    partial = s.synced_here and s.sync_ph >= s.complete_from
    if partial:
        bits |= _F_PARTIAL
    if s.overflow:
        bits |= _F_TOO_LONG
        n = 0
    else:
        if n:
            wbits, missing = _window_checks(buf[0, :n], buf[1, :n], buf[2, :n], s.has_pre, s.pre_t, s.pre_ph,
                                            s.has_post, s.post_t, s.post_ph, s.max_gap, s.gap_factor, s.max_dtheta,
                                            s.stop_dtheta, s.stop_time, s.full_scale, clip_values)
            bits |= wbits
        elif not partial and reason == 0:
            bits |= _F_GAP
    if s.nwin < s.min_samples:
        bits |= _F_SPARSE
    s.e_k = s.k
    s.e_t_open = s.t_open
    s.e_t_end = t_end
    s.e_n = n
    s.e_nwin = s.nwin
    s.e_bits = bits
    s.e_missing = missing if n and not s.overflow else 0


@numba.njit(cache=True)
def _advance(st, buf, t, az, theta, i, clip_values):
    """Run the segmenter ``st[0]`` (a :data:`_STATE` record) over samples ``i, i+1, ...`` of ``t`` [s],
    ``az`` [m/s^2], ``theta`` [rad], ``buf`` (3 x capacity) holding the window's t, az, theta_phase.

    Returns ``(i, what)``: ``_DONE`` (``i == t.size``), or it stopped early and is to be called again from ``i``
    after the caller has taken the cycle just emitted (``_EMITTED``: ``s.e_*`` and ``buf[:, :s.e_n]``) or given
    it a larger buffer (``_FULL``)."""
    s = st[0]
    n_in = t.size
    while i < n_in:
        ti = t[i]
        if s.resume:  # the window step of sample i is still to do
            s.resume = False
            th = s.th_resume
        else:
            s.samples_seen += 1
            raw = theta[i]
            if not (ti - ti == 0.0 and raw - raw == 0.0):
                s.samples_invalid += 1
                i += 1
                continue
            th = raw
            nwrap = s.nwrap
            if s.unwrap:
                if s.have_raw:
                    d = raw - s.last_raw
                    if d < -s.wlo:
                        if d > -s.whi:
                            nwrap += 1
                    elif s.wlo < d < s.whi:
                        nwrap -= 1
                th = raw + nwrap * _TWO_PI
            if s.have_ok and not abs(th - s.ok_th) <= s.max_speed * max(ti - s.ok_t, 0.0) + _JUMP_SLACK:
                # further from the last angle taken than the leg can turn: a glitch, unless it starts a run of
                # JUMP_CONFIRM that agree (a restart, a re-zeroed encoder: a new level, taken from then on)
                if s.cand_n > 0 and abs(th - s.cand_th) <= s.max_speed * max(ti - s.cand_t, 0.0) + _JUMP_SLACK:
                    s.cand_n += 1
                else:
                    s.cand_n = 1
                s.cand_t = ti
                s.cand_th = th
                if s.cand_n < JUMP_CONFIRM:
                    s.samples_jump += 1
                    i += 1
                    continue
            s.cand_n = 0
            s.have_ok = True
            s.ok_t = ti
            s.ok_th = th
            if s.unwrap:
                if nwrap != s.nwrap:
                    s.wraps += 1
                s.nwrap = nwrap
                s.have_raw = True
                s.last_raw = raw
            if ti < s.last_t:
                s.time_backwards += 1
            elif ti == s.last_t:
                s.time_duplicate += 1
            s.last_t = ti
            if s.mode == _FORWARD:
                if th < s.tmax - s.reverse_tol:
                    _emit(s, buf, clip_values, ti, _F_REVERSE)
                    s.mode = _REVERSE
                    s.tmin = th
                    s.reversals += 1
                    s.samples_reverse += 1
                    _open_cycle(s)
                    return i + 1, _EMITTED
                if th > s.tmax:
                    s.tmax = th
                if s.tmax - s.mk >= s.close_ph:
                    knew = math.floor((s.tmax + s.h) * s.invP)
                    if knew > s.k and s.has_prev and th - s.prev_th > s.max_dtheta:
                        # a jump lands as a first sample does: a hair before a cycle's start, in that cycle
                        knew = math.floor((s.tmax + s.h + _SYNC_EPS) * s.invP)
                    if knew > s.k:
                        if not s.has_post:
                            s.has_post = True
                            s.post_t = ti
                            s.post_ph = th - s.mk
                        _emit(s, buf, clip_values, ti, 0)
                        s.cycles_skipped += knew - s.k - 1
                        s.k = knew
                        s.mk = knew * s.P
                        s.t_open = ti
                        s.synced_here = False
                        _open_cycle(s)
                        s.resume = True
                        s.th_resume = th
                        return i, _EMITTED
            else:
                if s.mode == _REVERSE:
                    if th < s.tmin:
                        s.tmin = th
                    if not th > s.tmin + s.reverse_tol:
                        s.samples_reverse += 1
                        i += 1
                        continue
                # start a cycle on this sample with no history
                s.mode = _FORWARD
                s.tmax = th
                s.k = math.floor((th + s.h + _SYNC_EPS) * s.invP)  # a hair before a cycle's start: that cycle
                s.mk = s.k * s.P
                s.t_open = ti
                s.synced_here = True
                s.sync_ph = th - s.mk
                s.has_prev = False
                s.resyncs += 1
                _open_cycle(s)
        # the window step: store the sample if the running maximum is inside the window
        mk = s.mk
        ph = s.tmax - mk
        if s.w0 <= ph < s.w1:
            m = s.n
            cap = buf.shape[1]
            if m == cap and cap < s.max_samples:
                s.resume = True
                s.th_resume = th
                return i, _FULL
            if s.nwin == 0 and s.has_prev:
                s.has_pre = True
                s.pre_t = s.prev_t
                s.pre_ph = s.prev_th - mk
            s.nwin += 1
            if m < cap:
                buf[0, m] = ti
                buf[1, m] = az[i]
                buf[2, m] = th - mk
                s.n = m + 1
            else:
                s.overflow = True
                s.samples_overflow += 1
        elif ph >= s.w1 and not s.has_post:
            s.has_post = True
            s.post_t = ti
            s.post_ph = th - mk
        s.prev_t = ti
        s.prev_th = th
        s.has_prev = True
        i += 1
    return i, _DONE


@numba.njit(cache=True)
def _finish(st, buf, clip_values):
    """End the stream of ``st[0]``: describe its open cycle in ``s.e_*`` (True), if it has one with window
    samples, and go back to waiting for a first sample."""
    s = st[0]
    emitted = False
    if s.mode == _FORWARD and s.nwin > 0:
        cut = s.w1 - (s.tmax - s.mk) > s.max_dtheta
        _emit(s, buf, clip_values, s.last_t, _F_PARTIAL if cut else 0)
        emitted = True
    s.mode = _INIT
    s.resume = False
    s.has_prev = False
    s.have_raw = False
    s.have_ok = False
    s.cand_n = 0
    s.nwrap = 0
    s.last_t = -math.inf
    _open_cycle(s)
    return emitted


def usable(az, full_scale: float = 16 * G, clip_values=()) -> np.ndarray:
    """Mask of the samples whose ``az`` [m/s^2] may be estimated from: finite, below ``full_scale`` in
    magnitude, not one of ``clip_values`` (the segmenter's own rule; give it the segmenter's settings)."""
    az = np.asarray(az, dtype=float)
    ok = np.isfinite(az) & (np.abs(az) < full_scale)
    for c in clip_values:
        ok &= az != c
    return ok


@dataclass(frozen=True, eq=False)
class LegCycle:
    """One closed leg cycle.

    ``k``: index of the midstance ``m_k = 2*pi*k/nL`` (of the unwrapped
    angle). ``t_start`` [s]: time of the sample that opened the cycle (the
    previous cycle's closing sample, or the sample the segmenter synchronised
    on); ``t_end`` [s]: time of the closing sample (for ``"reverse"``: of the
    sample that revealed the reversal). ``t`` [s], ``az`` [m/s^2] and
    ``theta_phase`` [rad, angle minus ``m_k``] are the samples of the feature
    window, in arrival order (read-only arrays). ``n_samples``: samples the
    window had (equal to ``len(t)`` except for ``"too_long"``, whose arrays
    are empty). ``quality``: ``"ok"`` or why it must not be estimated;
    ``flags``: every reason found. ``n_missing``: samples of the window
    missing or unusable (NaN/inf or saturated ``az``, rows absent from the
    stream) in holes short enough to bridge; an ``"ok"`` cycle's unusable
    samples are still in the arrays and must be left out of its features
    (:meth:`CycleSegmenter.usable`).
    """

    k: int
    t_start: float
    t_end: float
    t: np.ndarray
    az: np.ndarray
    theta_phase: np.ndarray
    n_samples: int
    quality: str
    flags: tuple
    n_missing: int = 0

    @property
    def ok(self) -> bool:
        """True when the cycle may be used for estimation."""
        return self.quality == "ok"

    def __eq__(self, other):
        if not isinstance(other, LegCycle):
            return NotImplemented
        return (
            self.k == other.k
            and self.t_start == other.t_start
            and self.t_end == other.t_end
            and self.n_samples == other.n_samples
            and self.quality == other.quality
            and self.flags == other.flags
            and self.n_missing == other.n_missing
            and np.array_equal(self.t, other.t, equal_nan=True)
            and np.array_equal(self.az, other.az, equal_nan=True)
            and np.array_equal(self.theta_phase, other.theta_phase, equal_nan=True)
        )

    __hash__ = None

    def __repr__(self):
        return (
            f"LegCycle(k={self.k}, t_start={self.t_start:.6f}, t_end={self.t_end:.6f}, "
            f"n_samples={self.n_samples}, n_missing={self.n_missing}, quality={self.quality!r}, flags={self.flags})"
        )


class CycleSegmenter:
    """Cut a stream of ``(t, az, theta)`` samples into leg cycles.

    Parameters (SI):
      n_legs: legs of the wheel-leg (``nL``).
      window: ``(w0, w1)`` [rad], the window a cycle hands over, as phases
        relative to the midstance, ``-pi/nL <= w0 < w1 <= pi/nL``; default
        ``(0, pi/nL)`` (the feature window).
      complete_from: [rad] the first cycle after the stream starts (or
        re-synchronises) is ``"partial"`` when its first sample came at or
        after this phase; default ``w0`` (a window that takes the rigid half
        too can say that only the feature window, from 0, must be whole).
      max_gap: [s] largest allowed time step in the window span; None: adapt
        (``gap_factor`` times the span's median step).
      gap_factor: see ``max_gap``.
      max_dtheta: [rad] largest allowed theta step in the window span; None:
        ``(w1 - w0) / 10``.
      theta_wrap: ``"auto"`` (unwrap jumps of about 2*pi) or ``"none"``.
      wrap_tol: [rad] how close to 2*pi a jump must be to count as a wrap.
      reverse_tol: [rad] how far theta may go back (encoder jitter) before it
        counts as driving backwards; also the rise needed to resume.
      stop_time: [s], stop_dtheta: [rad] see "stopped" in the module doc.
      full_scale: [m/s^2] ``|az|`` at or above it is saturated (default 16 g).
      clip_values: [m/s^2] exact values the IMU reports when clipping.
      min_samples: fewer window samples than this flags ``"sparse"``.
      max_samples: most samples a window may hold (memory bound).
      initial_capacity: first size of the window buffers.
      max_speed: [rad/s] see "Theta jumps" in the module doc.
    """

    def __init__(
        self,
        n_legs: int = 4,
        window: tuple[float, float] | None = None,
        *,
        complete_from: float | None = None,
        max_gap: float | None = None,
        gap_factor: float = 5.0,
        max_dtheta: float | None = None,
        theta_wrap: str = "auto",
        wrap_tol: float = 1.0,
        reverse_tol: float = 0.01,
        stop_time: float = 0.5,
        stop_dtheta: float = 0.01,
        full_scale: float = 16.0 * G,
        clip_values=(),
        min_samples: int = 8,
        max_samples: int = 65536,
        initial_capacity: int = 4096,
        max_speed: float = 50.0,
    ):
        if not isinstance(n_legs, (int, np.integer)) or n_legs < 1:
            raise ValueError(f"n_legs must be an int >= 1, got {n_legs!r}")
        self.n_legs = int(n_legs)
        h = math.pi / self.n_legs
        if window is None:
            window = (0.0, h)
        w0, w1 = (float(w) for w in window)
        if not (-h - 1e-12 <= w0 < w1 <= h + 1e-12):
            raise ValueError(
                f"window {window!r} must satisfy -pi/n_legs <= w0 < w1 <= pi/n_legs (pi/n_legs = {h:.6f} rad)"
            )
        self.window = (w0, w1)
        self.complete_from = w0 if complete_from is None else float(complete_from)
        if not w0 <= self.complete_from < w1:
            raise ValueError(f"complete_from={complete_from!r} rad must lie in the window [{w0:.6f}, {w1:.6f})")
        if max_gap is not None and not max_gap > 0:
            raise ValueError(f"max_gap must be > 0 s or None, got {max_gap!r}")
        if not gap_factor > 1:
            raise ValueError(f"gap_factor must be > 1, got {gap_factor!r}")
        if max_dtheta is None:
            max_dtheta = (w1 - w0) / 10.0
        if not max_dtheta > 0:
            raise ValueError(f"max_dtheta must be > 0 rad, got {max_dtheta!r}")
        if theta_wrap not in ("auto", "none"):
            raise ValueError(f"theta_wrap must be 'auto' or 'none', got {theta_wrap!r}")
        if not 0 < wrap_tol < math.pi:
            raise ValueError(f"wrap_tol must be in (0, pi) rad, got {wrap_tol!r}")
        if not reverse_tol > 0:
            raise ValueError(f"reverse_tol must be > 0 rad, got {reverse_tol!r}")
        if not (stop_time > 0 and stop_dtheta > 0):
            raise ValueError("stop_time [s] and stop_dtheta [rad] must be > 0")
        if not full_scale > 0:
            raise ValueError(f"full_scale must be > 0 m/s^2, got {full_scale!r}")
        if min_samples < 0:
            raise ValueError(f"min_samples must be >= 0, got {min_samples!r}")
        if max_samples < 1 or initial_capacity < 1:
            raise ValueError("max_samples and initial_capacity must be >= 1")
        if not max_speed > 0:
            raise ValueError(f"max_speed must be > 0 rad/s, got {max_speed!r}")
        self.max_speed = float(max_speed)
        self.max_gap = None if max_gap is None else float(max_gap)
        self.gap_factor = float(gap_factor)
        self.max_dtheta = float(max_dtheta)
        self.theta_wrap = theta_wrap
        self.wrap_tol = float(wrap_tol)
        self.reverse_tol = float(reverse_tol)
        self.stop_time = float(stop_time)
        self.stop_dtheta = float(stop_dtheta)
        self.full_scale = float(full_scale)
        self.clip_values = np.array(sorted(float(c) for c in clip_values), dtype=np.float64)
        self.min_samples = int(min_samples)
        self.max_samples = int(max_samples)
        self.initial_capacity = int(min(initial_capacity, max_samples))
        self._fresh = np.zeros(1, _STATE)  # the state of a new stream
        for name, value in dict(
            h=h, P=2.0 * h, invP=1.0 / (2.0 * h), close_ph=h - _CLOSE_EPS, w0=w0, w1=w1,
            complete_from=self.complete_from,
            unwrap=theta_wrap == "auto", wlo=_TWO_PI - self.wrap_tol, whi=_TWO_PI + self.wrap_tol,
            reverse_tol=self.reverse_tol, max_gap=math.nan if max_gap is None else self.max_gap,
            gap_factor=self.gap_factor, max_dtheta=self.max_dtheta, stop_dtheta=self.stop_dtheta,
            stop_time=self.stop_time, full_scale=self.full_scale, min_samples=self.min_samples,
            max_samples=self.max_samples, last_t=-math.inf, max_speed=self.max_speed,
        ).items():
            self._fresh[name] = value
        self._buf = np.empty((3, self.initial_capacity))
        one = np.zeros(3)
        self._one = one
        self._one_t, self._one_az, self._one_theta = one[0:1], one[1:2], one[2:3]
        self.reset()
        # load the compiled segmenter now, not on the first sample
        _advance(self._fresh.copy(), self._buf, one[:0], one[:0], one[:0], 0, self.clip_values)

    # ------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the stream (buffers keep their current capacity)."""
        self._st = self._fresh.copy()
        self._c_cycles = dict.fromkeys(QUALITIES, 0)

    def resync(self) -> None:
        """Start the stream again from the next sample, as after a restart, keeping the counts, the
        unwrapping of theta and the last time seen: for a caller that re-times theta (the open cycle is
        dropped; the next sample synchronises, its first cycle may be ``"partial"``)."""
        old = self._st[0]
        self._st = self._fresh.copy()
        for name in _KEPT_ON_RESYNC:
            self._st[0][name] = old[name]

    def snapshot(self) -> tuple:
        """The segmenter's state now (the open window's samples copied), for :meth:`restore`."""
        n = int(self._st[0]["n"])
        return self._st.copy(), dict(self._c_cycles), self._buf[:, :n].copy()

    def restore(self, snap: tuple) -> None:
        """Go back to the state of a :meth:`snapshot` (the samples pushed since are forgotten)."""
        st, counts, window = snap
        self._buf[:, :window.shape[1]] = window  # (the buffer only grows: the window fits)
        self._st = st.copy()
        self._c_cycles = dict(counts)

    def usable(self, az) -> np.ndarray:
        """Mask of the samples of a cycle's ``az`` [m/s^2] that may be estimated from (:func:`usable` with
        this segmenter's ``full_scale`` and ``clip_values``)."""
        return usable(az, self.full_scale, self.clip_values)

    def open_window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The samples the open cycle's window holds so far: ``(t [s], az [m/s^2], theta_phase [rad])``
        (views, read them before the next push)."""
        n = int(self._st[0]["n"])
        return self._buf[0, :n], self._buf[1, :n], self._buf[2, :n]

    @property
    def buffer_capacity(self) -> int:
        """Current capacity (samples) of each window buffer."""
        return self._buf.shape[1]

    @property
    def counters(self) -> dict:
        """Counts so far: ``samples_seen``; ``samples_dropped`` = invalid
        (non-finite t or theta) + reverse (while driving backwards) + overflow
        (past ``max_samples`` in a window) + jump (theta jumps); ``time_backwards``,
        ``time_duplicate``; ``wraps``; ``reversals``; ``resyncs`` (stream start
        included); ``cycles_skipped`` (cycles jumped over without a sample);
        ``cycles_emitted`` and ``cycles_<quality>`` for every quality."""
        s = self._st[0]
        dropped = ("samples_invalid", "samples_reverse", "samples_overflow", "samples_jump")
        c = {"samples_seen": int(s["samples_seen"]), "samples_dropped": sum(int(s[k]) for k in dropped)}
        for k in dropped + ("time_backwards", "time_duplicate", "wraps", "reversals", "resyncs", "cycles_skipped"):
            c[k] = int(s[k])
        c["cycles_emitted"] = sum(self._c_cycles.values())
        for q in QUALITIES:
            c[f"cycles_{q}"] = self._c_cycles[q]
        return c

    # ------------------------------------------------------------------
    def push(self, t: float, az: float, theta: float) -> list:
        """Add one sample: ``t`` [s], ``az`` [m/s^2], ``theta`` [rad].

        Returns the cycles it completed (usually none, at most one)."""
        one = self._one
        one[0] = t
        one[1] = az
        one[2] = theta
        return self._run(self._one_t, self._one_az, self._one_theta)

    def push_many(self, t, az, theta) -> list:
        """Add a chunk of samples (equal-length 1-D arrays: ``t`` [s], ``az``
        [m/s^2], ``theta`` [rad]). Returns the cycles completed, in order;
        exactly what :meth:`push` on each sample would have returned."""
        t = np.ascontiguousarray(t, dtype=np.float64)
        az = np.ascontiguousarray(az, dtype=np.float64)
        theta = np.ascontiguousarray(theta, dtype=np.float64)
        if t.ndim != 1 or az.shape != t.shape or theta.shape != t.shape:
            raise ValueError(
                f"push_many() needs equal-length 1-D arrays, got t{t.shape}, az{az.shape}, theta{theta.shape}"
            )
        return self._run(t, az, theta)

    def finish(self) -> list:
        """Say the stream ended: the cycles this completes (the open one, if its window has samples; see
        "End of stream" in the module docstring). The next sample pushed starts a new stream."""
        if _finish(self._st, self._buf, self.clip_values):
            return [self._cycle()]
        return []

    def _run(self, t, az, theta) -> list:
        """Feed contiguous float64 arrays to the compiled segmenter; the cycles they closed."""
        out = []
        i = 0
        while True:
            i, what = _advance(self._st, self._buf, t, az, theta, i, self.clip_values)
            if what == _DONE:
                return out
            if what == _FULL:
                cap = min(2 * self._buf.shape[1], self.max_samples)
                buf = np.empty((3, cap))
                n = int(self._st[0]["n"])
                buf[:, :n] = self._buf[:, :n]
                self._buf = buf
            else:
                out.append(self._cycle())

    def _cycle(self) -> LegCycle:
        """The LegCycle of the cycle _advance just emitted."""
        s = self._st[0]
        flags = _FLAGS[int(s["e_bits"])]
        quality = flags[0] if flags else "ok"
        self._c_cycles[quality] += 1
        window = self._buf[:, : int(s["e_n"])].copy()
        window.flags.writeable = False
        t, az, ph = window
        return LegCycle(int(s["e_k"]), float(s["e_t_open"]), float(s["e_t_end"]), t, az, ph, int(s["e_nwin"]),
                        quality, flags, int(s["e_missing"]))
