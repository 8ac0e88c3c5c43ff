"""Per-leg-cycle features of the hub's vertical acceleration (pure computation).

A leg cycle's *feature window* is the propulsive half-stance, leg phase
``theta_phase`` from 0 (midstance) to ``pi/nL`` [rad] (what
:class:`slipest.segmentation.LegCycle` hands over). Inside it the model's
hub rides smoothly while the foot sticks, then, from the break-away,
oscillates (stick-slip) with an amplitude that usually grows towards the
end of the stance (``shared/spec/stickslip-model.md``, Fig. 5.5). What
carries what (spec section 5 and the project's sweeps): the break-away
angle mostly tracks slip (and ``kS``, ``phiS``), the oscillation frequency
tracks ``kS``, the amplitude and its growth over the stance depend on all
of slip, ``kS`` and ``dphi``.

=============  =====  =========================================================
name           unit   meaning
=============  =====  =========================================================
delta_a        g      ``Da``: max minus min of the raw ``az`` samples in the window
peak_pos       g      max of ``az`` above the stick level (analysis grid)
peak_neg       g      stick level minus min of ``az`` (analysis grid)
rms            g      RMS of ``az`` about the window mean
rms_q1..q4     g      the same per quarter of the window (about the window mean)
onset          rad    break-away angle: first phase where the smoothed ``|az -
                      stick level|`` exceeds the onset threshold; ``pi/nL`` when
                      it never does (no stick-slip)
energy_q10     rad    phases by which 10/50/90 % of the energy
energy_q50     rad      ``sum (az - stick level)^2`` over the window has
energy_q90     rad      accumulated
zc_rate        Hz     crossings of the window mean (with hysteresis) per second
osc_freq       Hz     ``(n - 1) / (2 dt)`` for the ``n`` hysteresis crossings
                      spanning ``dt`` seconds; 0 when ``n < 2``
rice_freq      Hz     ``rms(d az/dt) / (2 pi rms(az))`` after the onset (smoothed
                      signal, about its mean): a mean oscillation frequency; 0
                      when there is no onset
n_crossings    -      number of hysteresis crossings over the window
noise          g      the sample noise's standard deviation, from the median
                      absolute second difference of the raw samples
stick_mean     g      mean of ``az`` minus the stick level from the end of the
                      stick-level span to :data:`STICK_SPAN` rad, or to 0.01 rad
                      before the onset if that comes first (0 when that leaves
                      fewer than 4 bins): the hub's motion on the stuck foot,
                      which depends on slip and ``kS`` but not on friction
=============  =====  =========================================================

Gravity and bias removal, made explicit: the IMU reports the specific force
(``+g`` at rest) plus an unknown constant bias. No feature depends on either:
``delta_a`` and ``noise`` are differences; ``peak_pos``, ``peak_neg``,
``onset`` and the energy phases are taken relative to the **stick level**,
the mean of ``az`` over the first :data:`STICK_FRACTION` of the window
(before the earliest break-away of the spec's ranges: the hub then rides
smoothly on the stuck foot); the RMS features, the crossings and the
frequencies are taken about the **window mean** (``rice_freq``: about the
mean after the onset). Adding a constant to ``az`` changes no feature
(tested).

Uneven sampling: the raw samples are averaged into the :data:`N_GRID` bins
of a uniform *analysis grid* over ``[0, pi/nL]`` (empty bins are filled by
linear interpolation between their neighbours), and every feature except
``delta_a`` and ``noise`` is computed there. Samples outside the window are
ignored. Averaging (not point interpolation) keeps the features of a cycle
sampled at 1 kHz and of the same cycle sampled unevenly close together.

Frequencies are in Hz and need the leg speed: :func:`cycle_features` takes
it from the samples' ``t`` and ``theta_phase``; :func:`features_batch` is
given ``omega`` [rad/s] (default: the model's 0.63 rad/s).

Both entry points run the same compiled routine (numba), about 30 us a
cycle at 1 kHz.
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
)

#: Unit of each feature, same order as :data:`FEATURE_NAMES`.
FEATURE_UNITS = ("g",) * 8 + ("rad",) * 4 + ("Hz",) * 3 + ("-", "g", "g")

#: Column index of each feature.
INDEX = {name: j for j, name in enumerate(FEATURE_NAMES)}

#: Number of bins of the uniform analysis grid over the window [-].
N_GRID = 512
#: Fraction of the window, from its start, whose mean is the stick level [-].
STICK_FRACTION = 0.025
#: Length of the moving average applied before the onset test and ``rice_freq`` [grid bins].
SMOOTH_BINS = 4
#: Onset threshold: at least this much [g] ...
ONSET_FLOOR_G = 0.03
#: ... and at least this many standard deviations of the smoothed noise [-].
ONSET_SIGMAS = 5.0
#: Hysteresis half-band of the crossings: this fraction of the window's RMS ...
HYSTERESIS_FRACTION = 0.3
#: ... but at least this much [g].
HYSTERESIS_FLOOR_G = 0.03
#: End of the span of ``stick_mean`` [rad] (before the break-away for most of the spec's ranges).
STICK_SPAN = 0.1
#: Fewest samples a window may have [-].
MIN_SAMPLES = 16
#: Default leg speed [rad/s] for :func:`features_batch` (the model's omega).
DEFAULT_OMEGA = 0.63

_N_FEATURES = len(FEATURE_NAMES)


def analysis_grid(n_legs: int = 4, n: int = N_GRID) -> np.ndarray:
    """Centres [rad] of the ``n`` bins of the uniform analysis grid over ``[0, pi/n_legs]``."""
    half = math.pi / n_legs
    return (np.arange(n) + 0.5) * (half / n)


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


# Column of each feature in a row, as compile-time constants of the kernels below.
_DELTA_A, _PEAK_POS, _PEAK_NEG, _RMS = INDEX["delta_a"], INDEX["peak_pos"], INDEX["peak_neg"], INDEX["rms"]
_RMS_Q1, _ONSET, _ENERGY_Q10 = INDEX["rms_q1"], INDEX["onset"], INDEX["energy_q10"]
_ZC_RATE, _OSC_FREQ, _RICE_FREQ = INDEX["zc_rate"], INDEX["osc_freq"], INDEX["rice_freq"]
_N_CROSSINGS, _NOISE, _STICK_MEAN = INDEX["n_crossings"], INDEX["noise"], INDEX["stick_mean"]
_ENERGY_TARGETS = (0.1, 0.5, 0.9)


@numba.njit(cache=True, inline="always")
def _raw_features(phase, a, half, out):
    """``delta_a`` and ``noise`` [g] from the raw samples inside the window; returns (noise, samples inside)."""
    n_raw = phase.size
    amax = -np.inf
    amin = np.inf
    n_in = 0
    for i in range(n_raw):
        if 0.0 <= phase[i] <= half:
            n_in += 1
            if a[i] > amax:
                amax = a[i]
            if a[i] < amin:
                amin = a[i]
    out[_DELTA_A] = amax - amin
    d2 = np.empty(max(n_raw - 2, 1))
    m = 0
    for i in range(1, n_raw - 1):
        if 0.0 <= phase[i] <= half:
            d2[m] = abs(a[i + 1] - 2.0 * a[i] + a[i - 1])
            m += 1
    noise = 1.4826 * np.median(d2[:m]) / math.sqrt(6.0) if m > 0 else 0.0
    out[_NOISE] = noise
    return noise, n_in


@numba.njit(cache=True, inline="always")
def _analysis_grid_means(phase, a, half, n_grid):
    """The samples inside the window averaged into the ``n_grid`` bins of the analysis grid (gaps filled)."""
    y = np.zeros(n_grid)
    cnt = np.zeros(n_grid)
    scale = n_grid / half
    for i in range(phase.size):
        if 0.0 <= phase[i] <= half:
            b = int(phase[i] * scale)
            if b >= n_grid:
                b = n_grid - 1
            y[b] += a[i]
            cnt[b] += 1.0
    bin_mean_fill(y, cnt)
    return y


@numba.njit(cache=True, inline="always")
def _moving_average(y):
    """Centred moving average over ``SMOOTH_BINS`` bins, shrinking at the edges."""
    n_grid = y.size
    ys = np.empty(n_grid)
    h0 = SMOOTH_BINS // 2
    for b in range(n_grid):
        lo = max(0, b - h0)
        hi = min(n_grid, b - h0 + SMOOTH_BINS)
        s = 0.0
        for g in range(lo, hi):
            s += y[g]
        ys[b] = s / (hi - lo)
    return ys


@numba.njit(cache=True, inline="always")
def _onset_bin(ys, stick, thr, dphase, half):
    """First bin where the smoothed signal leaves the stick level by more than ``thr``, and the onset phase
    [rad] interpolated to the crossing (``(n_grid, half)`` when it never does)."""
    n_grid = ys.size
    prev = 0.0
    for b in range(n_grid):
        v = abs(ys[b] - stick)
        if v > thr:
            c = (b + 0.5) * dphase
            if b > 0 and v > prev:
                frac = (thr - prev) / (v - prev)
                c = (b - 0.5 + min(max(frac, 0.0), 1.0)) * dphase
            return b, c
        prev = v
    return n_grid, half


@numba.njit(cache=True, inline="always")
def _stick_relative_features(y, ys, noise, n_in, half, out):
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
    per_point = max(n_in / n_grid, 1.0) * SMOOTH_BINS
    thr = max(ONSET_FLOOR_G, ONSET_SIGMAS * noise / math.sqrt(per_point))
    k_on, onset = _onset_bin(ys, stick, thr, dphase, half)
    out[_ONSET] = onset
    k_end = min(int(STICK_SPAN / dphase), int((onset - 0.01) / dphase))
    if k_end - n_stick >= 4:
        acc = 0.0
        for b in range(n_stick, k_end):
            acc += y[b] - stick
        out[_STICK_MEAN] = acc / (k_end - n_stick)
    else:
        out[_STICK_MEAN] = 0.0
    etot = 0.0
    for b in range(n_grid):
        etot += (y[b] - stick) ** 2
    for q in range(3):
        if etot <= 0.0:
            out[_ENERGY_Q10 + q] = _ENERGY_TARGETS[q] * half
            continue
        acc = 0.0
        res = half
        for b in range(n_grid):
            acc += (y[b] - stick) ** 2
            if acc >= _ENERGY_TARGETS[q] * etot:
                res = (b + 0.5) * dphase
                break
        out[_ENERGY_Q10 + q] = res
    return k_on


@numba.njit(cache=True, inline="always")
def _mean_relative_features(y, duration, dphase, omega, out):
    """RMS (whole window and quarters) about the window mean, and the hysteresis crossings and frequencies."""
    n_grid = y.size
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
        out[_RMS_Q1 + qi] = math.sqrt(sq / (hi - lo))
    rms = math.sqrt(sq_all / n_grid)
    out[_RMS] = rms
    hband = max(HYSTERESIS_FRACTION * rms, HYSTERESIS_FLOOR_G)
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
    out[_ZC_RATE] = n_cross / duration
    span = (lastc - first) * dphase / omega
    out[_OSC_FREQ] = (n_cross - 1) / (2.0 * span) if (n_cross >= 2 and span > 0) else 0.0


@numba.njit(cache=True, inline="always")
def _rice_frequency(ys, k_on, dt):
    """``rms(d ys/dt) / (2 pi rms(ys))`` after the onset bin ``k_on`` (about the mean there) [Hz]; 0 without one."""
    n_grid = ys.size
    if k_on >= n_grid - 2:
        return 0.0
    m2 = 0.0
    for b in range(k_on, n_grid):
        m2 += ys[b]
    m2 /= n_grid - k_on
    v0 = 0.0
    v1 = 0.0
    for b in range(k_on, n_grid - 1):
        v0 += (ys[b] - m2) ** 2
        v1 += ((ys[b + 1] - ys[b]) / dt) ** 2
    v0 /= n_grid - k_on - 1
    v1 /= n_grid - k_on - 1
    return math.sqrt(v1 / v0) / (2.0 * math.pi) if v0 > 0 else 0.0


@numba.njit(cache=True)
def _row_features(phase, a, half, omega, n_grid, out):
    """Features of one cycle (the table of the module docstring). phase [rad] sorted; a [g]; out: one row."""
    noise, n_in = _raw_features(phase, a, half, out)
    y = _analysis_grid_means(phase, a, half, n_grid)
    ys = _moving_average(y)
    k_on = _stick_relative_features(y, ys, noise, n_in, half, out)
    dphase = half / n_grid
    _mean_relative_features(y, half / omega, dphase, omega, out)
    out[_RICE_FREQ] = _rice_frequency(ys, k_on, dphase / omega)


@numba.njit(cache=True)
def _batch_kernel(phase, a2, scale, half, omega, n_grid, out):
    """Features of every row of ``a2`` (``a2 * scale`` in g); NaN rows where ``a2`` is not finite."""
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
            _row_features(phase, row, half, omega, n_grid, out[r])
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
def _cycle_kernel(phase, az, t, omega, half, min_samples, n_grid, scale, out):
    """:func:`cycle_features`'s checks and features in one call: ``out`` one row (``az * scale`` in g).

    ``omega`` [rad/s]: NaN takes it from ``t`` [s] and ``phase`` [rad].
    Returns ``(code, first, last, omega)``: 0 done; 1-4 as
    :func:`_phase_status`; 5 ``t`` does not increase; 6 the phase does not
    advance; 7 ``omega`` not finite and positive; 8 ``az`` not finite.
    """
    first = np.nan
    last = np.nan
    if math.isnan(omega):
        span = t[t.size - 1] - t[0] if t.size else 0.0
        if not (np.isfinite(span) and span > 0):
            return 5, first, last, omega
        omega = (phase[phase.size - 1] - phase[0]) / span
        if not omega > 0:
            return 6, first, last, omega
    code, first, last = _phase_status(phase, half, min_samples)
    if code != 0:
        return code, first, last, omega
    if not (np.isfinite(omega) and omega > 0):
        return 7, first, last, omega
    row = np.empty(phase.size)
    for i in range(phase.size):
        v = az[i]
        if not np.isfinite(v):
            return 8, first, last, omega
        row[i] = v * scale
    _row_features(phase, row, half, omega, n_grid, out)
    return 0, first, last, omega


def _check_phase(phase: np.ndarray, n_legs: int) -> None:
    if phase.ndim != 1:
        raise ValueError(f"phase must be 1-D, got shape {phase.shape}")
    half = math.pi / n_legs
    code, first, last = _phase_status(phase, half, MIN_SAMPLES)
    _raise_phase(code, first, last, n_legs)


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


def features_batch(phase, az_2d, n_legs: int = 4, omega: float = DEFAULT_OMEGA) -> np.ndarray:
    """Features of many leg cycles sampled on one phase grid.

    phase: ``(n,)`` leg phase of the samples [rad] relative to midstance,
        non-decreasing, covering the window ``[0, pi/n_legs]`` (samples
        outside it are ignored); may be uneven.
    az_2d: ``(B, n)`` vertical specific force [m/s^2] (gravity and any
        constant bias included or not), one row per cycle; or ``(n,)``.
    n_legs: number of legs ``nL`` [-] (the window is ``[0, pi/nL]``).
    omega: mean leg angular speed [rad/s], to express frequencies in Hz.

    Returns ``(B, len(FEATURE_NAMES))`` in the units of
    :data:`FEATURE_UNITS`. A row with any non-finite ``az`` gives a row of
    NaN (never a feature from corrupted data). Raises ``ValueError`` for a
    bad phase grid or shapes.
    """
    phase = np.ascontiguousarray(phase, dtype=np.float64)
    az_2d = np.asarray(az_2d, dtype=np.float64)
    if az_2d.ndim == 1:
        az_2d = az_2d[None, :]
    _check_phase(phase, n_legs)
    if az_2d.ndim != 2 or az_2d.shape[1] != phase.size:
        raise ValueError(f"az_2d must have shape (B, {phase.size}), got {az_2d.shape}")
    if not (math.isfinite(omega) and omega > 0):
        raise ValueError(f"omega={omega} rad/s must be positive")
    out = np.empty((az_2d.shape[0], _N_FEATURES))
    _batch_kernel(phase, az_2d, 1.0 / G, math.pi / n_legs, float(omega), N_GRID, out)
    return out


def cycle_features(theta_phase, az, t=None, n_legs: int = 4, omega: float | None = None) -> np.ndarray:
    """Features of one leg cycle's window: one row in the order of :data:`FEATURE_NAMES`.

    theta_phase: leg phase of the samples relative to midstance [rad]
        (the window is ``[0, pi/n_legs]``); sorted, may be uneven.
    az: vertical specific force [m/s^2] (gravity and a constant bias allowed).
    t: sample times [s]; gives the leg speed for the frequencies
        (``omega`` [rad/s] may be given instead; default 0.63 rad/s).
    n_legs: number of legs [-].

    Raises ``ValueError`` for unusable input (mismatched lengths, fewer
    than :data:`MIN_SAMPLES` samples in the window, unsorted or non-finite
    phase, the window's start or end missing, non-finite ``az``, time not
    increasing).
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
    # one compiled call (checks and features): the same as features_batch on one row, without its overhead
    # on a cycle's closing sample
    row = np.empty(_N_FEATURES)
    code, first, last, om = _cycle_kernel(theta_phase, az, t, om, math.pi / n_legs, MIN_SAMPLES, N_GRID, 1.0 / G, row)
    if code == 5:
        raise ValueError("t must increase over the window")
    if code == 6:
        raise ValueError("the leg phase does not advance over the window")
    _raise_phase(code, first, last, n_legs)
    if code == 7:
        raise ValueError(f"omega={om} rad/s must be positive")
    if code == 8:
        raise ValueError("az has non-finite values")
    return row


__all__ = [
    "FEATURE_NAMES",
    "FEATURE_UNITS",
    "INDEX",
    "N_GRID",
    "analysis_grid",
    "cycle_features",
    "features_batch",
]
