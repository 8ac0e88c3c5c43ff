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
  is emitted with quality ``"partial"`` when its window was not observed from
  its start (the first sample was already at or past ``m_k + w0``).
* **NaN / inf.** A sample with a non-finite ``t`` or ``theta`` cannot be
  placed: it is dropped and counted, and flags the current cycle ``"nan"``
  unless that cycle's window is already over. A NaN ``az`` in the window flags
  ``"nan"``; ``|az| >= full_scale`` (default 16 g) or ``az`` equal to one of
  ``clip_values`` flags ``"saturated"``.
* **Gaps.** Over the window plus its two neighbour samples (the one before the
  first window sample and the one after the last), a time step larger than
  ``max_gap`` or a theta step larger than ``max_dtheta`` flags ``"gap"``.
  ``max_gap=None`` (default) means ``gap_factor`` (5) times the median time
  step of that same span; ``max_dtheta=None`` means a tenth of the window
  width.
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
* The last, unclosed cycle of a stream is never emitted.

A cycle may have several flags (``LegCycle.flags``); ``quality`` is the first
of them in the order of :data:`QUALITY_PRIORITY`, or ``"ok"``. Only ``"ok"``
cycles may be estimated from.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass

import numba
import numpy as np

from .units import G

__all__ = ["QUALITIES", "QUALITY_PRIORITY", "LegCycle", "CycleSegmenter"]

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
_INIT, _FORWARD, _REVERSE = 0, 1, 2
_CLOSE_EPS = 1e-6  # rad; pre-check margin before the exact floor() test
_BLOCK = 16384  # samples per vectorised step in push_many
# bits of _window_checks' result
_F_TIME, _F_GAP, _F_STOPPED, _F_NAN, _F_SATURATED = 1, 2, 4, 8, 16


@numba.njit(cache=True)
def _window_checks(t, az, ph, has_pre, pre_t, pre_ph, has_post, post_t, post_ph, max_gap, gap_factor, max_dtheta,
                   stop_dtheta, stop_time, full_scale, clip_values):
    """The sample checks of a closed window, one pass each (the cycle-close cost), as bits ``_F_*``.

    ``t`` [s], ``az`` [m/s^2], ``ph`` [rad]: the window's samples (at least
    one); the span checked for time order, gaps and stops is the window plus
    its neighbours ``(pre_t, pre_ph)`` and ``(post_t, post_ph)`` when
    ``has_pre`` / ``has_post``. ``max_gap`` [s]: NaN adapts it
    (``gap_factor`` times the median positive time step of the span).
    ``max_dtheta``, ``stop_dtheta`` [rad], ``stop_time`` [s], ``full_scale``
    [m/s^2], ``clip_values`` [m/s^2]: see :class:`CycleSegmenter`.
    """
    n = t.size
    a0 = 1 if has_pre else 0
    m = n + a0 + (1 if has_post else 0)
    ts = np.empty(m)
    ps = np.empty(m)
    ts[a0:a0 + n] = t
    ps[a0:a0 + n] = ph
    if has_pre:
        ts[0] = pre_t
        ps[0] = pre_ph
    if has_post:
        ts[m - 1] = post_t
        ps[m - 1] = post_ph
    bits = 0
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
        elif npos:
            if not math.isnan(max_gap):
                if pmax > max_gap:
                    bits |= _F_GAP
            # adaptive: gap_factor times the median step; no step above gap_factor times the
            # smallest (the usual even sampling) decides it without the median
            elif pmax > gap_factor * pmin and pmax > gap_factor * np.median(pos[:npos]):
                bits |= _F_GAP
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
    for i in range(n):
        a = az[i]
        if math.isnan(a):
            bits |= _F_NAN
        elif abs(a) >= full_scale:
            bits |= _F_SATURATED
        else:
            for c in clip_values:
                if a == c:
                    bits |= _F_SATURATED
    return bits


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
    ``flags``: every reason found.
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
            and np.array_equal(self.t, other.t, equal_nan=True)
            and np.array_equal(self.az, other.az, equal_nan=True)
            and np.array_equal(self.theta_phase, other.theta_phase, equal_nan=True)
        )

    __hash__ = None

    def __repr__(self):
        return (
            f"LegCycle(k={self.k}, t_start={self.t_start:.6f}, t_end={self.t_end:.6f}, "
            f"n_samples={self.n_samples}, quality={self.quality!r}, flags={self.flags})"
        )


class CycleSegmenter:
    """Cut a stream of ``(t, az, theta)`` samples into leg cycles.

    Parameters (SI):
      n_legs: legs of the wheel-leg (``nL``).
      window: ``(w0, w1)`` [rad], the feature window as phases relative to
        the midstance, ``-pi/nL <= w0 < w1 <= pi/nL``; default ``(0, pi/nL)``.
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
    """

    def __init__(
        self,
        n_legs: int = 4,
        window: tuple[float, float] | None = None,
        *,
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
        # derived constants
        self._h = h
        self._P = 2.0 * h
        self._invP = 1.0 / self._P
        self._close_ph = h - _CLOSE_EPS
        self._w0, self._w1 = w0, w1
        self._wlo = _TWO_PI - self.wrap_tol
        self._whi = _TWO_PI + self.wrap_tol
        self._unwrap = theta_wrap == "auto"
        self.reset()
        # load the compiled window checks now, not on the first cycle's close
        one = np.zeros(1)
        _window_checks(one, one, one, False, 0.0, 0.0, False, 0.0, 0.0, math.nan, self.gap_factor, self.max_dtheta,
                       self.stop_dtheta, self.stop_time, self.full_scale, self.clip_values)

    # ------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the stream (buffers keep their current capacity)."""
        self._mode = _INIT
        self._have_raw = False
        self._last_raw = 0.0
        self._nwrap = 0
        self._last_t = -math.inf  # last valid sample's time, any mode
        self._prev_t = 0.0
        self._prev_th = 0.0
        self._has_prev = False
        self._tmax = 0.0
        self._tmin = 0.0
        self._k = 0
        self._mk = 0.0
        self._t_open = 0.0
        self._synced_here = False
        self._sync_ph = 0.0
        if not hasattr(self, "_cap"):
            self._alloc(self.initial_capacity)
        self._clear_cycle()
        self._c_seen = 0
        self._c_invalid = 0
        self._c_reverse = 0
        self._c_overflow = 0
        self._c_back = 0
        self._c_dup = 0
        self._c_wraps = 0
        self._c_reversals = 0
        self._c_skipped = 0
        self._c_syncs = 0
        self._c_cycles = dict.fromkeys(QUALITIES, 0)

    def _alloc(self, cap: int) -> None:
        old = None
        if hasattr(self, "_cap"):
            old = (self._bt_np, self._baz_np, self._bph_np, self._n)
        self._cap = cap
        self._bt = array("d", bytes(8 * cap))
        self._baz = array("d", bytes(8 * cap))
        self._bph = array("d", bytes(8 * cap))
        self._bt_np = np.frombuffer(self._bt, dtype=np.float64)
        self._baz_np = np.frombuffer(self._baz, dtype=np.float64)
        self._bph_np = np.frombuffer(self._bph, dtype=np.float64)
        if old is not None:
            n = old[3]
            self._bt_np[:n] = old[0][:n]
            self._baz_np[:n] = old[1][:n]
            self._bph_np[:n] = old[2][:n]

    def _clear_cycle(self) -> None:
        self._n = 0  # samples stored
        self._nwin = 0  # samples the window had (stored + overflow)
        self._overflow = False
        self._has_pre = False
        self._pre_t = 0.0
        self._pre_ph = 0.0
        self._has_post = False
        self._post_t = 0.0
        self._post_ph = 0.0
        self._nanflag = False

    # ------------------------------------------------------------------
    @property
    def buffer_capacity(self) -> int:
        """Current capacity (samples) of each window buffer."""
        return self._cap

    @property
    def counters(self) -> dict:
        """Counts so far: ``samples_seen``; ``samples_dropped`` = invalid
        (non-finite t or theta) + reverse (while driving backwards) + overflow
        (past ``max_samples`` in a window); ``time_backwards``,
        ``time_duplicate``; ``wraps``; ``reversals``; ``resyncs`` (stream start
        included); ``cycles_skipped`` (cycles jumped over without a sample);
        ``cycles_emitted`` and ``cycles_<quality>`` for every quality."""
        c = {
            "samples_seen": self._c_seen,
            "samples_dropped": self._c_invalid + self._c_reverse + self._c_overflow,
            "samples_invalid": self._c_invalid,
            "samples_reverse": self._c_reverse,
            "samples_overflow": self._c_overflow,
            "time_backwards": self._c_back,
            "time_duplicate": self._c_dup,
            "wraps": self._c_wraps,
            "reversals": self._c_reversals,
            "resyncs": self._c_syncs,
            "cycles_skipped": self._c_skipped,
            "cycles_emitted": sum(self._c_cycles.values()),
        }
        for q in QUALITIES:
            c[f"cycles_{q}"] = self._c_cycles[q]
        return c

    # ------------------------------------------------------------------
    def _sync(self, t: float, th: float) -> None:
        """Start a cycle on sample (t, th) with no history."""
        self._mode = _FORWARD
        self._tmax = th
        self._k = k = math.floor((th + self._h) * self._invP)
        self._mk = k * self._P
        self._t_open = t
        self._synced_here = True
        self._sync_ph = th - self._mk
        self._has_prev = False
        self._c_syncs += 1
        self._clear_cycle()

    def _grow(self) -> bool:
        if self._cap >= self.max_samples:
            return False
        self._alloc(min(2 * self._cap, self.max_samples))
        return True

    def _emit(self, t_end: float, reason: str | None) -> LegCycle:
        """Build the LegCycle of the current cycle (state is not changed)."""
        n = self._n
        w0 = self._w0
        flags = []
        if reason is not None:
            flags.append(reason)
        if self._overflow:
            flags.append("too_long")
            t = az = ph = np.empty(0)
        else:
            t = self._bt_np[:n].copy()
            az = self._baz_np[:n].copy()
            ph = self._bph_np[:n].copy()
        partial = self._synced_here and self._sync_ph >= w0
        if partial:
            flags.append("partial")
        if not self._overflow:
            if n:
                bits = _window_checks(t, az, ph, self._has_pre, self._pre_t, self._pre_ph, self._has_post, self._post_t,
                                      self._post_ph, math.nan if self.max_gap is None else self.max_gap,
                                      self.gap_factor, self.max_dtheta, self.stop_dtheta, self.stop_time,
                                      self.full_scale, self.clip_values)
                if bits & _F_TIME:
                    flags.append("time")
                if bits & _F_GAP:
                    flags.append("gap")
                if bits & _F_STOPPED:
                    flags.append("stopped")
                if self._nanflag or bits & _F_NAN:
                    flags.append("nan")
                if bits & _F_SATURATED:
                    flags.append("saturated")
            else:
                if not partial and reason is None:
                    flags.append("gap")
                if self._nanflag:
                    flags.append("nan")
        if self._nwin < self.min_samples:
            flags.append("sparse")
        flags = tuple(f for f in QUALITY_PRIORITY if f in flags)
        quality = flags[0] if flags else "ok"
        self._c_cycles[quality] += 1
        for arr_ in (t, az, ph):
            arr_.flags.writeable = False
        return LegCycle(self._k, self._t_open, t_end, t, az, ph, self._nwin, quality, flags)

    def _close(self, t: float, th: float, knew: int) -> LegCycle:
        """Close the current cycle on its closing sample (t, th); open knew."""
        if not self._has_post:
            self._has_post = True
            self._post_t = t
            self._post_ph = th - self._mk
        cyc = self._emit(t, None)
        self._c_skipped += knew - self._k - 1
        self._k = knew
        self._mk = knew * self._P
        self._t_open = t
        self._synced_here = False
        self._clear_cycle()
        return cyc

    def _reverse(self, t: float, th: float) -> LegCycle:
        cyc = self._emit(t, "reverse")
        self._mode = _REVERSE
        self._tmin = th
        self._c_reversals += 1
        self._c_reverse += 1
        self._clear_cycle()
        return cyc

    # ------------------------------------------------------------------
    def push(self, t: float, az: float, theta: float) -> list:
        """Add one sample: ``t`` [s], ``az`` [m/s^2], ``theta`` [rad].

        Returns the cycles it completed (usually none, at most one)."""
        self._c_seen += 1
        t = float(t)
        theta = float(theta)
        if not (t - t == 0.0 and theta - theta == 0.0):
            self._c_invalid += 1
            if self._mode == _FORWARD and self._tmax - self._mk < self._w1:
                self._nanflag = True
            return []
        az = float(az)
        if self._unwrap:
            if self._have_raw:
                d = theta - self._last_raw
                if d < -self._wlo:
                    if d > -self._whi:
                        self._nwrap += 1
                        self._c_wraps += 1
                elif d > self._wlo and d < self._whi:
                    self._nwrap -= 1
                    self._c_wraps += 1
            else:
                self._have_raw = True
            self._last_raw = theta
            th = theta + self._nwrap * _TWO_PI
        else:
            th = theta
        if t <= self._last_t:
            if t < self._last_t:
                self._c_back += 1
            else:
                self._c_dup += 1
        self._last_t = t
        out = []
        mode = self._mode
        if mode != _FORWARD:
            if mode == _REVERSE:
                if th < self._tmin:
                    self._tmin = th
                    self._c_reverse += 1
                    return out
                if not th > self._tmin + self.reverse_tol:
                    self._c_reverse += 1
                    return out
            self._sync(t, th)
        else:
            tmax = self._tmax
            if th < tmax - self.reverse_tol:
                out.append(self._reverse(t, th))
                return out
            if th > tmax:
                self._tmax = tmax = th
            if tmax - self._mk >= self._close_ph:
                knew = math.floor((tmax + self._h) * self._invP)
                if knew > self._k:
                    out.append(self._close(t, th, knew))
        mk = self._mk
        ph = self._tmax - mk
        if self._w0 <= ph < self._w1:
            n = self._n
            if self._nwin == 0 and self._has_prev:
                self._has_pre = True
                self._pre_t = self._prev_t
                self._pre_ph = self._prev_th - mk
            self._nwin += 1
            if n < self._cap or self._grow():
                self._bt[n] = t
                self._baz[n] = az
                self._bph[n] = th - mk
                self._n = n + 1
            else:
                self._overflow = True
                self._c_overflow += 1
        elif ph >= self._w1 and not self._has_post:
            self._has_post = True
            self._post_t = t
            self._post_ph = th - mk
        self._prev_t = t
        self._prev_th = th
        self._has_prev = True
        return out

    # ------------------------------------------------------------------
    def push_many(self, t, az, theta) -> list:
        """Add a chunk of samples (equal-length 1-D arrays: ``t`` [s], ``az``
        [m/s^2], ``theta`` [rad]). Returns the cycles completed, in order;
        exactly what :meth:`push` on each sample would have returned."""
        t = np.asarray(t, dtype=np.float64)
        az = np.asarray(az, dtype=np.float64)
        raw = np.asarray(theta, dtype=np.float64)
        if t.ndim != 1 or az.shape != t.shape or raw.shape != t.shape:
            raise ValueError(
                f"push_many() needs equal-length 1-D arrays, got t{t.shape}, az{az.shape}, theta{raw.shape}"
            )
        n = t.shape[0]
        out: list = []
        if n == 0:
            return out
        self._c_seen += n
        valid = np.isfinite(t) & np.isfinite(raw)
        nan_after = None
        if not valid.all():
            nvalid_before = np.cumsum(valid) - valid  # valid samples before each sample
            inv = ~valid
            self._c_invalid += int(inv.sum())
            prev_valid = nvalid_before[inv] - 1  # index (in valid arrays) preceding each invalid sample
            t, az, raw = t[valid], az[valid], raw[valid]
            m = t.shape[0]
            if (prev_valid < 0).any() and self._mode == _FORWARD and self._tmax - self._mk < self._w1:
                self._nanflag = True
            nan_after = np.zeros(m, dtype=bool)
            nan_after[prev_valid[prev_valid >= 0]] = True
        m = t.shape[0]
        if m == 0:
            return out
        # unwrap
        if self._unwrap:
            first = raw[0] if not self._have_raw else self._last_raw
            d = np.diff(raw, prepend=first)
            fwd = (d < -self._wlo) & (d > -self._whi)
            bwd = (d > self._wlo) & (d < self._whi)
            corr = fwd.astype(np.int64) - bwd
            nz = int(np.count_nonzero(corr))
            if nz:
                nw = np.cumsum(corr)
                nw += self._nwrap
                th = raw + nw * _TWO_PI
                self._nwrap = int(nw[-1])
                self._c_wraps += nz
            else:
                th = raw + self._nwrap * _TWO_PI
            self._have_raw = True
            self._last_raw = float(raw[-1])
        else:
            th = raw
        # time order
        dt = np.diff(t, prepend=self._last_t)
        self._c_back += int(np.count_nonzero(dt < 0))
        self._c_dup += int(np.count_nonzero(dt == 0))
        self._last_t = float(t[-1])
        p = 0
        rtol = self.reverse_tol
        while p < m:
            mode = self._mode
            if mode != _FORWARD:
                if mode == _REVERSE:
                    seg = th[p : p + _BLOCK]
                    rmin = np.minimum.accumulate(seg)
                    np.minimum(rmin, self._tmin, out=rmin)
                    rprev = np.empty_like(rmin)
                    rprev[0] = self._tmin
                    rprev[1:] = rmin[:-1]
                    hit = np.flatnonzero(seg > rprev + rtol)
                    if hit.size == 0:
                        self._tmin = float(rmin[-1])
                        self._c_reverse += seg.size
                        p += seg.size
                        continue
                    s = p + int(hit[0])
                    self._c_reverse += int(hit[0])
                else:
                    s = p
                self._sync(float(t[s]), float(th[s]))
                p = s
            q = min(m, p + _BLOCK)
            seg = th[p:q]
            rm = np.maximum.accumulate(seg)
            np.maximum(rm, self._tmax, out=rm)
            rprev = np.empty_like(rm)
            rprev[0] = self._tmax
            rprev[1:] = rm[:-1]
            rev = np.flatnonzero(seg < rprev - rtol)
            stop = int(rev[0]) if rev.size else seg.size
            if stop:
                self._forward(t, az, th, rm[:stop], p, nan_after, out)
            if rev.size:
                r = p + stop
                out.append(self._reverse(float(t[r]), float(th[r])))
                p = r + 1
            else:
                p = q
        return out

    def _forward(self, t, az, th, rm, p, nan_after, out) -> None:
        """Forward samples p .. p+len(rm)-1 (no reversal among them), rm being
        their running maximum of theta."""
        L = rm.shape[0]
        h = self._h
        w0, w1 = self._w0, self._w1
        k0 = self._k
        # cycle index of every sample; only computed where a close is possible
        if rm[-1] - self._mk >= self._close_ph:
            K = np.floor((rm + h) * self._invP).astype(np.int64)
            np.maximum(K, k0, out=K)
            bounds = np.flatnonzero(np.diff(K, prepend=k0) > 0)
        else:
            K = None
            bounds = np.empty(0, dtype=np.intp)
        starts = [0] + bounds.tolist()
        ends = bounds.tolist() + [L]
        for j, (a, b) in enumerate(zip(starts, ends)):
            if j > 0:
                c = p + a
                out.append(self._close(float(t[c]), float(th[c]), int(K[a])))
            mk = self._mk
            ph = rm[a:b] - mk
            i0 = int(np.searchsorted(ph, w0, side="left"))
            i1 = int(np.searchsorted(ph, w1, side="left"))
            if nan_after is not None and i1 > 0 and nan_after[p + a : p + a + i1].any():
                self._nanflag = True
            if i1 > i0:
                g0 = p + a + i0  # first window sample of this segment
                if self._nwin == 0:
                    # predecessor: the previous valid sample, if any since sync
                    gi = g0 - 1
                    if gi >= p:
                        self._has_pre = True
                        self._pre_t = float(t[gi])
                        self._pre_ph = float(th[gi]) - mk
                    elif self._has_prev:
                        self._has_pre = True
                        self._pre_t = self._prev_t
                        self._pre_ph = self._prev_th - mk
                cnt = i1 - i0
                self._nwin += cnt
                n = self._n
                room = self.max_samples - n
                take = cnt if cnt <= room else room
                while n + take > self._cap:
                    self._grow()
                if take:
                    g1 = g0 + take
                    self._bt_np[n : n + take] = t[g0:g1]
                    self._baz_np[n : n + take] = az[g0:g1]
                    np.subtract(th[g0:g1], mk, out=self._bph_np[n : n + take])
                    self._n = n + take
                if take < cnt:
                    self._overflow = True
                    self._c_overflow += cnt - take
            if i1 < b - a and not self._has_post:
                g = p + a + i1
                self._has_post = True
                self._post_t = float(t[g])
                self._post_ph = float(th[g]) - mk
        last = p + L - 1
        self._tmax = float(rm[-1])
        self._prev_t = float(t[last])
        self._prev_th = float(th[last])
        self._has_prev = True
