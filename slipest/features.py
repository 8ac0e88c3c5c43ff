"""Per-leg-cycle features of the hub's vertical acceleration (pure computation).

A leg cycle's *feature window* is the propulsive half-stance, leg phase
``theta_phase`` from 0 (midstance) to ``pi/nL`` [rad]. Inside it the hub
rides on the stuck foot, then, from the break-away, oscillates (stick-slip).
The break-away angle is quasi-static (it moves with slip, ``kS`` and
``phiS``, not with the leg speed); the oscillation frequency is the hub's on
the leg/soil spring (set by ``kS``, in Hz); the amplitude and its growth
depend on slip, ``kS`` and ``dphi``.

The features are built to mean the same thing whatever the IMU's rate
(200 Hz - 2 kHz) and noise: the samples of the window are averaged into the
:data:`N_GRID` bins of a uniform phase grid, then smoothed with a Gaussian
kernel of fixed width in *time* (:data:`SMOOTH_TIME`, about a 20 Hz
low-pass; the stick-slip oscillation is at 3-8 Hz), and every feature but
``delta_a`` is taken on that smoothed signal, with thresholds and RMS values
referred to the smoothed noise level ``noise_smooth`` (computed from the
sample noise ``noise`` and how many samples each smoothed point averages).

=============  =====  =========================================================
name           unit   meaning
=============  =====  =========================================================
delta_a        g      ``Da`` as the thesis defines it: max minus min of the raw
                      ``az`` samples in the window (grows with noise and rate)
peak_pos       g      max of the smoothed ``az`` above the stick level
peak_neg       g      stick level minus min of the smoothed ``az``
rms            g      RMS of the smoothed ``az`` about the window mean, with the
                      smoothed noise's variance taken out
rms_q1..q4     g      the same per quarter of the window (about the window mean)
onset          rad    break-away angle: first phase where the smoothed ``|az -
                      stick level|`` exceeds the onset threshold
                      (:func:`onset_threshold`); ``pi/nL`` when it never does
energy_q10     rad    phases by which 10/50/90 % of the energy
energy_q50     rad      ``sum max((az - stick level)^2 - noise_smooth^2, 0)`` over
energy_q90     rad      the window has accumulated
zc_rate        Hz     crossings of the window mean (with hysteresis) per second
osc_freq       Hz     ``(n - 1) / (2 dt)`` for the ``n`` hysteresis crossings
                      spanning ``dt`` seconds; 0 when ``n < 2``
rice_freq      Hz     ``rms(d az/dt) / (2 pi rms(az))`` after the onset (about its
                      mean there); 0 when there is no onset or no signal above
                      3 ``noise_smooth``
n_crossings    -      number of hysteresis crossings over the window
noise          g      the sample noise's standard deviation (given, or estimated
                      by :func:`sample_noise`)
stick_mean     g      mean of ``az`` minus the stick level from the end of the
                      stick-level span to :data:`STICK_SPAN` rad, or to 0.01 rad
                      before the onset if that comes first (0 when that leaves
                      fewer than 4 bins): the hub's motion on the stuck foot
omega          rad/s  mean leg speed over the window
noise_smooth   g      standard deviation of the noise left on the smoothed signal
spec_cent      Hz     power-weighted mean frequency of the window's signal (mean
                      removed, Hann-windowed) over :data:`SPECTRAL_BAND`; 0 with
                      no power there
spec_bw        Hz     power-weighted spread of that frequency (same band)
e_cent         rad    energy-weighted mean phase (energy as for ``energy_q*``);
                      0 when no energy is above the noise
e_spread       rad    energy-weighted spread of the phase about ``e_cent``
spec_skew      Hz     cube root of the power-weighted third central moment of
                      that frequency (band and spectrum of ``spec_cent``)
spec_cent2     Hz     ``spec_cent`` of the window's second half (its own mean
                      removed and Hann window); 0 with no power there
=============  =====  =========================================================

Gravity and bias: the IMU reports the specific force (``+g`` at rest) plus
an unknown constant bias; no feature depends on either (``delta_a`` and the
RMS values are differences or spreads; peaks, onset, energies and
``stick_mean`` are relative to the **stick level**, the mean of the smoothed
signal over the first :data:`STICK_FRACTION` of the window; crossings and
frequencies are about the window mean). Adding a constant to ``az`` changes
no feature (tested).

Noise: :func:`sample_noise` estimates it from the median absolute second
difference of the samples of the rigid half of the cycle (phase in
``[-0.8 pi/nL, -0.05 pi/nL]``, where the hub rides smoothly on the planted
foot), or, when the cycle does not carry that half, of the first
:data:`STICK_SPAN` rad of the window.

One compiled routine (numba) computes a row, the spectral moments' discrete Fourier transforms over their band
included: 0.10 ms median a closing cycle in ``tools/bench_latency.py``'s features stage.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from slipest.units import G

#: Feature names, in the column order of :func:`cycle_features` / :func:`features_batch`.
FEATURE_NAMES = (
    "delta_a",
    "peak_pos",
    "peak_neg",
    "rms",
    "rms_q1",
    "rms_q2",
    "rms_q3",
    "rms_q4",
    "onset",
    "energy_q10",
    "energy_q50",
    "energy_q90",
    "zc_rate",
    "osc_freq",
    "rice_freq",
    "n_crossings",
    "noise",
    "stick_mean",
    "omega",
    "noise_smooth",
    "spec_cent",
    "spec_bw",
    "e_cent",
    "e_spread",
    "spec_skew",
    "spec_cent2",
)

#: Unit of each feature, same order as :data:`FEATURE_NAMES`.
FEATURE_UNITS = ("g",) * 8 + ("rad",) * 4 + ("Hz",) * 3 + ("-", "g", "g", "rad/s", "g", "Hz", "Hz", "rad", "rad", "Hz",
                                                             "Hz")

#: Column index of each feature.
INDEX = {name: j for j, name in enumerate(FEATURE_NAMES)}

#: Number of bins of the uniform phase grid over the window [-].
N_GRID = 512
#: Standard deviation of the Gaussian smoothing kernel, in time [s] (about a 20 Hz low-pass).
SMOOTH_TIME = 0.006
#: Fraction of the window, from its start, whose mean is the stick level [-].
STICK_FRACTION = 0.025
#: Onset threshold ``sqrt(ONSET_FLOOR_G^2 + (ONSET_SPEED_G omega^2)^2) + ONSET_SIGMAS noise_smooth`` [g]: a floor
#: [g], the hub's own bounce on the stuck foot, which grows as omega^2 (its 99th percentile over the envelope
#: is 0.039 omega^2 g) [g s^2/rad^2], and a margin over the smoothed noise [-].
ONSET_FLOOR_G = 0.03
ONSET_SPEED_G = 0.05
ONSET_SIGMAS = 4.5
#: Hysteresis half-band of the crossings: this fraction of the window's RMS ...
HYSTERESIS_FRACTION = 0.3
#: ... but at least this much [g] ...
HYSTERESIS_FLOOR_G = 0.03
#: ... and at least this many smoothed-noise standard deviations [-].
HYSTERESIS_SIGMAS = 4.0
#: End of the span of ``stick_mean``, and of the window part that estimates the noise when the cycle
#: carries no rigid half [rad].
STICK_SPAN = 0.1
#: Rigid-half phases (fractions of ``pi/nL``) whose samples estimate the noise.
NOISE_SPAN = (-0.8, -0.05)
#: Fewest samples a window may have, and fewest samples a noise estimate uses [-].
MIN_SAMPLES = 16
#: Default leg speed [rad/s] for :func:`features_batch` (the model's omega).
DEFAULT_OMEGA = 0.63

_N_FEATURES = len(FEATURE_NAMES)
_DELTA_A, _PEAK_POS, _PEAK_NEG, _RMS = INDEX["delta_a"], INDEX["peak_pos"], INDEX["peak_neg"], INDEX["rms"]
_RMS_Q1, _ONSET, _ENERGY_Q10 = INDEX["rms_q1"], INDEX["onset"], INDEX["energy_q10"]
_ZC_RATE, _OSC_FREQ, _RICE_FREQ = INDEX["zc_rate"], INDEX["osc_freq"], INDEX["rice_freq"]
_N_CROSSINGS, _NOISE, _STICK_MEAN = INDEX["n_crossings"], INDEX["noise"], INDEX["stick_mean"]
_OMEGA, _NOISE_SMOOTH = INDEX["omega"], INDEX["noise_smooth"]
_SPEC_CENT, _E_CENT = INDEX["spec_cent"], INDEX["e_cent"]
_SPEC_SKEW, _SPEC_CENT2 = INDEX["spec_skew"], INDEX["spec_cent2"]
#: Frequency band of ``spec_cent``, ``spec_bw``, ``spec_skew`` and ``spec_cent2`` [Hz].
SPECTRAL_BAND = (1.5, 20.0)
_ENERGY_TARGETS = (0.1, 0.5, 0.9)


def analysis_grid(n_legs: int = 4, n: int = N_GRID) -> np.ndarray:
    """Centres [rad] of the ``n`` bins of the uniform phase grid over ``[0, pi/n_legs]``."""
    half = math.pi / n_legs
    return (np.arange(n) + 0.5) * (half / n)


@numba.njit(cache=True)
def onset_threshold(omega, noise_smooth):
    """The onset threshold [g] at leg speed ``omega`` [rad/s] and smoothed noise ``noise_smooth`` [g]."""
    return math.sqrt(ONSET_FLOOR_G**2 + (ONSET_SPEED_G * omega * omega) ** 2) + ONSET_SIGMAS * noise_smooth


@numba.njit(cache=True)
def bin_mean_fill(acc, cnt):
    """In place: bin sums ``acc`` with counts ``cnt`` become bin means, and
    empty bins are filled by linear interpolation between their neighbours
    (held flat before the first and after the last filled bin; zeros if no
    bin has a sample). Shared by the features and the diagnosis's phase grid."""
    m = acc.shape[0]
    last = -1
    for j in range(m):
        if cnt[j] > 0:
            acc[j] /= cnt[j]
            if last < j - 1:  # fill the gap (last, j)
                for g in range(last + 1, j):
                    if last < 0:
                        acc[g] = acc[j]
                    else:
                        w = (g - last) / (j - last)
                        acc[g] = acc[last] * (1.0 - w) + acc[j] * w
            last = j
    for g in range(last + 1, m):
        acc[g] = acc[last] if last >= 0 else 0.0


@numba.njit(cache=True)
def _second_difference_noise(phase, a, lo, hi, min_samples):
    """1.4826 median|a[i+1] - 2 a[i] + a[i-1]| / sqrt(6) over samples with phase in [lo, hi]; NaN if too few."""
    d2 = np.empty(max(phase.size, 1))
    m = 0
    for i in range(1, phase.size - 1):
        if lo <= phase[i - 1] and phase[i + 1] <= hi:
            d2[m] = abs(a[i + 1] - 2.0 * a[i] + a[i - 1])
            m += 1
    if m < min_samples:
        return np.nan
    return 1.4826 * np.median(d2[:m]) / math.sqrt(6.0)


@numba.njit(cache=True)
def _sample_noise(phase, a, half):
    """Noise [units of ``a``] from the rigid half when the cycle carries it, else from the window's start."""
    s = _second_difference_noise(phase, a, NOISE_SPAN[0] * half, NOISE_SPAN[1] * half, MIN_SAMPLES)
    if s == s:
        return s
    s = _second_difference_noise(phase, a, 0.0, STICK_SPAN, MIN_SAMPLES // 2)
    if s == s:
        return s
    return _second_difference_noise(phase, a, 0.0, half, 3)


@numba.njit(cache=True, inline="always")
def _raw_delta_a(phase, a, half):
    """Max minus min of the raw samples inside the window [units of ``a``], and how many there are."""
    amax = -np.inf
    amin = np.inf
    n_in = 0
    for i in range(phase.size):
        if 0.0 <= phase[i] <= half:
            n_in += 1
            if a[i] > amax:
                amax = a[i]
            if a[i] < amin:
                amin = a[i]
    return amax - amin, n_in


@numba.njit(cache=True, inline="always")
def _smoothed_grid(phase, a, half, omega, n_grid, y):
    """The window's samples binned on the phase grid, then smoothed by a Gaussian of SMOOTH_TIME s (weighted by
    the bins' sample counts); writes ``y`` and returns the mean over the grid of the sum of squared normalised
    weights of the samples behind each point (the smoothed noise variance per unit sample variance)."""
    dphase = half / n_grid
    acc = np.zeros(n_grid)
    cnt = np.zeros(n_grid)
    scale = n_grid / half
    for i in range(phase.size):
        if 0.0 <= phase[i] <= half:
            b = int(phase[i] * scale)
            if b >= n_grid:
                b = n_grid - 1
            acc[b] += a[i]
            cnt[b] += 1.0
    s_bins = SMOOTH_TIME * omega / dphase
    reach = max(1, int(math.ceil(3.0 * s_bins)))
    kern = np.empty(2 * reach + 1)
    for h in range(-reach, reach + 1):
        kern[h + reach] = math.exp(-0.5 * (h / s_bins) ** 2)
    w2sum = 0.0
    n_ok = 0
    filled = np.zeros(n_grid)
    for g in range(n_grid):
        sw = 0.0
        swy = 0.0
        sw2 = 0.0
        for h in range(max(0, g - reach), min(n_grid, g + reach + 1)):
            c = cnt[h]
            if c > 0.0:
                k = kern[h - g + reach]
                sw += k * c
                swy += k * acc[h]
                sw2 += k * k * c
        if sw > 0.0:
            y[g] = swy / sw
            w2sum += sw2 / (sw * sw)
            n_ok += 1
            filled[g] = 1.0
        else:
            y[g] = 0.0
    if n_ok < n_grid:  # points no sample reaches: interpolated between their neighbours
        bin_mean_fill(y, filled)
    return w2sum / max(n_ok, 1)


@numba.njit(cache=True, inline="always")
def _stick_relative_features(y, sig_s, omega, half, out):
    """Peaks, onset, ``stick_mean`` and energy quantiles relative to the stick level; returns the onset bin."""
    n_grid = y.size
    dphase = half / n_grid
    n_stick = max(2, int(round(STICK_FRACTION * n_grid)))
    stick = 0.0
    for b in range(n_stick):
        stick += y[b]
    stick /= n_stick
    pmax = -np.inf
    pmin = np.inf
    for b in range(n_grid):
        d = y[b] - stick
        if d > pmax:
            pmax = d
        if d < pmin:
            pmin = d
    out[_PEAK_POS] = pmax
    out[_PEAK_NEG] = -pmin
    thr = onset_threshold(omega, sig_s)
    k_on = n_grid
    onset = half
    for b in range(n_grid):
        if abs(y[b] - stick) > thr:
            k_on = b
            onset = (b + 0.5) * dphase
            break
    out[_ONSET] = onset
    k_end = min(int(STICK_SPAN / dphase), int((onset - 0.01) / dphase))
    if k_end - n_stick >= 4:
        acc = 0.0
        for b in range(n_stick, k_end):
            acc += y[b] - stick
        out[_STICK_MEAN] = acc / (k_end - n_stick)
    else:
        out[_STICK_MEAN] = 0.0
    var_s = sig_s * sig_s
    etot = 0.0
    e1 = 0.0
    for b in range(n_grid):
        e = max((y[b] - stick) ** 2 - var_s, 0.0)
        etot += e
        e1 += e * (b + 0.5) * dphase
    if etot > 0.0:
        cent = e1 / etot
        e2 = 0.0
        for b in range(n_grid):
            e2 += max((y[b] - stick) ** 2 - var_s, 0.0) * ((b + 0.5) * dphase - cent) ** 2
        out[_E_CENT] = cent
        out[_E_CENT + 1] = math.sqrt(e2 / etot)
    else:
        out[_E_CENT] = 0.0
        out[_E_CENT + 1] = 0.0
    for q in range(3):
        res = _ENERGY_TARGETS[q] * half
        if etot > 0.0:
            acc = 0.0
            for b in range(n_grid):
                acc += max((y[b] - stick) ** 2 - var_s, 0.0)
                if acc >= _ENERGY_TARGETS[q] * etot:
                    res = (b + 0.5) * dphase
                    break
        out[_ENERGY_Q10 + q] = res
    return k_on


@numba.njit(cache=True, inline="always")
def _mean_relative_features(y, sig_s, half, omega, out):
    """RMS (window and quarters, noise variance taken out) about the window mean, hysteresis crossings."""
    n_grid = y.size
    dphase = half / n_grid
    var_s = sig_s * sig_s
    mean = 0.0
    for b in range(n_grid):
        mean += y[b]
    mean /= n_grid
    sq_all = 0.0
    for qi in range(4):
        lo = (qi * n_grid) // 4
        hi = ((qi + 1) * n_grid) // 4
        sq = 0.0
        for b in range(lo, hi):
            sq += (y[b] - mean) ** 2
        sq_all += sq
        out[_RMS_Q1 + qi] = math.sqrt(max(sq / (hi - lo) - var_s, 0.0))
    rms = math.sqrt(max(sq_all / n_grid - var_s, 0.0))
    out[_RMS] = rms
    hband = max(HYSTERESIS_FRACTION * rms, HYSTERESIS_FLOOR_G, HYSTERESIS_SIGMAS * sig_s)
    state = 0
    n_cross = 0
    first = -1
    lastc = -1
    for b in range(n_grid):
        c = y[b] - mean
        s = 1 if c > hband else (-1 if c < -hband else 0)
        if s != 0:
            if state != 0 and s != state:
                n_cross += 1
                if first < 0:
                    first = b
                lastc = b
            state = s
    out[_N_CROSSINGS] = n_cross
    out[_ZC_RATE] = n_cross / (half / omega)
    span = (lastc - first) * dphase / omega
    out[_OSC_FREQ] = (n_cross - 1) / (2.0 * span) if (n_cross >= 2 and span > 0) else 0.0


@numba.njit(cache=True, inline="always")
def _band_power_moments(y, i0, i1, dt):
    """Power-weighted moments of the frequency over :data:`SPECTRAL_BAND` of the signal ``y[i0:i1]`` (grid step
    ``dt`` [s]; its mean removed, Hann-windowed, discrete Fourier transform at the frequencies ``k / (n dt)``):
    ``(mean, spread, skew)`` [Hz], the skew the cube root of the third central moment; 0, 0, 0 with no power
    in the band."""
    n = i1 - i0
    mean = 0.0
    for b in range(i0, i1):
        mean += y[b]
    mean /= n
    x = np.empty(n)
    for b in range(n):
        x[b] = (y[i0 + b] - mean) * (0.5 - 0.5 * math.cos(2.0 * math.pi * b / (n - 1)))
    k0 = int(math.ceil(SPECTRAL_BAND[0] * n * dt))
    k1 = min(int(math.floor(SPECTRAL_BAND[1] * n * dt)), n // 2)
    p0 = 0.0
    p1 = 0.0
    p2 = 0.0
    p3 = 0.0
    for k in range(k0, k1 + 1):
        step = 2.0 * math.pi * k / n
        cs, sn = math.cos(step), math.sin(step)
        c, s = 1.0, 0.0  # cos and sin of step * b, by rotation
        re = 0.0
        im = 0.0
        for b in range(n):
            re += x[b] * c
            im -= x[b] * s
            c, s = c * cs - s * sn, s * cs + c * sn
        pw = re * re + im * im
        f = k / (n * dt)
        p0 += pw
        p1 += pw * f
        p2 += pw * f * f
        p3 += pw * f * f * f
    if not p0 > 0.0:
        return 0.0, 0.0, 0.0
    cent = p1 / p0
    m2 = p2 / p0
    third = p3 / p0 - 3.0 * cent * m2 + 2.0 * cent * cent * cent  # E[(f - cent)^3]
    return cent, math.sqrt(max(m2 - cent * cent, 0.0)), math.copysign(abs(third) ** (1.0 / 3.0), third)


@numba.njit(cache=True, inline="always")
def _spectral_moments(y, dt, out):
    """``spec_cent``, ``spec_bw``, ``spec_skew`` of the whole window's signal ``y`` and ``spec_cent2`` of its
    second half [Hz] (:func:`_band_power_moments`; grid step ``dt`` [s])."""
    n = y.size
    cent, bw, skew = _band_power_moments(y, 0, n, dt)
    out[_SPEC_CENT] = cent
    out[_SPEC_CENT + 1] = bw
    out[_SPEC_SKEW] = skew
    out[_SPEC_CENT2] = _band_power_moments(y, n // 2, n, dt)[0]


@numba.njit(cache=True, inline="always")
def _rice_frequency(y, k_on, dt, sig_s):
    """``rms(d y/dt) / (2 pi rms(y))`` after the onset bin ``k_on`` (about the mean there) [Hz]; 0 without one,
    or when the signal there is within 3 smoothed-noise standard deviations."""
    n_grid = y.size
    if k_on >= n_grid - 2:
        return 0.0
    m2 = 0.0
    for b in range(k_on, n_grid):
        m2 += y[b]
    m2 /= n_grid - k_on
    v0 = 0.0
    v1 = 0.0
    for b in range(k_on, n_grid - 1):
        v0 += (y[b] - m2) ** 2
        v1 += ((y[b + 1] - y[b]) / dt) ** 2
    v0 /= n_grid - k_on - 1
    v1 /= n_grid - k_on - 1
    if not (v0 > 9.0 * sig_s * sig_s and v0 > 0.0):
        return 0.0
    return math.sqrt(v1 / v0) / (2.0 * math.pi)


@numba.njit(cache=True)
def _row_features(phase, a, half, omega, noise, n_grid, out):
    """Features of one cycle (the table of the module docstring). phase [rad] sorted; a [g]; noise [g]
    (NaN: estimated); out: one row."""
    out[_DELTA_A], n_in = _raw_delta_a(phase, a, half)
    if not noise == noise:
        noise = _sample_noise(phase, a, half)
    y = np.empty(n_grid)
    w2 = _smoothed_grid(phase, a, half, omega, n_grid, y)
    sig_s = noise * math.sqrt(w2)
    k_on = _stick_relative_features(y, sig_s, omega, half, out)
    _mean_relative_features(y, sig_s, half, omega, out)
    dt = half / n_grid / omega  # the grid's step in time [s]
    out[_RICE_FREQ] = _rice_frequency(y, k_on, dt, sig_s)
    _spectral_moments(y, dt, out)
    out[_NOISE] = noise
    out[_OMEGA] = omega
    out[_NOISE_SMOOTH] = sig_s


@numba.njit(cache=True)
def _batch_kernel(phase, a2, scale, half, omega, noise, n_grid, out):
    """Features of every row of ``a2`` (``a2 * scale`` in g; ``noise[r]`` [g], NaN: estimated); NaN rows where
    ``a2`` is not finite."""
    row = np.empty(phase.size)
    for r in range(a2.shape[0]):
        finite = True
        for i in range(phase.size):
            v = a2[r, i]
            if not np.isfinite(v):
                finite = False
                break
            row[i] = v * scale
        if finite:
            _row_features(phase, row, half, omega, noise[r], n_grid, out[r])
        else:
            out[r, :] = np.nan


@numba.njit(cache=True)
def _phase_status(phase, half, min_samples):
    """0: usable; 1: non-finite; 2: decreasing; 3: too few inside; 4: start/end missing. Also first/last inside."""
    first = np.nan
    last = np.nan
    n_in = 0
    for i in range(phase.size):
        p = phase[i]
        if not np.isfinite(p):
            return 1, first, last
        if i > 0 and p < phase[i - 1]:
            return 2, first, last
        if 0.0 <= p <= half:
            if n_in == 0:
                first = p
            last = p
            n_in += 1
    if n_in < min_samples:
        return 3, first, last
    if first > 0.1 * half or last < 0.9 * half:
        return 4, first, last
    return 0, first, last


@numba.njit(cache=True)
def _cycle_kernel(phase, az, t, omega, noise, half, min_samples, n_grid, scale, out):
    """:func:`cycle_features`'s checks and features in one call: ``out`` one row (``az * scale`` in g).

    ``omega`` [rad/s]: NaN takes it from ``t`` [s] and ``phase`` [rad] over the window.
    Returns ``(code, first, last, omega)``: 0 done; 1-4 as
    :func:`_phase_status`; 5 ``t`` does not increase; 6 the phase does not
    advance; 7 ``omega`` not finite and positive; 8 ``az`` not finite;
    9 the noise cannot be estimated.
    """
    first = np.nan
    last = np.nan
    code, first, last = _phase_status(phase, half, min_samples)
    if code != 0:
        return code, first, last, omega
    if math.isnan(omega):
        i0 = -1
        i1 = -1
        for i in range(phase.size):
            if 0.0 <= phase[i] <= half:
                if i0 < 0:
                    i0 = i
                i1 = i
        span = t[i1] - t[i0]
        if not (np.isfinite(span) and span > 0):
            return 5, first, last, omega
        omega = (phase[i1] - phase[i0]) / span
        if not omega > 0:
            return 6, first, last, omega
    if not (np.isfinite(omega) and omega > 0):
        return 7, first, last, omega
    row = np.empty(phase.size)
    for i in range(phase.size):
        v = az[i]
        if not np.isfinite(v):
            return 8, first, last, omega
        row[i] = v * scale
    if not noise == noise:
        noise = _sample_noise(phase, row, half)
        if not noise == noise:
            return 9, first, last, omega
    _row_features(phase, row, half, omega, noise, n_grid, out)
    return 0, first, last, omega


def _raise_phase(code: int, first: float, last: float, n_legs: int) -> None:
    """The ValueError of a :func:`_phase_status` code (none for 0)."""
    half = math.pi / n_legs
    if code == 1:
        raise ValueError("phase has non-finite values")
    if code == 2:
        raise ValueError("phase must be non-decreasing")
    if code == 3:
        raise ValueError(f"fewer than {MIN_SAMPLES} samples inside the feature window [0, {half:.4f}] rad")
    if code == 4:
        raise ValueError(
            f"phase covers [{first:.3f}, {last:.3f}] rad of the feature window "
            f"[0, {half:.3f}] rad of a {n_legs}-leg wheel: its start or end is missing"
        )


def smoothed_noise(noise: float, rate: float) -> float:
    """What a white sample noise of ``noise`` [g] at ``rate`` [Hz] leaves on the smoothed signal the features are
    taken on (their ``noise_smooth``) [g]: ``noise / sqrt(2 sqrt(pi) SMOOTH_TIME rate)``, the Gaussian kernel's
    effective number of samples. Within 1 % of what :func:`cycle_features` gives at 200-2000 Hz and 0.3-1.2
    rad/s (tested); NaN in, NaN out."""
    return noise / math.sqrt(2.0 * math.sqrt(math.pi) * SMOOTH_TIME * rate)


def sample_noise(theta_phase, az, n_legs: int = 4) -> float:
    """The IMU noise's standard deviation [g] of one cycle's samples (see the module docstring); NaN when
    too few samples lie where it is measured. ``theta_phase`` [rad] sorted; ``az`` [m/s^2]."""
    phase = np.ascontiguousarray(theta_phase, dtype=np.float64)
    a = np.ascontiguousarray(az, dtype=np.float64) / G
    return float(_sample_noise(phase, a, math.pi / n_legs))


def stance_noise(theta_phase, az, n_legs: int = 4) -> float:
    """The same second-difference measure as :func:`sample_noise` over the stance window ``[0, pi/nL]`` [g]; NaN
    when fewer than :data:`MIN_SAMPLES` samples lie there. The stick-slip signal adds to it (up to 1.5 times the
    rigid half's measure on clean cycles at 200 Hz, about 1.1 at 1 kHz): a check for a noise burst confined to
    the stance, not the noise the features are referred to. ``theta_phase`` [rad] sorted; ``az`` [m/s^2]."""
    phase = np.ascontiguousarray(theta_phase, dtype=np.float64)
    a = np.ascontiguousarray(az, dtype=np.float64) / G
    return float(_second_difference_noise(phase, a, 0.0, math.pi / n_legs, MIN_SAMPLES))


def features_batch(phase, az_2d, n_legs: int = 4, omega: float = DEFAULT_OMEGA, noise=None) -> np.ndarray:
    """Features of many leg cycles sampled on one phase grid.

    phase: ``(n,)`` leg phase of the samples [rad] relative to midstance,
        non-decreasing, covering the window ``[0, pi/n_legs]`` (samples
        outside it are used only to estimate the noise); may be uneven.
    az_2d: ``(B, n)`` vertical specific force [m/s^2] (gravity and any
        constant bias included or not), one row per cycle; or ``(n,)``.
    n_legs: number of legs ``nL`` [-] (the window is ``[0, pi/nL]``).
    omega: leg angular speed [rad/s] (the samples are taken as evenly paced in time).
    noise: the IMU noise's standard deviation [g], a scalar or one per row
        (None or NaN: estimated from each row, :func:`sample_noise`).

    Returns ``(B, len(FEATURE_NAMES))`` in the units of
    :data:`FEATURE_UNITS`. A row with any non-finite ``az`` gives a row of
    NaN (never a feature from corrupted data). Raises ``ValueError`` for a
    bad phase grid or shapes.
    """
    phase = np.ascontiguousarray(phase, dtype=np.float64)
    az_2d = np.asarray(az_2d, dtype=np.float64)
    if az_2d.ndim == 1:
        az_2d = az_2d[None, :]
    if phase.ndim != 1:
        raise ValueError(f"phase must be 1-D, got shape {phase.shape}")
    code, first, last = _phase_status(phase, math.pi / n_legs, MIN_SAMPLES)
    _raise_phase(code, first, last, n_legs)
    if az_2d.ndim != 2 or az_2d.shape[1] != phase.size:
        raise ValueError(f"az_2d must have shape (B, {phase.size}), got {az_2d.shape}")
    if not (math.isfinite(omega) and omega > 0):
        raise ValueError(f"omega={omega} rad/s must be positive")
    noise = np.broadcast_to(np.asarray(np.nan if noise is None else noise, dtype=np.float64), (az_2d.shape[0],))
    out = np.empty((az_2d.shape[0], _N_FEATURES))
    _batch_kernel(phase, az_2d, 1.0 / G, math.pi / n_legs, float(omega), np.ascontiguousarray(noise), N_GRID, out)
    return out


def cycle_features(theta_phase, az, t=None, n_legs: int = 4, omega: float | None = None,
                   noise: float | None = None) -> np.ndarray:
    """Features of one leg cycle: one row in the order of :data:`FEATURE_NAMES`.

    theta_phase: leg phase of the samples relative to midstance [rad]
        (the window is ``[0, pi/n_legs]``; samples of the rigid half before
        it, phase ``>= -pi/n_legs``, are used to estimate the noise); sorted,
        may be uneven.
    az: vertical specific force [m/s^2] (gravity and a constant bias allowed).
    t: sample times [s]; give the leg speed (``omega`` [rad/s] may be
        given instead; default 0.63 rad/s).
    n_legs: number of legs [-].
    noise: the IMU noise's standard deviation [g] (None: estimated from the
        samples, :func:`sample_noise`).

    Raises ``ValueError`` for unusable input (mismatched lengths, fewer
    than :data:`MIN_SAMPLES` samples in the window, unsorted or non-finite
    phase, the window's start or end missing, non-finite ``az``, time not
    increasing, a noise that cannot be estimated).
    """
    theta_phase = np.ascontiguousarray(theta_phase, dtype=np.float64)
    az = np.asarray(az, dtype=np.float64)
    if az.shape != theta_phase.shape:
        raise ValueError(f"theta_phase and az must have the same shape, got {theta_phase.shape} and {az.shape}")
    if omega is None and t is not None:
        t = np.asarray(t, dtype=np.float64)
        if t.shape != theta_phase.shape:
            raise ValueError(f"t and theta_phase must have the same shape, got {t.shape} and {theta_phase.shape}")
        om = math.nan  # from t
    else:
        om = float(DEFAULT_OMEGA if omega is None else omega)
        t = theta_phase  # not read
    if theta_phase.ndim != 1:
        raise ValueError(f"phase must be 1-D, got shape {theta_phase.shape}")
    nz = math.nan if noise is None else float(noise)
    # one compiled call (checks and features): no numpy overhead on a cycle's closing sample
    row = np.empty(_N_FEATURES)
    code, first, last, om = _cycle_kernel(theta_phase, az, t, om, nz, math.pi / n_legs, MIN_SAMPLES, N_GRID,
                                          1.0 / G, row)
    if code == 5:
        raise ValueError("t must increase over the window")
    if code == 6:
        raise ValueError("the leg phase does not advance over the window")
    _raise_phase(code, first, last, n_legs)
    if code == 7:
        raise ValueError(f"omega={om} rad/s must be positive")
    if code == 8:
        raise ValueError("az has non-finite values")
    if code == 9:
        raise ValueError("the noise cannot be estimated: too few samples")
    return row


__all__ = [
    "FEATURE_NAMES",
    "FEATURE_UNITS",
    "INDEX",
    "N_GRID",
    "analysis_grid",
    "cycle_features",
    "features_batch",
    "onset_threshold",
    "sample_noise",
    "stance_noise",
]
