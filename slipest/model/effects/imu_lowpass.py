"""``imu_lowpass``: the IMU's bandwidth, a Butterworth low-pass before sampling (continuous sensor effect)."""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy import signal

from slipest.model.effects.base import Effect, FitParam, ParamSpec


class LowPass:
    """Butterworth low-pass of order ``order`` and cut-off ``cutoff`` [Hz] ("continuous" stage).

    The sample rate is that of the first chunk it sees (the model step);
    the filter starts in steady state at the first value (no start-up
    transient) and keeps its state across chunks.
    """

    domain = "continuous"

    def __init__(self, cutoff: float, order: int = 2):
        self.cutoff = float(cutoff)
        self.order = int(order)
        self._ba = None
        self._zi = None
        self._fs = None

    def design(self, fs: float):
        """``(b, a)`` at sample rate ``fs`` [Hz]."""
        if not self.cutoff < fs / 2:
            raise ValueError(f"imu_lowpass: cutoff={self.cutoff:g} Hz must be below the Nyquist frequency {fs / 2:g} Hz")
        return signal.butter(self.order, self.cutoff, btype="low", fs=fs)

    def apply(self, t, az, theta, rng):
        if len(az) == 0:
            return az, theta
        if self._ba is None:
            if len(t) < 2:
                raise ValueError("imu_lowpass needs at least two samples in the first chunk to know the rate")
            self._fs = 1.0 / float(t[1] - t[0])
            self._ba = self.design(self._fs)
            self._zi = signal.lfilter_zi(*self._ba) * az[0]
        b, a = self._ba
        out, self._zi = signal.lfilter(b, a, az, zi=self._zi)
        return out, theta


def butter_sections(order: int, cutoff: float, fs: float) -> np.ndarray:
    """Butterworth low-pass as second-order sections ``(n_sec, 5)`` rows ``b0 b1 b2 a1 a2``.

    Bilinear transform with the cut-off prewarped, as ``scipy.signal.butter``
    does (same filter; a first-order section has ``b2 = a2 = 0``).
    """
    k = math.tan(math.pi * cutoff / fs)
    rows = []
    for j in range(order // 2):
        theta = math.pi * (2 * j + 1) / (2 * order)
        q = 1.0 / (2 * math.sin(theta))
        norm = 1.0 / (1 + k / q + k * k)
        b0 = k * k * norm
        rows.append((b0, 2 * b0, b0, 2 * (k * k - 1) * norm, (1 - k / q + k * k) * norm))
    if order % 2:
        b0 = k / (1 + k)
        rows.append((b0, b0, 0.0, (k - 1) / (k + 1), 0.0))
    return np.array(rows, dtype=float)


@numba.njit(cache=True, parallel=True)
def _sos_rows(x, sos, nsec, out):
    """Filter row ``r`` of ``x`` with its own ``nsec[r]`` sections ``sos[r]``, steady start."""
    n_rows, n = x.shape
    for r in numba.prange(n_rows):
        for i in range(n):
            out[r, i] = x[r, i]
        for s in range(nsec[r]):
            b0, b1, b2, a1, a2 = sos[r, s, 0], sos[r, s, 1], sos[r, s, 2], sos[r, s, 3], sos[r, s, 4]
            x0 = out[r, 0]
            z2 = (b2 - a2) * x0
            z1 = (b1 - a1) * x0 + z2
            for i in range(n):
                xi = out[r, i]
                yi = b0 * xi + z1
                z1 = b1 * xi - a1 * yi + z2
                z2 = b2 * xi - a2 * yi
                out[r, i] = yi


def lowpass_batch(x: np.ndarray, grid, omega: float, cutoff, order) -> np.ndarray:
    """Butterworth low-pass of ``x (P, G, n)`` on the extended grid, cut-off [Hz] and integer order per candidate ``(P,)``.

    The grid's sample rate is ``omega / dpsi`` at the constant leg speed
    ``omega`` [rad/s]. Candidates whose cut-off is not below the Nyquist
    frequency give NaN.
    """
    fs = omega / grid.dpsi
    P, G, n = x.shape
    cutoff = np.asarray(cutoff, dtype=float)
    order = np.asarray(order).astype(int)
    n_sec_max = int((order.max() + 1) // 2)
    sos = np.zeros((P, n_sec_max, 5))
    nsec = np.zeros(P, dtype=np.int64)
    bad = ~((cutoff > 0) & (cutoff < fs / 2))
    for p in range(P):
        if bad[p]:
            continue
        s = butter_sections(int(order[p]), float(cutoff[p]), fs)
        sos[p, : len(s)] = s
        nsec[p] = len(s)
    out = np.empty((P * G, n))
    _sos_rows(np.ascontiguousarray(x.reshape(P * G, n)), np.repeat(sos, G, axis=0), np.repeat(nsec, G), out)
    out = out.reshape(P, G, n)
    out[bad] = np.nan
    return out


class ImuLowpassEffect(Effect):
    """The IMU's bandwidth: a Butterworth low-pass of order ``n``, -3 dB at ``fc`` [Hz], before sampling.

    Gain ``1/sqrt(2)`` at ``fc``, on the continuous signal
    (``scipy.signal.butter`` + ``lfilter``; the filter state carries across
    chunks; it starts in steady state). The stick-slip oscillation is at
    4-7 Hz. The filter's memory carries the previous stance into the
    cycle; the order is fitted as a categorical parameter (one search
    instance per order).
    """

    name = "imu_lowpass"
    kind = "continuous"
    equation = "Butterworth low-pass, order n, -3 dB at fc, before sampling"
    description = "IMU bandwidth (digital low-pass / anti-alias filter) below the stick-slip oscillation"
    params = (
        ParamSpec("cutoff", "Hz", 5.0, (5.0, 100.0), (3.0, 6.0), (0.1, 1e5), "cut-off (-3 dB) frequency fc",
                  log_scale=True),
        ParamSpec("order", "-", 2, (1, 4), (1, 4), (1, 8), "filter order n", integer=True),
    )
    fit_params = (
        FitParam("cutoff", "Hz", 1.0, 40.0, log=True, off=40.0),
        FitParam("order", "-", 1, 4, integer=True, choices=(1, 2, 3, 4), off=2),
    )
    memory = True

    def stage(self, values):
        return LowPass(values["cutoff"], values["order"])

    def sense(self, x, values, ctx):
        for om, sel in ctx.speed_groups():
            x[:, sel] = lowpass_batch(x[:, sel], ctx.grid, om, values["cutoff"], values["order"])
        return ctx.bin_average(x)
