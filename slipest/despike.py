"""Isolated outliers in a leg cycle's acceleration: found, to be left out of its features (pure computation).

A glitch sample (EMI, a loose connector, a stone on the hub) is one or two
samples far from their neighbours; the stick-slip signal itself, even at
its sharpest (the break-away, a bounce), moves over many samples. The rule
is a Hampel filter on the residual from a local median:

* ``r[i] = az[i] - median(az[i-2 .. i+2])`` (the median of five samples
  follows steps, slopes and extrema and ignores up to two outliers);
* the residual's local scale ``s`` is 1.4826 times the median ``|r|`` of
  blocks of :data:`BLOCK` samples, the largest of a block and its two
  neighbours (so an oscillation or a noisy stretch raises the bar around
  it);
* sample ``i`` is an outlier when ``|r[i]| > max(K s, FLOOR)``
  (:data:`K` = 6, :data:`FLOOR` = 0.25 g: smaller glitches barely move the
  time-smoothed features).
* the two samples at each end of the cycle are not judged: their median
  is one-sided, so a real step there (the next leg's touchdown, which a
  rounded leg angle can put in the cycle's last sample) would look like a
  spike; a glitch there touches one sample at the edge of the window.

On clean simulated cycles over the estimator's envelope (IMU 200-2000 Hz,
noise 0-0.03 g) it flags no sample (``tests/test_despike.py``); at 1 kHz it
finds every 3-15 g spike. At low rates the stance oscillation spans few
samples and raises the bar: a spike smaller than about four times the
oscillation's amplitude is then kept.

Units: ``az`` in any unit, ``floor`` in the same unit.
"""

from __future__ import annotations

import numba
import numpy as np

from slipest.units import G

#: Samples per block of the local scale [-].
BLOCK = 32
#: Threshold in local scales [-].
K = 6.0
#: Smallest residual called an outlier [m/s^2] (0.25 g).
FLOOR = 0.25 * G


@numba.njit(cache=True, inline="always")
def _med3(a, b, c):
    return max(min(a, b), min(max(a, b), c))


@numba.njit(cache=True, inline="always")
def _med5(a, b, c, d, e):
    """Median of five (six comparisons: the smallest of four is dropped, twice)."""
    if a > b:
        a, b = b, a
    if c > d:
        c, d = d, c
    if a > c:
        a, b, c, d = c, d, a, b
    a = e
    if a > b:
        a, b = b, a
    if a > c:
        a, b, c, d = c, d, a, b
    return min(b, c)


@numba.njit(cache=True)
def _median5(a, i, n):
    """Median of ``a[i-2 .. i+2]`` clipped to ``[0, n)`` (``n >= 3``; no allocation)."""
    lo = max(0, i - 2)
    m = min(n, i + 3) - lo
    if m == 5:
        return _med5(a[lo], a[lo + 1], a[lo + 2], a[lo + 3], a[lo + 4])
    if m == 4:
        w0, w1, w2, w3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
        return 0.5 * (w0 + w1 + w2 + w3 - max(max(w0, w1), max(w2, w3)) - min(min(w0, w1), min(w2, w3)))
    return _med3(a[lo], a[lo + 1], a[lo + 2])


@numba.njit(cache=True)
def _outliers(az, k, floor, block, out):
    n = az.size
    r = np.empty(n)
    top = 0.0
    for i in range(n):
        r[i] = az[i] - _median5(az, i, n)
        if abs(r[i]) > top:
            top = abs(r[i])
    count = 0
    for i in range(n):
        out[i] = False
    if not top > floor:  # no residual above the floor: no outlier whatever the local scale (most clean cycles)
        return count
    nb = (n + block - 1) // block
    bs = np.empty(nb)
    work = np.empty(block)
    for b in range(nb):
        m = min(n, (b + 1) * block) - b * block
        for j in range(m):
            work[j] = abs(r[b * block + j])
        bs[b] = np.median(work[:m])
    for i in range(2, n - 2):  # the two samples at each end have a one-sided median: a step there is no spike
        b = i // block
        s = bs[b]
        if b > 0 and bs[b - 1] > s:
            s = bs[b - 1]
        if b + 1 < nb and bs[b + 1] > s:
            s = bs[b + 1]
        out[i] = abs(r[i]) > max(k * 1.4826 * s, floor)
        if out[i]:
            count += 1
    return count


def outliers(az, k: float = K, floor: float = FLOOR, block: int = BLOCK) -> np.ndarray:
    """Mask of the isolated outliers of ``az`` (finite samples in time order; see the module docstring).
    Fewer than five samples: none."""
    az = np.ascontiguousarray(az, dtype=np.float64)
    out = np.zeros(az.size, dtype=np.bool_)
    if az.size >= 5:
        _outliers(az, float(k), float(floor), int(block), out)
    return out


__all__ = ["BLOCK", "K", "FLOOR", "outliers"]
