"""The IMU's timing against the leg-angle encoder, read from the step at each leg swap (pure computation).

At a leg swap (phase ``pi/nL`` of one cycle, ``-pi/nL`` of the next) the
stance leg hands the hub over to the next leg: the hub's vertical
acceleration jumps from where the stance's stick-slip left it to the rigid
level of the new leg, within one sample (the stick-slip model, thesis Eqs.
5.10-5.14). The encoder says when the swap happens; the IMU shows when it
happened. The two agree on a rover whose encoder zero and clocks are right.
An encoder zero offset, or a time skew between the IMU's and the encoder's
time stamps, moves the IMU's step away from the encoder's swap by the same
amount on every cycle, and the estimates then come out biased with tight
intervals (an angle offset of 0.12-0.18 rad: slip 0.09 low, 95 % intervals
covering about 57 %; docs/estimator.md).

:func:`swap_step` finds the step in the samples around one swap;
:func:`swap_summary` reads every swap of a whole log (the diagnosis's
report); :class:`SwapTiming` follows the steps of consecutive cycles and decides
when the IMU and the encoder disagree by more than :data:`TOLERANCE`
(consistently over :data:`MIN_STEPS` steps): it then gives the angle to
take off ``theta`` (the offset times the leg speed) so that they agree
again. A cycle without a step that stands out (no stick-slip at the end of
the stance, or an IMU whose bandwidth smooths the step) gives no measure.

Units: t [s], az [m/s^2], theta and phases [rad], leg speed [rad/s].
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass

import numba
import numpy as np

#: How far from the encoder's swap a step is looked for, each side [rad of leg angle] (at most
#: :data:`MAX_REACH_FRACTION` of ``pi/nL``).
SEARCH_REACH = 0.35
MAX_REACH_FRACTION = 0.45
#: A step stands out when its jump exceeds this many standard deviations of the sample-to-sample noise
#: and this much [m/s^2] (a noiseless log) ...
STEP_SIGMAS = 8.0
STEP_FLOOR = 0.3
#: ... and this many times the median jump of the samples near it (the signal's own slope) [-].
STEP_LOCAL = 6.0
#: Samples each side of a step whose jumps give its local median (the step's neighbours excluded) [-].
LOCAL_SAMPLES = 8
#: After a swap's step ``az`` is at the new leg's rigid level: the median over this time after it [s] ...
POST_TIME = 0.015
#: ... within this [m/s^2] or this share of the jump [-], whichever is larger.
LEVEL_TOLERANCE = 0.5
LEVEL_SHARE = 0.15
#: Jumps tried per swap, largest first [-].
MAX_CANDIDATES = 8
#: Rigid-half phases (fractions of ``pi/nL``) whose median ``az`` is the rigid level: the end of the rigid
#: half, which an IMU lagging by up to 0.6 of it leaves clear of the previous stance.
LEVEL_SPAN = (-0.4, -0.05)
#: IMU-encoder disagreement [s] above which the angle is corrected. Clean logs measure 0 ms (no step of 1375
#: beyond 12.5 ms, 200 Hz-2 kHz); re-timed by 20 ms they lose 0.004-0.006 of slip RMSE, one log 0.02
#: (docs/estimator.md, "The IMU's timing against the encoder").
TOLERANCE = 0.012
#: Consistent steps needed before a correction (and kept in memory, the most recent) [-].
MIN_STEPS = 5
MEMORY = 9
#: How the IMU settles after a swap: the mean of ``az`` from :data:`SETTLE_SPAN` [s] after the encoder's
#: swap, less the rigid level, over the step (the stance's last :data:`PRE_TIME` [s] less the rigid level):
#: 0 for an IMU that follows the hub, about 0.5-1 through a low-pass at 3-4 Hz (0.37 for a first-order
#: one at 5 Hz, 0.16 at 10 Hz, 0.05 at 20 Hz), negative for a ringing mount.
SETTLE_SPAN = (0.010, 0.060)
PRE_TIME = 0.015
#: Steps counted for the settling: larger than this many noise standard deviations [-] and this [m/s^2].
SETTLE_MIN_SIGMAS = 10.0
SETTLE_FLOOR = 0.5
#: The IMU is *sluggish* (a low-pass the model does not know) when the median settling of the recent steps
#: (at least :data:`MIN_STEPS`, the last :data:`MEMORY`) exceeds this [-].
SLUGGISH = 0.12
#: Variance factor on the likelihood of a cycle while the IMU is sluggish [-] (docs/estimator.md).
SLUGGISH_WIDENING = 9.0


@numba.njit(cache=True)
def jump_sigma(d: np.ndarray) -> float:
    """Robust standard deviation of the sample-to-sample jumps ``d`` of ``az`` [m/s^2] (1.4826 times their
    median absolute value: the noise's jumps, the signal's few large ones left out); NaN for none."""
    if d.size == 0:
        return math.nan
    return 1.4826 * np.median(np.abs(d))


@numba.njit(cache=True)
def _swap_step(t, az, t_swap, reach_s, level, sigma):
    n = t.size
    d = az[1:] - az[:-1]
    if not sigma >= 0.0:
        sigma = jump_sigma(d)
    thr = max(STEP_SIGMAS * sigma, STEP_FLOOR)
    cand = np.empty(n - 1, np.int64)
    m = 0
    for j in range(n - 1):
        if abs(0.5 * (t[j] + t[j + 1]) - t_swap) <= reach_s and abs(d[j]) > thr:
            cand[m] = j
            m += 1
    if m == 0:
        return math.nan, math.nan
    cand = cand[:m]
    cand = cand[np.argsort(-np.abs(d[cand]))]
    post_n = max(2, int(round(POST_TIME / max((t[n - 1] - t[0]) / (n - 1), 1e-9))))  # mean sample period
    near = np.empty(2 * LOCAL_SAMPLES)
    for c in range(min(m, MAX_CANDIDATES)):
        j = cand[c]
        jump = abs(d[j])
        q = 0
        for i in range(max(0, j - LOCAL_SAMPLES - 1), max(0, j - 1)):
            near[q] = abs(d[i])
            q += 1
        for i in range(j + 2, min(n - 1, j + 2 + LOCAL_SAMPLES)):
            near[q] = abs(d[i])
            q += 1
        if q == 0 or not jump > STEP_LOCAL * np.median(near[:q]):
            continue
        post = az[j + 1:min(n, j + 1 + post_n)]
        if post.size and abs(np.median(post) - level) <= max(LEVEL_TOLERANCE, LEVEL_SHARE * jump):
            return 0.5 * (t[j] + t[j + 1]) - t_swap, jump / sigma if sigma > 0 else math.inf
    return math.nan, math.nan


def swap_step(t: np.ndarray, az: np.ndarray, t_swap: float, reach_s: float, level: float,
              sigma: float | None = None) -> tuple[float, float]:
    """The IMU's step of a leg swap within ``reach_s`` [s] of the encoder's swap at ``t_swap`` [s].

    ``t`` [s] (increasing) and ``az`` [m/s^2]: consecutive samples around
    the swap; ``level`` [m/s^2]: the rigid level of the new leg (what ``az``
    settles to after a swap). A step is a jump of ``az`` between two
    samples above :data:`STEP_SIGMAS` noise standard deviations (``sigma``,
    default :func:`jump_sigma` of the samples' jumps) and :data:`STEP_FLOOR`,
    and :data:`STEP_LOCAL` times the median jump of its neighbours, after
    which ``az`` is at the rigid level (the median over :data:`POST_TIME`,
    within :data:`LEVEL_TOLERANCE` or :data:`LEVEL_SHARE` of the jump): a
    swap's, not a re-plant's after the foot lost contact, which the model
    also makes at high slip. The largest such step counts (of the
    :data:`MAX_CANDIDATES` largest jumps). Returns ``(offset, ratio)``: its
    time (midway between its two samples) minus ``t_swap`` [s], positive
    when the IMU sees the swap after the encoder, and its jump over the
    noise's standard deviation [-]; ``offset`` is NaN when there is none
    (or too few samples). Compiled (numba): about 10 us for 2000 samples.
    """
    t = np.ascontiguousarray(t, dtype=np.float64)
    az = np.ascontiguousarray(az, dtype=np.float64)
    if t.size < 2 * LOCAL_SAMPLES + 3 or t.size != az.size:
        return math.nan, math.nan
    offset, ratio = _swap_step(t, az, float(t_swap), float(reach_s), float(level),
                               math.nan if sigma is None else float(sigma))
    return float(offset), float(ratio)


def agreement(steps, tolerance: float) -> tuple[float, float, int, int]:
    """Steps ``(offset in time [s], in angle [rad], leg speed [rad/s])``: their median offset in time and in
    angle, and how many agree with each within ``tolerance`` [s] (in angle: at their own leg speed);
    ``(nan, nan, 0, 0)`` without steps."""
    if len(steps) == 0:
        return math.nan, math.nan, 0, 0
    steps = np.asarray(steps, dtype=float)
    t_med = statistics.median(steps[:, 0].tolist())
    a_med = statistics.median(steps[:, 1].tolist())
    t_agree = int(np.count_nonzero(np.abs(steps[:, 0] - t_med) <= tolerance))
    a_agree = int(np.count_nonzero(np.abs(steps[:, 1] - a_med) <= tolerance * steps[:, 2]))
    return t_med, a_med, t_agree, a_agree


class SwapTiming:
    """Follows the IMU's step at each leg swap, cycle after cycle, and says how to correct the angle.

    Feed each cycle that may be estimated, in order, with :meth:`add_cycle`
    (its samples over the whole cycle, phases ``[-pi/nL, pi/nL)``, on the
    angle as corrected so far); the swap between two consecutive cycles
    (``k - 1`` and ``k``) is measured from the end of the first and the
    start of the second. Each step found gives the IMU's whole offset from
    the encoder (the correction in force added back), in time [s] and in
    angle [rad]. Two explanations are weighed on the recent steps: a time
    skew (the same offset in time whatever the leg speed) and an encoder
    zero offset (the same in angle); the one more of them agree with wins
    (the angle on a tie, as at a steady speed where both agree). Once
    ``min_steps`` agree within ``tolerance`` [s] and the correction it
    calls for (the angle, or the time offset times this cycle's leg speed)
    differs from the one in force by more than ``tolerance`` times the leg
    speed, :meth:`add_cycle` returns it. ``tolerance``, ``min_steps``,
    ``memory``: :data:`TOLERANCE`, :data:`MIN_STEPS`, :data:`MEMORY`.
    """

    def __init__(self, n_legs: int, tolerance: float = TOLERANCE, min_steps: int = MIN_STEPS, memory: int = MEMORY):
        if not (tolerance > 0 and 1 <= min_steps <= memory):
            raise ValueError("tolerance must be > 0 and 1 <= min_steps <= memory")
        self.half = math.pi / n_legs
        self.reach = min(SEARCH_REACH, MAX_REACH_FRACTION * self.half)
        self.tolerance = float(tolerance)
        self.min_steps = int(min_steps)
        self.steps: deque = deque(maxlen=int(memory))  # recent steps: (offset in time [s], in angle [rad], omega)
        self.angle = 0.0  # the correction in force: angle taken off theta [rad]
        self.model = None  # "time" or "angle" once a correction was made
        self.offset = 0.0  # the offset that correction explains: [s] for "time", [rad] for "angle"
        self.settle: deque = deque(maxlen=int(memory))  # recent swaps' settling ratios [-]
        self.measured = 0  # swaps whose step was found
        self.looked = 0  # swaps looked at
        self._tail = None  # (k, t, az) of the previous cycle's end
        self._fresh = False  # a step was added since the explanations were last weighed

    @property
    def sluggish(self) -> bool:
        """The IMU settles slowly after the recent swaps (:data:`SLUGGISH`): its signal path smooths what the
        model has sharp (a low-pass filter, a soft mount), and the features are not the model's."""
        return len(self.settle) >= self.min_steps and statistics.median(self.settle) > SLUGGISH

    @property
    def settling(self) -> float:
        """Median settling ratio of the recent swaps (:data:`SETTLE_SPAN`) [-]; NaN before any."""
        return statistics.median(self.settle) if self.settle else math.nan

    def forget_tail(self) -> None:
        """The next cycle does not follow the last one fed (the stream was cut or re-timed)."""
        self._tail = None

    def add_cycle(self, k: int, t: np.ndarray, az: np.ndarray, theta_phase: np.ndarray, omega: float,
                  noise: float = math.nan) -> float | None:
        """Cycle ``k``'s samples (``t`` [s], ``az`` [m/s^2], ``theta_phase`` [rad] on the corrected angle) at
        leg speed ``omega`` [rad/s]; ``noise``: the IMU noise's standard deviation when known [m/s^2] (else
        measured from the samples' jumps, :func:`jump_sigma`). Returns the new correction (the angle to take
        off ``theta`` [rad], in all, from the next sample on), or None to keep the one in force."""
        head = theta_phase < -self.half + self.reach
        if self._tail is not None and self._tail[0] == k - 1 and np.any(head) and omega > 0:
            tt = np.concatenate([self._tail[1], t[head]])
            aa = np.concatenate([self._tail[2], az[head]])
            t_swap = 0.5 * (float(self._tail[1][-1]) + float(t[head][0]))
            rigid = az[(theta_phase > LEVEL_SPAN[0] * self.half) & (theta_phase < LEVEL_SPAN[1] * self.half)]
            self.looked += 1
            level = float(np.mean(rigid)) if rigid.size else math.nan  # (outliers are out: slipest.despike)
            sigma = math.sqrt(2.0) * noise if noise > 0 else float(jump_sigma(aa[1:] - aa[:-1]))
            self._settling(tt, aa, t_swap, level, sigma / math.sqrt(2.0))
            residual, _ = swap_step(tt, aa, t_swap, self.reach / omega, level, sigma)
            if math.isfinite(residual):
                self.measured += 1
                self.steps.append((residual + self.angle / omega, residual * omega + self.angle, omega))
                self._fresh = True
        tail = theta_phase >= self.half - self.reach
        self._tail = (k, t[tail].copy(), az[tail].copy()) if np.any(tail) else None
        return self._decide(omega) if omega > 0 else None

    def _settling(self, t, az, t_swap: float, level: float, noise: float) -> None:
        i = int(np.searchsorted(t, t_swap))  # the first sample after the swap
        pre = az[int(np.searchsorted(t, t_swap - PRE_TIME)):i]
        post = az[int(np.searchsorted(t, t_swap + SETTLE_SPAN[0])):int(np.searchsorted(t, t_swap + SETTLE_SPAN[1]))]
        if pre.size == 0 or post.size < 2 or not math.isfinite(level):
            return
        jump = statistics.median(pre.tolist()) - level
        if abs(jump) > max(SETTLE_MIN_SIGMAS * noise, SETTLE_FLOOR):
            self.settle.append((float(np.mean(post)) - level) / jump)

    def _decide(self, omega: float) -> float | None:
        if self._fresh and len(self.steps) >= self.min_steps:
            self._fresh = False
            t_med, a_med, t_agree, a_agree = agreement(self.steps, self.tolerance)
            if max(t_agree, a_agree) >= self.min_steps:
                self.model, self.offset = ("angle", a_med) if a_agree >= t_agree else ("time", t_med)
        if self.model is None:
            return None
        target = self.offset if self.model == "angle" else self.offset * omega
        if abs(target) <= self.tolerance * omega:
            target = 0.0
        if abs(target - self.angle) <= self.tolerance * omega:
            return None
        self.angle = target
        self._tail = None  # the stream is re-timed from the next sample
        self.settle.clear()  # measured on the old timing
        return target


@dataclass(frozen=True)
class SwapSummary:
    """What the leg swaps of a whole log say about the IMU's timing against the encoder (:func:`swap_summary`).

    looked, measured: swaps looked at, and with a step found [-]. offset_s: median offset of the IMU's
    step from the encoder's swap [s] (positive: the IMU shows the swap after the encoder says it happened),
    NaN without steps; offset_rad: the same in leg angle [rad] (each step's offset times its cycle's leg
    speed); agree_time, agree_angle: steps within :data:`TOLERANCE` of the median offset in time, and in
    angle (at their leg speed) [-]. settling: median settling ratio of the swaps [-] (:data:`SETTLE_SPAN`;
    0 for an IMU that follows the hub), NaN without any; settled: how many swaps gave one. The settling
    is read at the encoder's swap, so it means something only when the timing is not :attr:`off`
    (:attr:`settling_read`).
    """

    looked: int
    measured: int
    offset_s: float
    offset_rad: float
    agree_time: int
    agree_angle: int
    settling: float
    settled: int

    @property
    def off(self) -> bool:
        """At least :data:`MIN_STEPS` steps found and their median beyond :data:`TOLERANCE`."""
        return self.measured >= MIN_STEPS and abs(self.offset_s) > TOLERANCE

    @property
    def settling_read(self) -> float:
        """:attr:`settling`, or NaN when the timing is :attr:`off` (it is then read at the wrong time) [-]."""
        return math.nan if self.off else self.settling

    @property
    def sluggish(self) -> bool:
        """At least :data:`MIN_STEPS` settling ratios and their median (:attr:`settling_read`) above
        :data:`SLUGGISH`."""
        return self.settled >= MIN_STEPS and self.settling_read > SLUGGISH

    def explanation(self) -> str:
        """One sentence: the offset and what it looks like, and how the IMU settles."""
        if self.measured == 0:
            timing = (f"no step found at the {self.looked} leg swaps (no stick-slip at the end of the stance, or "
                      "an IMU path that smooths it)")
        else:
            timing = (f"the IMU's step at the leg swaps is {1000 * self.offset_s:+.1f} ms "
                      f"({self.offset_rad:+.3f} rad) from the encoder's swap, median of {self.measured} of "
                      f"{self.looked} swaps")
            if self.off:
                kind = ("an encoder zero offset (the same angle at every speed)" if self.agree_angle > self.agree_time
                        else "a time skew between the IMU and the encoder (the same time at every speed)"
                        if self.agree_time > self.agree_angle else "a time skew or an encoder zero offset (one speed "
                        "cannot tell them apart)")
                timing += f": off by more than {1000 * TOLERANCE:.0f} ms, like {kind}"
            elif self.measured < MIN_STEPS:
                timing += f" (fewer than {MIN_STEPS} steps: no conclusion)"
            else:
                timing += f": within {1000 * TOLERANCE:.0f} ms"
        if self.settled == 0:
            return timing
        if self.off:
            return f"{timing}; settling not read (it is read at the encoder's swap, which is off)"
        settle = (f"settling ratio {self.settling:.2f} over {self.settled} swaps"
                  + (f": above {SLUGGISH}, the IMU's path smooths the swap (a low-pass filter, a soft mount)"
                     if self.sluggish else ""))
        return f"{timing}; {settle}"


def swap_summary(t, az, theta, n_legs: int) -> SwapSummary:
    """Every leg swap of a whole log measured as :class:`SwapTiming` measures them, without correcting the
    angle: ``t`` [s], ``az`` [m/s^2], ``theta`` [rad] (unwrapped or wrapped; a whole-count encoder's angle is
    interpolated first, :func:`slipest.dequantize.dequantize_log`), arrays of one length; samples with a
    non-finite value are left out. A cycle whose angle does not increase (the leg standing still or
    reversing) gives no swap with its neighbours."""
    from slipest.dequantize import dequantize_log

    t = np.asarray(t, dtype=float)
    az = np.asarray(az, dtype=float)
    theta = np.asarray(theta, dtype=float)
    if not (t.shape == az.shape == theta.shape):
        raise ValueError(f"t, az and theta must have the same length ({t.size}, {az.size}, {theta.size})")
    if n_legs < 1:
        raise ValueError(f"n_legs must be >= 1, got {n_legs}")
    ok = np.isfinite(t) & np.isfinite(az) & np.isfinite(theta)
    t, az = t[ok], az[ok]
    theta = dequantize_log(t, theta[ok])
    half = math.pi / n_legs
    k = np.floor((theta + half) / (2 * half)).astype(np.int64)
    # every step kept; an infinite tolerance never calls for a correction, so the angle is read as logged
    timing = SwapTiming(n_legs, tolerance=math.inf, min_steps=1, memory=max(1, int(k.size)))
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    ends = np.r_[starts[1:], k.size]
    for a, b in zip(starts, ends):
        if b - a < 3 or t[b - 1] <= t[a]:
            timing.forget_tail()
            continue
        phase = theta[a:b] - 2 * half * k[a]
        omega = float(theta[b - 1] - theta[a]) / float(t[b - 1] - t[a])
        if not omega > 0:
            timing.forget_tail()
            continue
        timing.add_cycle(int(k[a]), t[a:b], az[a:b], phase, omega)
    t_med, a_med, agree_t, agree_a = agreement(timing.steps, TOLERANCE)
    return SwapSummary(timing.looked, timing.measured, t_med, a_med, agree_t, agree_a, timing.settling,
                       len(timing.settle))
