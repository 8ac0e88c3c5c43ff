"""The stuck-sensor rule: ``az`` repeating bit for bit long enough is a frozen sensor (pure computation).

A frozen IMU or a stuck driver keeps handing on its last value. Noisy data
repeats far less (:mod:`slipest.io.device_stream` gives the false-alarm
rates, ``tools/stuck_threshold.py`` measures them), so a run of
bit-identical ``az`` lasting :data:`STUCK_TIME` (never fewer than
:data:`STUCK_MIN_SAMPLES` samples) is taken as stuck. Two places apply it:

* a device's frames, as they arrive (:class:`slipest.io.device_stream.WheelStream`):
  the run's samples become NaN, so their cycle is flagged ``"nan"``;
* samples handed to :class:`slipest.online.SlipEstimator` (a log's, a
  program's own driver's): a closed cycle holding such a run, counted
  across the cycle's start from the one before, is flagged ``"stuck"``
  (:func:`repeat_runs`), unless the run holds the cycle's largest or
  smallest value: that is a clipped (saturated) sensor, for the
  segmenter's ``full_scale`` and ``clip_values`` (a calibrated rover may
  know the clipping), or unless the IMU's noise is below
  :data:`STUCK_NOISE_MIN` (a noise-free signal repeats itself where it is
  smooth). After the first place NaN never repeats, so a stream is never
  flagged by both.
"""

from __future__ import annotations

import math

import numba

__all__ = ["STUCK_MIN_SAMPLES", "STUCK_NOISE_MIN", "STUCK_TIME", "repeat_runs", "stuck_run_length"]

#: [s] a run of bit-identical az lasting this long is a stuck sensor.
STUCK_TIME = 0.02
#: ...but never fewer samples than this (at low IMU rates).
STUCK_MIN_SAMPLES = 12
#: [g] below this IMU noise a smooth signal repeats itself (a noise-free simulated log's printed digits): the rule
#: is not applied to the samples SlipEstimator is given.
STUCK_NOISE_MIN = 0.001


def stuck_run_length(stuck_time: float, period: float | None) -> int:
    """Samples of a run of identical ``az`` lasting ``stuck_time`` [s] at the sample ``period`` [s]
    (None: unknown), never fewer than :data:`STUCK_MIN_SAMPLES`."""
    if not period:
        return STUCK_MIN_SAMPLES
    return max(STUCK_MIN_SAMPLES, round(stuck_time / period))


@numba.njit(cache=True)
def repeat_runs(az, lead_value, lead_count):
    """``(longest, tail)``: the longest run of consecutive bit-identical values of ``az`` strictly between its
    smallest and largest value (a run at either is a clipped, saturated sensor, which the segmenter's
    ``full_scale`` and ``clip_values`` govern, not a frozen one), and the length of the run ``az`` ends with
    [samples]. A run continues from before ``az`` when ``az[0] == lead_value``: ``lead_count`` samples of it
    came before (0: none). NaN never equals anything, so it breaks runs. Empty ``az``: ``(0, lead_count)``."""
    n = az.size
    if n == 0:
        return 0, lead_count
    lo = math.inf
    hi = -math.inf
    for i in range(n):
        v = az[i]
        if v < lo:
            lo = v
        if v > hi:
            hi = v
    run = lead_count + 1 if lead_count > 0 and az[0] == lead_value else 1
    longest = run if lo < az[0] < hi else 0
    for i in range(1, n):
        run = run + 1 if az[i] == az[i - 1] else 1
        if run > longest and lo < az[i] < hi:
            longest = run
    return longest, run
