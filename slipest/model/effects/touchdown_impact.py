"""``touchdown_impact``: a decaying hub transient after every touchdown (continuous sensor effect)."""

from __future__ import annotations

import math

import numpy as np

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
    it sits on one (the first leg touching down). Transients still ringing
    at the end of a chunk carry over into the next.
    """

    domain = "continuous"

    def __init__(self, amplitude: float, tau: float, freq: float, n_legs: int = DEFAULT_LEGS, onset: float = 0.0):
        self.amplitude = float(amplitude)
        self.tau = float(tau)
        self.freq = float(freq)
        self.onset = float(onset)
        self.n_legs = int(n_legs)
        self._last_k = None
        self._active: list[float] = []  # boundary times still ringing [s]

    def configure(self, params: StickSlipParams):
        """Take the leg count from the model parameters."""
        self.n_legs = int(params.nL)

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
        elif k[0] != self._last_k:
            times.append(float(t[0]))
        for j in np.flatnonzero(np.diff(k) != 0):
            # interpolate the crossing of the boundary angle between samples j and j+1
            th_b = k[j + 1] * step - math.pi / self.n_legs
            frac = (th_b - theta[j]) / (theta[j + 1] - theta[j]) if theta[j + 1] != theta[j] else 1.0
            times.append(float(t[j] + frac * (t[j + 1] - t[j])))
        self._last_k = int(k[-1])
        active = self._active + times
        out = np.array(az, dtype=float, copy=True)
        for tb in active:
            sel = t >= tb
            if sel.any():
                out[sel] += impact_response(t[sel] - tb, self.amplitude, self.tau, self.freq, self.onset)
        horizon = 12.0 * self.tau  # exp(-12) ~ 6e-6 of the amplitude: done
        self._active = [tb for tb in active if t[-1] - tb < horizon]
        return out, theta


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
    t = grid.time(omega)[None, :]
    period = 2 * grid.half / omega
    s0 = t - np.floor(t / period) * period
    lam = -1.0 / tau + 2j * math.pi * freq
    return amplitude * np.imag(np.exp(1j * onset + lam * s0) / (1.0 - np.exp(lam * period)))


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

    The prediction is linear in ``A``: the fit solves it in closed form with
    the bias. The rigid half's residual against the nominal fit (whose
    kinematics do not depend on the soil beyond the leg length) shows the
    transient directly and seeds the fit.
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
    fit_params = (
        FitParam("amplitude", "m/s^2", -35.0, 35.0, linear=True, off=0.0),
        FitParam("tau", "s", 0.01, 2.0, log=True, off=0.05),
        FitParam("freq", "Hz", 3.0, 60.0, log=True, off=10.0),
    )

    def stage(self, values):
        return TouchdownImpact(values["amplitude"], values["tau"], values["freq"], onset=values["onset"])

    def catalog_values(self, fitted, soil, geometry):
        return {**{k: fitted[k] for k in ("amplitude", "tau", "freq")}, "onset": np.zeros_like(fitted["tau"])}

    def sense(self, x, values, ctx):
        tau, freq = values["tau"], values["freq"]
        if ctx.solve_linear:
            # the transient is linear in its amplitude: least squares with the bias, per candidate
            m0 = ctx.bin_average(x)
            h = np.zeros_like(m0)
            for om, sel in ctx.speed_groups():
                train = impact_batch(ctx.grid, om, np.ones(len(tau)), tau, freq)
                h[:, sel] = ctx.bin_average(train[:, None, :])
            amp = ctx.solve_amplitude(self.fit_params[0], m0, h)
            return m0 + amp[:, None, None] * h
        for om, sel in ctx.speed_groups():
            x[:, sel] += impact_batch(ctx.grid, om, values["amplitude"], tau, freq)[:, None]
        return ctx.bin_average(x)

    def signature_seeds(self, data):
        """The transient train fitted to the rigid half's mean residual against the nominal fit.

        On a grid of ``tau`` x ``freq``, the amplitude in closed form; the
        pair that reduces the squared residual most.
        """
        grid = data.grid
        phi = grid.bin_centres
        r = data.mean_residual[: grid.nb_half]
        omega = data.omega
        t = (phi[: grid.nb_half] + grid.half) / omega
        period = 2 * grid.half / omega
        best = (0.0, None)
        for tau in np.geomspace(0.02, 2.0, 16):
            for f in np.geomspace(3.0, 60.0, 40):
                n_back = int(math.ceil(14 * tau / period)) + 1
                h = sum(
                    np.where(t + j * period >= 0,
                             np.exp(-(t + j * period) / tau) * np.sin(2 * math.pi * f * (t + j * period)), 0.0)
                    for j in range(n_back + 1)
                )
                hh = float(h @ h)
                if hh <= 0:
                    continue
                gain = float(r @ h) ** 2 / hh  # reduction of the squared residual
                if gain > best[0]:
                    best = (gain, {"amplitude": float(r @ h) / hh, "tau": float(tau), "freq": float(f)})
        return [best[1]] if best[1] else []
