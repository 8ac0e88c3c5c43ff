"""The model's prediction of logged leg cycles on a phase grid, for many candidates at once.

A logged cycle is the leg phase ``phi`` in ``[-pi/nL, pi/nL)`` (the stream
convention of :mod:`slipest.model.stream`): the rigid half (``phi < 0``,
the hub riding a planted spoke) then the stick-slip stance (``phi >= 0``).
The model's cycle is deterministic given the slip and the soil, so the
prediction for every cycle at one slip is one stance simulation.

Pipeline, mirroring the simulated stream (SI units; ``az`` is the specific
force with gravity, z up); arrays are ``(P candidates, G groups, ...)``:

1. :func:`stance_fine` integrates many stances in one compiled parallel loop
   (the project's kernel, :func:`slipest.model.kernel.integrate_stance`)
   and averages each stance's ``zH''`` over ``m`` uniform bins of leg angle
   ``[0, pi/nL)`` (the *fine grid*), so only ``(B, m)`` numbers leave the
   loop;
2. the caller lays a cycle out on an *extended* fine grid of true phase
   ``psi`` in ``[-2 pi/nL, pi/nL + margin)`` (:class:`Grid`): the previous
   cycle's stance (the source of the filter memory and of a positive
   encoder offset), the rigid half (:func:`rigid_batch`: kinematic
   ``-l (w^2 cos phi + w w' sin phi)``, ``l = lS - MH g/kS``), the stance,
   and the start of the next rigid half;
3. sensor effects act on it: the touchdown train (:func:`impact_batch`),
   the IMU low-pass (:func:`lowpass_batch`, in time along the grid);
4. :func:`bin_average_batch` averages the signal over the *analysis bins*
   of the logged phase (an encoder offset shifts the logged phase against
   the true one, ``phi_log = psi + offset``).

Everything is pure numpy/numba; nothing here knows about files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from slipest.features import bin_mean_fill
from slipest.model import kernel as K

#: Fine-grid bins per half cycle (``pi/nL`` of leg angle) [-].
FINE_PER_HALF = 500


@numba.njit(cache=True, parallel=True)
def _stance_fine_kernel(params, dt, max_steps, m, out, status):
    n_b = params.shape[0]
    for b in numba.prange(n_b):
        rec = np.empty((max_steps, 2))
        res = np.empty(K.N_RESULTS)
        K.integrate_stance(params[b], dt, max_steps, res, rec)
        status[b] = res[K.R_STATUS]
        n = int(res[K.R_N_STEPS])
        half = math.pi / params[b, K.P_NL]
        scale = m / half
        acc = np.zeros(m)
        cnt = np.zeros(m)
        for i in range(min(n, max_steps)):
            j = int(rec[i, 0] * scale)
            if j >= m:
                j = m - 1
            acc[j] += rec[i, 1]
            cnt[j] += 1.0
        bin_mean_fill(acc, cnt)
        for j in range(m):
            out[b, j] = acc[j]


def stance_fine(params: np.ndarray, dt: float = 1e-4, m: int = FINE_PER_HALF) -> tuple[np.ndarray, np.ndarray]:
    """Stance ``zH''`` [m/s^2] (gravity-free) averaged over ``m`` uniform leg-angle bins of ``[0, pi/nL)``.

    ``params``: kernel parameter matrix ``(B, N_PARAMS)``. Returns
    ``(az_fine (B, m), status (B,))``; rows whose status is not OK are NaN.
    """
    params = np.ascontiguousarray(params, dtype=np.float64)
    if params.ndim != 2 or params.shape[1] != K.N_PARAMS:
        raise ValueError(f"parameter matrix must have shape (B, {K.N_PARAMS})")
    out = np.empty((params.shape[0], m))
    status = np.empty(params.shape[0])
    if params.shape[0]:
        angle = float(np.max(np.pi / params[:, K.P_NL]))
        omega = float(np.min(params[:, K.P_OMEGA] * (1.0 - params[:, K.P_RIPPLE_A])))
        max_steps = int(math.ceil(angle / (omega * dt))) + 2
        _stance_fine_kernel(params, float(dt), max_steps, int(m), out, status)
    status = status.astype(np.int64)
    out[status != K.STATUS_OK] = np.nan
    return out, status


@dataclass(frozen=True)
class Grid:
    """The extended fine grid of one cycle and the analysis bins.

    n_legs [-]; m: fine bins per half cycle; nb_half: analysis bins per
    half cycle (``m`` a multiple of it); margin_halves: how much of the next
    cycle the grid covers, in half cycles. ``psi``: fine-bin centres [rad]
    of true phase relative to the cycle's midstance, from ``-2 pi/nL``
    (previous stance) to ``pi/nL + margin``.
    """

    n_legs: int
    m: int = FINE_PER_HALF
    nb_half: int = 125
    margin_halves: float = 0.3

    def __post_init__(self):
        if self.m % self.nb_half:
            raise ValueError("the fine bins per half cycle must be a multiple of the analysis bins")

    @property
    def half(self) -> float:
        return math.pi / self.n_legs

    @property
    def dpsi(self) -> float:
        return self.half / self.m

    @property
    def n_margin(self) -> int:
        return int(round(self.margin_halves * self.m))

    @property
    def n_ext(self) -> int:
        return 3 * self.m + self.n_margin

    @property
    def psi(self) -> np.ndarray:
        return -2 * self.half + (np.arange(self.n_ext) + 0.5) * self.dpsi

    @property
    def nb(self) -> int:
        """Analysis bins per cycle."""
        return 2 * self.nb_half

    @property
    def bin_edges(self) -> np.ndarray:
        """Edges [rad] of the analysis bins of logged phase over ``[-pi/nL, pi/nL)``."""
        return np.linspace(-self.half, self.half, self.nb + 1)

    @property
    def bin_centres(self) -> np.ndarray:
        e = self.bin_edges
        return 0.5 * (e[1:] + e[:-1])


def psi_time(grid: Grid, omega: float) -> np.ndarray:
    """Time [s] of the extended grid's centres relative to the cycle's start (phase ``-pi/nL``), constant speed."""
    return (grid.psi + grid.half) / omega


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


# --- batched versions (one row per candidate x group) --------------------------------------------


def rigid_batch(grid: Grid, leg: np.ndarray, omega: np.ndarray, ripple_a=None, ripple_ph=None) -> np.ndarray:
    """Rigid-half ``zH''`` [m/s^2] for candidates ``leg (P,)`` [m] and groups ``omega (G,)`` or ``(P, G)`` [rad/s].

    Optional drive ripple per candidate (``ripple_a``, ``ripple_ph`` ``(P,)``).
    Returns ``(P, G, m)``.
    """
    phi = -grid.half + (np.arange(grid.m) + 0.5) * grid.dpsi
    leg = np.asarray(leg, dtype=float)[:, None, None]
    w0 = np.asarray(omega, dtype=float)
    w0 = np.broadcast_to(w0, (leg.shape[0],) + w0.shape[-1:])[:, :, None]
    if ripple_a is None:
        return -leg * np.cos(phi)[None, None, :] * w0**2
    a = np.asarray(ripple_a, dtype=float)[:, None, None]
    arg = grid.n_legs * phi[None, None, :] + np.asarray(ripple_ph, dtype=float)[:, None, None]
    w = w0 * (1.0 + a * np.sin(arg))
    dw = w0 * a * grid.n_legs * np.cos(arg)
    return -leg * (np.cos(phi)[None, None, :] * w * w + np.sin(phi)[None, None, :] * w * dw)


def impact_batch(grid: Grid, omega: float, amplitude, tau, freq) -> np.ndarray:
    """The touchdown train for candidates (arrays ``(P,)``): ``(P, n_ext)`` [m/s^2], constant leg speed.

    Every boundary ``k T`` (``T = 2 pi/(nL omega)``) up to a point contributes
    ``A exp(-s/tau) sin(2 pi f s)``, ``s`` its age; summed over the whole past
    (a geometric series): ``Im(A exp(l s0) / (1 - exp(l T)))`` with
    ``l = -1/tau + 2 pi i f`` and ``s0`` the age of the latest boundary.
    """
    amplitude = np.asarray(amplitude, dtype=float)[:, None]
    tau = np.asarray(tau, dtype=float)[:, None]
    freq = np.asarray(freq, dtype=float)[:, None]
    t = psi_time(grid, omega)[None, :]
    period = 2 * grid.half / omega
    s0 = t - np.floor(t / period) * period
    lam = -1.0 / tau + 2j * math.pi * freq
    return amplitude * np.imag(np.exp(lam * s0) / (1.0 - np.exp(lam * period)))


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


def lowpass_batch(x: np.ndarray, grid: Grid, omega: float, cutoff, order) -> np.ndarray:
    """Butterworth low-pass of ``x (P, G, n)`` with a cut-off [Hz] and integer order per candidate ``(P,)``.

    Candidates whose cut-off is not below the Nyquist frequency give NaN.
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


def bin_average_batch(grid: Grid, x: np.ndarray, offset=None) -> np.ndarray:
    """:func:`bin_average` of ``x (P, G, n_ext)`` with an encoder offset per candidate ``(P,)`` [rad] (or none)."""
    P, G, n = x.shape
    if offset is None:
        r = grid.m // grid.nb_half
        return x[:, :, grid.m : 3 * grid.m].reshape(P, G, grid.nb, r).mean(axis=3)
    offset = np.asarray(offset, dtype=float)
    pos = (grid.bin_edges[None, :] - offset[:, None] + 2 * grid.half) / grid.dpsi  # (P, nb+1)
    pos = np.clip(pos, 0.0, n - 1e-9)
    i = np.floor(pos).astype(np.int64)
    frac = pos - i
    csum = np.concatenate([np.zeros((P, G, 1)), np.cumsum(x, axis=2)], axis=2)
    idx = np.broadcast_to(i[:, None, :], (P, G, i.shape[1]))
    c_at = np.take_along_axis(csum, idx, axis=2) + frac[:, None, :] * np.take_along_axis(x, idx, axis=2)
    return np.diff(c_at, axis=2) / np.diff(pos, axis=1)[:, None, :]
