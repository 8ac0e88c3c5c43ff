"""``touchdown_impact``: a decaying hub transient after every touchdown (continuous sensor effect)."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize

from slipest.model.effects.base import Effect, FitParam, ParamSpec
from slipest.model.params import DEFAULT_LEGS, StickSlipParams


def impact_response(tau_since, amplitude, tau, freq, onset=0.0):
    """The touchdown transient ``A exp(-s/tau) sin(2 pi f s + onset)`` at ``s >= 0`` [s], 0 before [m/s^2]."""
    s = np.asarray(tau_since, dtype=float)
    out = np.zeros_like(s)
    on = s >= 0
    out[on] = amplitude * np.exp(-s[on] / tau) * np.sin(2 * math.pi * freq * s[on] + onset)
    return out


class TouchdownImpact:
    """A decaying transient after every cycle boundary (leg phase ``-pi/nL``) ("continuous" stage).

    Boundaries are found from ``theta`` (unwrapped, 0 at midstances, legs
    ``n_legs`` apart); the stream's first sample counts as a boundary when
    it sits on one (the first leg touching down). A boundary is placed where
    ``theta`` crosses it, interpolated between the samples on either side,
    also across two chunks (so the stream is the same however it is
    chunked). Transients still ringing at the end of a chunk carry over into
    the next.
    """

    domain = "continuous"

    def __init__(self, amplitude: float, tau: float, freq: float, n_legs: int = DEFAULT_LEGS, onset: float = 0.0):
        self.amplitude = float(amplitude)
        self.tau = float(tau)
        self.freq = float(freq)
        self.onset = float(onset)
        self.n_legs = int(n_legs)
        self._last_k = None
        self._last_sample = None  # (t, theta) of the previous chunk's last sample
        self._active: list[float] = []  # boundary times still ringing [s]

    def configure(self, params: StickSlipParams):
        """Take the leg count from the model parameters."""
        self.n_legs = int(params.nL)

    def _crossing(self, k, t0, th0, t1, th1) -> float:
        """The time [s] ``theta`` crosses boundary ``k``, interpolated between samples ``(t0, th0)`` and
        ``(t1, th1)``."""
        th_b = k * (2 * math.pi / self.n_legs) - math.pi / self.n_legs
        frac = (th_b - th0) / (th1 - th0) if th1 != th0 else 1.0
        return float(t0 + frac * (t1 - t0))

    def apply(self, t, az, theta, rng):
        if len(t) == 0:
            return az, theta
        step = 2 * math.pi / self.n_legs
        k = np.floor((np.asarray(theta) + math.pi / self.n_legs) / step + 1e-9).astype(np.int64)
        times = []
        if self._last_k is None:
            phase0 = theta[0] + math.pi / self.n_legs - k[0] * step
            if abs(phase0) < 1e-6:
                times.append(float(t[0]))
        elif k[0] != self._last_k:  # crossed between the previous chunk's last sample and this one's first
            t_prev, th_prev = self._last_sample
            times.append(self._crossing(k[0], t_prev, th_prev, float(t[0]), float(theta[0])))
        for j in np.flatnonzero(np.diff(k) != 0):
            times.append(self._crossing(k[j + 1], t[j], theta[j], t[j + 1], theta[j + 1]))
        self._last_k = int(k[-1])
        self._last_sample = (float(t[-1]), float(theta[-1]))
        active = self._active + times
        out = np.array(az, dtype=float, copy=True)
        horizon = 12.0 * self.tau  # exp(-12) ~ 6e-6 of the amplitude: done (cut at that age, however chunked)
        for tb in active:
            sel = (t >= tb) & (t - tb < horizon)
            if sel.any():
                out[sel] += impact_response(t[sel] - tb, self.amplitude, self.tau, self.freq, self.onset)
        self._active = [tb for tb in active if t[-1] - tb < horizon]
        return out, theta


def _unit_train(s0, period, tau, freq):
    """``exp(l s0) / (1 - exp(l T))``, ``l = -1/tau + 2 pi i f``: the sum over every past boundary (complex, broadcast).

    ``s0`` [s]: the age of the latest boundary; ``T`` [s]: the boundaries'
    spacing. ``Im`` of it is the train of ``exp(-s/tau) sin(2 pi f s)``,
    ``Re`` the train of ``exp(-s/tau) cos(2 pi f s)``.
    """
    lam = -1.0 / tau + 2j * math.pi * freq
    return np.exp(lam * s0) / (1.0 - np.exp(lam * period))


def impact_batch(grid, omega: float, amplitude, tau, freq, onset=0.0) -> np.ndarray:
    """The touchdown train on the extended grid for candidates (arrays ``(P,)``): ``(P, n_ext)`` [m/s^2].

    Constant leg speed ``omega`` [rad/s]. Every boundary ``k T``
    (``T = 2 pi/(nL omega)``) up to a point contributes ``A exp(-s/tau)
    sin(2 pi f s + onset)``, ``s`` its age; summed over the whole past (a
    geometric series): ``Im(A exp(i onset) exp(l s0) / (1 - exp(l T)))`` with
    ``l = -1/tau + 2 pi i f`` and ``s0`` the age of the latest boundary.
    """
    amplitude = np.asarray(amplitude, dtype=float)[:, None]
    tau = np.asarray(tau, dtype=float)[:, None]
    freq = np.asarray(freq, dtype=float)[:, None]
    onset = np.broadcast_to(np.asarray(onset, dtype=float), tau.shape[:1])[:, None]
    return amplitude * np.imag(np.exp(1j * onset) * impact_basis(grid, omega, tau[:, 0], freq[:, 0]))


def impact_basis(grid, omega: float, tau, freq) -> np.ndarray:
    """The complex unit train ``(P, n_ext)`` on the extended grid (see :func:`impact_batch`): ``Im`` is the
    train of ``sin(2 pi f s)`` transients, ``Re`` that of ``cos(2 pi f s)`` ones, for ``tau, freq (P,)``."""
    t = grid.time(omega)[None, :]
    period = 2 * grid.half / omega
    s0 = t - np.floor(t / period) * period
    return _unit_train(s0, period, np.asarray(tau, dtype=float)[:, None], np.asarray(freq, dtype=float)[:, None])


def _since_start(omega, grid, tau, freq, touchdowns) -> np.ndarray:
    """``1 - exp(l n T)`` ``(P, G)``: the share of the steady train that ``n`` touchdowns since the log's start
    (``touchdowns (G,)``, inf: a long history) have built up by a cycle's analysis bins."""
    period = 2 * grid.half / omega
    n = np.asarray(touchdowns, dtype=float)[None, :]
    lam = -1.0 / np.asarray(tau, dtype=float)[:, None] + 2j * math.pi * np.asarray(freq, dtype=float)[:, None]
    finite = np.isfinite(n)
    return np.where(finite, 1.0 - np.exp(lam * np.where(finite, n, 0.0) * period), 1.0 + 0j)


class TouchdownImpactEffect(Effect):
    """The next leg's touchdown at every cycle boundary excites a decaying hub transient.

    ``az += A exp(-(t - tb)/tau) sin(2 pi f (t - tb) + onset)`` for ``t >= tb``,
    at every boundary (phase ``-pi/nL``, time ``tb``), either sign of ``A``.
    The onset phase sets the transient's shape at touchdown: 0 starts at
    zero (an impulse into a lightly damped mode), ``pi/2`` with a jump (a
    step of load); with a low ``f`` and ``onset = pi/2`` it is a plain
    exponential decay.
    The transient starts in the rigid half; it reaches the stance window's
    ``Da`` only when it rings for about a second (a lightly damped chassis
    mode, damping ratio ~1.5%); a short one is visible to the diagnosis but
    not to ``Da``.

    The prediction is linear in ``a_sin = A cos(onset)`` and ``a_cos = A
    sin(onset)`` (the transient is ``exp(-s/tau) (a_sin sin(2 pi f s) + a_cos
    cos(2 pi f s))``): the fit solves both in closed form with the bias and
    searches ``tau`` and ``f`` over wide ranges (0.005-8 s, 1-80 Hz). The
    train builds up from the log's start (its first touchdown,
    :mod:`slipest.diagnosis.cycles`): a cycle ``n`` touchdowns in sees
    ``1 - exp(-n T/tau)`` of the steady train's envelope. The
    catalog's ``A`` takes the sign of ``a_sin``, so ``onset`` is in
    ``[-pi/2, pi/2]``. The rigid half's residual against the nominal fit
    (whose kinematics do not depend on the soil beyond the leg length) shows
    the transient directly and seeds the fit.
    """

    name = "touchdown_impact"
    kind = "continuous"
    equation = ("az += A exp(-(t - tb)/tau) sin(2 pi f (t - tb) + onset),  t >= tb, tb: each boundary at phase "
                "-pi/nL")
    description = "the next leg's touchdown at each cycle boundary excites a decaying hub transient"
    params = (
        ParamSpec("amplitude", "m/s^2", 15.0, (2.0, 30.0), (12.0, 20.0), (-1e3, 1e3),
                  "transient amplitude A (either sign; ranges are of |A|)", neutral=0.0),
        ParamSpec("tau", "s", 1.0, (0.01, 1.5), (0.8, 1.2), (1e-4, 10.0),
                  "decay time constant (a lightly damped hub/chassis mode rings for up to ~1 s)", log_scale=True),
        ParamSpec("freq", "Hz", 12.0, (5.0, 60.0), (8.0, 20.0), (0.1, 500.0), "ringing frequency",
                  log_scale=True),
        ParamSpec("onset", "rad", 0.0, (-math.pi, math.pi), (0.0, 0.0), (-2 * math.pi, 2 * math.pi),
                  "onset phase: the transient's shape at touchdown (0: starts at zero, an impulse; pi/2: "
                  "starts with a jump, a step of load)"),
    )
    history_s = 40.0  # 5 x the longest fitted tau: the train is steady to 0.7% after that
    fit_params = (
        FitParam("a_sin", "m/s^2", -35.0, 35.0, linear=True, off=0.0),
        FitParam("a_cos", "m/s^2", -35.0, 35.0, linear=True, off=0.0),
        FitParam("tau", "s", 0.005, 8.0, log=True, off=0.05),
        FitParam("freq", "Hz", 1.0, 80.0, log=True, off=10.0),
    )

    def stage(self, values):
        return TouchdownImpact(values["amplitude"], values["tau"], values["freq"], onset=values["onset"])

    def catalog_values(self, fitted, soil, geometry):
        a_sin, a_cos = np.asarray(fitted["a_sin"], dtype=float), np.asarray(fitted["a_cos"], dtype=float)
        sign = np.where(a_sin < 0, -1.0, 1.0)
        return {"amplitude": sign * np.hypot(a_sin, a_cos), "tau": fitted["tau"], "freq": fitted["freq"],
                "onset": np.arctan2(sign * a_cos, sign * a_sin)}

    def sense(self, x, values, ctx):
        """Bin averages plus the train, per group ``m0 + a_sin Im(B) + a_cos Re(B)``, ``B`` the complex unit
        train's bin averages times ``1 - exp(l n T)`` for a group ``n`` touchdowns from the log's start."""
        tau, freq = np.asarray(values["tau"], dtype=float), np.asarray(values["freq"], dtype=float)
        m0 = ctx.bin_average(x)
        B = np.empty(m0.shape, dtype=complex)
        for om, sel in ctx.speed_groups():
            z = impact_basis(ctx.grid, om, tau, freq)[:, None, :]
            b = ctx.bin_average(z.real) + 1j * ctx.bin_average(z.imag)  # (P, 1, nb)
            B[:, sel] = b * _since_start(om, ctx.grid, tau, freq, ctx.g_touchdowns[sel])[:, :, None]
        if ctx.solve_linear:
            # linear in a_sin and a_cos: least squares with the bias, per candidate
            a_sin, a_cos = ctx.solve_amplitudes(self.fit_params[:2], m0, (B.imag, B.real))
        else:
            amp, onset = np.asarray(values["amplitude"], dtype=float), np.asarray(values["onset"], dtype=float)
            a_sin, a_cos = amp * np.cos(onset), amp * np.sin(onset)
        return m0 + a_sin[:, None, None] * B.imag + a_cos[:, None, None] * B.real

    def signature_seeds(self, data):
        """The transient train fitted to the rigid half's mean residual against the nominal fit.

        ``a_sin``, ``a_cos`` and a constant by least squares for each
        ``tau`` x ``freq`` of a grid over the fit's ranges; the pair that
        reduces the squared residual most, polished by a local search in
        ``(log tau, log f)`` (the grid's steps, 38% in tau and 8% in f, leave
        a phase error over the rigid half that a fixed seed cannot absorb).
        """
        grid = data.grid
        phi = grid.bin_centres
        r = data.mean_residual[: grid.nb_half]
        omega = data.omega
        t = (phi[: grid.nb_half] + grid.half) / omega  # age of the cycle's boundary [s]
        period = 2 * grid.half / omega
        tau_p, f_p = self.fit_params[2], self.fit_params[3]
        rc = r - r.mean()

        def solve(tau, freq):
            """Least-squares amplitudes ``(..., 2)`` and the reduction of the squared residual ``(...)``."""
            z = _unit_train(t, period, tau[..., None], freq[..., None])  # (..., bins)
            X = np.stack([z.imag, z.real], axis=-1)
            X = X - X.mean(axis=-2, keepdims=True)  # with a constant: centred columns
            XtX = np.einsum("...ik,...il->...kl", X, X)
            Xtr = np.einsum("...ik,i->...k", X, rc)
            ridge = 1e-9 * np.trace(XtX, axis1=-2, axis2=-1)[..., None, None] * np.eye(2) + 1e-300
            coef = np.linalg.solve(XtX + ridge, Xtr[..., None])[..., 0]
            return coef, np.einsum("...k,...k->...", coef, Xtr)

        taus = np.geomspace(tau_p.lo, tau_p.hi, 24)[:, None]
        freqs = np.geomspace(f_p.lo, f_p.hi, 60)[None, :]
        _, gain = solve(*np.broadcast_arrays(taus, freqs))
        a, b = np.unravel_index(int(np.argmax(gain)), gain.shape)
        if not gain[a, b] > 0:
            return []
        lo = np.log([tau_p.lo, f_p.lo])
        hi = np.log([tau_p.hi, f_p.hi])

        def loss(x):
            x = np.clip(x, lo, hi)
            return -float(solve(np.exp(x[:1]), np.exp(x[1:]))[1][0])

        x0 = np.log([taus[a, 0], freqs[0, b]])
        res = minimize(loss, x0, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-12, "maxiter": 400,
                                                                 "initial_simplex": [x0, x0 + [0.3, 0], x0 + [0, 0.05]]})
        x = np.clip(res.x, lo, hi) if res.fun < loss(x0) else x0
        coef, _ = solve(np.exp(x[:1]), np.exp(x[1:]))
        return [{"a_sin": float(coef[0, 0]), "a_cos": float(coef[0, 1]), "tau": float(np.exp(x[0])),
                 "freq": float(np.exp(x[1]))}]
