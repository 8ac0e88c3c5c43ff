"""``time_skew``: the IMU's and the encoder's clocks disagree by a constant time (sampled sensor effect)."""

from __future__ import annotations

import math

import numpy as np

from slipest.model.effects.base import Effect, FitParam, ParamSpec


class TimeSkew:
    """The IMU's samples ``skew`` [s] late relative to the encoder's (negative: the encoder's late) ("sampled" stage).

    A logged pair ``(az, theta)`` holds ``az`` from ``skew`` seconds before
    ``theta``. Done causally, in bounded memory and the same however the
    stream is chunked: for ``skew > 0``, ``az`` is delayed by the whole
    samples ``m = ceil(skew * rate)`` and ``theta`` by the remainder
    ``m / rate - skew`` (linear interpolation of the smooth angle, so the
    accelerometer's noise is not smoothed); for ``skew < 0``, ``theta`` is
    delayed by ``-skew``. The stage asks for ``lead_in`` = ``|skew|`` of
    signal before a run's start, which :func:`slipest.model.stream.iter_stream`
    simulates and drops; a caller that gives it none gets ``az`` held at its
    first value and ``theta`` continued at the first two samples' speed for
    that long. The sample rate is that of the first chunk (at least two
    samples).
    """

    domain = "sampled"

    def __init__(self, skew: float):
        self.skew = float(skew)
        self._m = None  # whole-sample delay of az
        self._theta_delay = None  # [s]
        self._az_tail = None  # the last m az samples
        self._t_tail = np.empty(0)  # recent (t, theta) samples covering the angle's delay
        self._th_tail = np.empty(0)
        self._speed0 = None  # theta's speed at the stream's start [rad/s]
        self._period = None  # sample period [s]

    @property
    def lead_in(self) -> float:
        """Signal [s] the stage needs from before a run's first sample: the skew's size."""
        return abs(self.skew)

    def apply(self, t, az, theta, rng):
        if self.skew == 0.0 or len(t) == 0:
            return az, theta
        t = np.asarray(t, dtype=float)
        theta = np.asarray(theta, dtype=float)
        if self._m is None:
            if len(t) < 2:
                raise ValueError("time_skew needs at least two samples in the first chunk to know the rate")
            period = self._period = float(t[1] - t[0])
            self._speed0 = float(theta[1] - theta[0]) / period
            if self.skew > 0:
                self._m = int(math.ceil(self.skew / period - 1e-9))
                self._theta_delay = self._m * period - self.skew
            else:
                self._m = 0
                self._theta_delay = -self.skew
            self._az_tail = np.full(self._m, float(az[0]))
        out_az = np.asarray(az, dtype=float)
        if self._m:
            joined = np.concatenate([self._az_tail, out_az])
            out_az = joined[: len(out_az)]
            self._az_tail = joined[len(joined) - self._m :]
        out_theta = theta
        if self._theta_delay > 0:
            tt = np.concatenate([self._t_tail, t])
            th = np.concatenate([self._th_tail, theta])
            want = t - self._theta_delay
            out_theta = np.interp(want, tt, th)
            early = want < tt[0]  # before the stream's first sample: continue at its speed
            out_theta[early] = th[0] + (want[early] - tt[0]) * self._speed0
            keep = tt >= t[-1] - self._theta_delay - 2 * self._period
            self._t_tail, self._th_tail = tt[keep], th[keep]
        return out_az, out_theta


class TimeSkewEffect(Effect):
    """A constant time offset between the IMU's and the encoder's samples: ``az_log(t) = az(t - skew)``.

    ``skew`` [s] > 0: the IMU's samples are late relative to the encoder's
    (or the encoder's early); < 0: the encoder's are late. Within a cycle
    at leg speed ``omega`` it is an encoder angle offset ``omega skew``
    (:class:`~slipest.model.effects.angle_offset.AngleOffsetEffect`), so the
    two differ only when the leg speed changes: on cycles at one speed the
    diagnosis does not fit it (:meth:`equivalent_on`). The prediction takes
    each cycle's speed level and, for the part of the cycle whose ``az``
    comes from the previous cycle, the previous cycle's.
    """

    name = "time_skew"
    kind = "sampled"
    equation = "az_log(t) = az(t - skew)  (= angle offset omega skew at leg speed omega)"
    description = ("constant time offset between the IMU's and the encoder's samples (clocks, buffering, "
                   "timestamps taken on reception)")
    params = (
        ParamSpec("skew", "s", 0.25, (-0.1, 0.1), (0.15, 0.3), (-5.0, 5.0),
                  "IMU sample time minus encoder sample time of a logged pair (positive: the IMU is late; "
                  "the moderate range is for leg speeds 0.4-1.1 rad/s)", neutral=0.0),
    )
    fit_params = (FitParam("skew", "s", -0.2, 0.6, off=0.0),)  # -0.2 s: the prediction grid's margin at 1.2 rad/s
    memory = True
    #: Relative spread of the cycles' leg speeds ``(max - min) / median`` below which a time skew is an angle offset.
    MIN_SPEED_SPREAD = 0.2

    def stage(self, values):
        return TimeSkew(values["skew"])

    def sense(self, x, values, ctx):
        """Bin averages with the time shift mapped to phase: ``skew`` seconds before the bin edge at logged phase
        ``e`` is phase ``e - omega skew`` while that is still in the cycle, else the previous cycle's end at its
        own speed."""
        lag = np.asarray(values["skew"], dtype=float)[:, None]
        half = ctx.grid.half
        edges = ctx.grid.bin_edges[None, :]
        out = np.empty(x.shape[:2] + (ctx.grid.nb,))
        for om, pom, sel in ctx.speed_groups(previous=True):
            since = (edges + half) / om  # time since the cycle's boundary [s]
            true = np.where(since >= lag, edges - om * lag, -half - pom * (lag - since))
            out[:, sel] = ctx.bin_average(x[:, sel], edges - true)
        return out

    def angle_offset_at(self, values, omega):
        """``omega skew`` [rad]: at a steady leg speed ``omega`` [rad/s] the skew is that angle offset."""
        return float(omega) * float(values["skew"])

    def equivalent_on(self, omega) -> str | None:
        """``angle_offset`` when the cycles' leg speeds ``omega`` [rad/s] spread by less than :attr:`MIN_SPEED_SPREAD`."""
        omega = np.asarray(omega, dtype=float)
        omega = omega[np.isfinite(omega)]
        if omega.size and (omega.max() - omega.min()) < self.MIN_SPEED_SPREAD * float(np.median(omega)):
            return "angle_offset"
        return None
