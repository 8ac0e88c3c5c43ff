"""Turn a scenario into a continuous IMU + encoder sample stream ``t, az, theta``.

Conventions (the project's log format):

* ``theta`` [rad] is the wheel-leg rotation angle, continuous (unwrapped),
  0 at every midstance, increasing; midstances at ``2 pi k / nL``. The run
  starts at ``t = 0``, ``theta = -pi/nL``: the first leg cycle is whole.
* for a leg's phase ``phi = theta - 2 pi k / nL`` in ``[-pi/nL, 0)`` the hub
  rides rigidly on the planted foot: its height is ``l cos(phi)`` with the
  loaded leg ``l = lS - MH g / kS``, and the hub's acceleration is that
  small kinematic one (no stick-slip);
* for ``phi`` in ``[0, pi/nL)`` it is the stick-slip stance of
  :mod:`slipest.model.stance`, started from static equilibrium at midstance;
* ``az`` [m/s^2] is the vertical specific force an IMU reports, z up,
  gravity included (``+g`` at rest): the hub's ``zH'' + g``.

Each cycle runs at its own leg speed (a drive may change speed from one
cycle to the next): cycle ``k`` lasts ``2 pi / (nL omega_k)`` (with a
drive ripple, its timeline's period). The model integrates at its own step
``dt``; the continuous signal is built
on that grid, passes the "continuous" sensor stages (hub transients, the
IMU's bandwidth), is sampled at the IMU rate, then passes the "sampled"
stages (noise, clipping, encoder offset). The stream is produced in chunks
of whole leg cycles, in bounded memory, identical however it is chunked: a
chunk covers at most :data:`MAX_CHUNK_SECONDS` of simulated time (but always
one whole cycle, so a single very slow cycle still takes memory in
proportion to its length: about 80 bytes per model step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from slipest.model import kernel as K
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.sensor import GaussianNoise, run_stages
from slipest.model.stance import simulate_batch

#: Longest simulated time [s] a chunk of :func:`iter_stream` covers (unless one cycle alone is longer): a
#: chunk's model grid takes memory in proportion to its duration / dt (80 s: 32 cycles at the default leg speed).
MAX_CHUNK_SECONDS = 80.0


@dataclass(frozen=True)
class SampleChunk:
    """Consecutive IMU samples. t [s]; az [m/s^2] specific force, gravity included;
    theta [rad] unwrapped; slip: the true slip of each sample's leg cycle [-];
    cycle: the index of that leg cycle."""

    t: np.ndarray
    az: np.ndarray
    theta: np.ndarray
    slip: np.ndarray
    cycle: np.ndarray

    def __len__(self) -> int:
        return len(self.t)

    @staticmethod
    def concatenate(chunks) -> "SampleChunk":
        chunks = list(chunks)
        return SampleChunk(*(np.concatenate([getattr(c, f) for c in chunks]) for f in ("t", "az", "theta", "slip", "cycle")))


class CycleTimeline:
    """Leg phase as a function of time within one cycle, for a given drive law.

    With a constant leg speed the phase is linear in time; with a drive
    speed ripple ``omega(phi) = omega0 (1 + A sin(h nL phi + ph))`` the time to
    reach each phase is tabulated once (the ripple repeats every cycle).
    """

    def __init__(self, params: StickSlipParams):
        self.n_legs = params.nL
        self.omega0 = params.omega
        self.amp = params.ripple_amp
        self.phase0 = params.ripple_phase
        self.k = self.n_legs * params.ripple_harmonic  # ripples per radian of leg angle
        half = math.pi / self.n_legs
        if self.amp == 0.0:
            self.period = 2 * half / self.omega0
            self._tab = None
        else:
            phi = np.linspace(-half, half, 20001)
            inv = 1.0 / self.omega(phi)
            t = np.concatenate([[0.0], np.cumsum(0.5 * (inv[1:] + inv[:-1]) * np.diff(phi))])
            self.period = float(t[-1])
            self._tab = (t, phi)

    def omega(self, phi):
        """Leg angular speed [rad/s] at phase ``phi`` [rad]."""
        return self.omega0 * (1.0 + self.amp * np.sin(self.k * phi + self.phase0))

    def domega_dphi(self, phi):
        """Derivative of the leg speed with respect to the phase [1/s]."""
        return self.omega0 * self.amp * self.k * np.cos(self.k * phi + self.phase0)

    def phase(self, tau):
        """Phase [rad] at time ``tau`` [s] since the cycle's start (phase ``-pi/nL``)."""
        half = math.pi / self.n_legs
        if self._tab is None:
            return -half + self.omega0 * tau
        return np.interp(tau, *self._tab)


def _effect_chain(scenario: Scenario):
    """(parameter transform, sensor stages) of the scenario's sim-to-real effects."""
    if not scenario.effects:
        return (lambda p: p), []
    from slipest.model.effects import compile_effects

    return compile_effects(scenario.effects)


class _Schedule:
    """When each cycle starts [s] and its timeline: cycle ``k`` spans ``[start[k], start[k + 1])``."""

    def __init__(self, cycles):
        cache: dict = {}
        self.timelines = []
        for c in cycles:
            key = (c.nL, c.omega, c.ripple_amp, c.ripple_phase, c.ripple_harmonic)
            if key not in cache:
                cache[key] = CycleTimeline(c)
            self.timelines.append(cache[key])
        self.start = np.concatenate([[0.0], np.cumsum([tl.period for tl in self.timelines])])

    def cycle_of(self, t, k0: int, k1: int) -> np.ndarray:
        """Cycle index of each time [s], within ``[k0, k1)``."""
        return np.clip(np.searchsorted(self.start, t, side="right") - 1, k0, k1 - 1)

    def phase(self, t, k) -> np.ndarray:
        """Leg phase [rad] at times ``t`` [s] of cycles ``k`` (phase ``-pi/nL`` at each cycle's start)."""
        out = np.empty(len(t))
        for kk in np.unique(k):
            sel = k == kk
            tl = self.timelines[kk]
            out[sel] = tl.phase(np.clip(t[sel] - self.start[kk], 0.0, tl.period))
        return out


def cycle_starts(scenario: Scenario) -> np.ndarray:
    """Start times [s] of the scenario's leg cycles, and the end of the last: ``(len(cycles) + 1,)``, from 0
    (each cycle lasts ``2 pi / (nL omega)`` at its own leg speed, longer or shorter with a speed ripple)."""
    transform, _ = _effect_chain(scenario)
    return _Schedule([transform(c) for c in scenario.cycles]).start


def _lead_in_cycles(first: StickSlipParams, stages) -> int:
    """How many copies of the first cycle to simulate before ``t = 0`` so every stage's ``lead_in`` [s] is covered."""
    lead = max((float(getattr(s, "lead_in", 0.0)) for s in stages), default=0.0)
    if not lead > 0.0:
        return 0
    return int(math.floor(lead / CycleTimeline(first).period)) + 1


def iter_stream(scenario: Scenario, chunk_cycles: int = 32) -> Iterator[SampleChunk]:
    """Yield the scenario's samples in chunks of at most ``chunk_cycles`` leg cycles and at most
    :data:`MAX_CHUNK_SECONDS` of simulated time (at least one whole cycle per chunk); the samples do not
    depend on the chunking.

    A sensor stage that needs signal from before the run's start (its
    ``lead_in`` [s], e.g. a time skew's delay) gets it from lead-in cycles
    that repeat the first cycle before ``t = 0`` (the rover was already
    driving); their samples pass the stages and are not yielded."""
    if chunk_cycles < 1:
        raise ValueError("chunk_cycles must be >= 1")
    transform, effect_stages = _effect_chain(scenario)
    cycles = [transform(c) for c in scenario.cycles]
    stages = [s for s in effect_stages if s.domain == "continuous"]
    stages += [GaussianNoise(scenario.noise_g)]
    stages += [s for s in effect_stages if s.domain == "sampled"]
    rng = np.random.default_rng(scenario.seed)
    n_lead = _lead_in_cycles(cycles[0], effect_stages)
    ext = [cycles[0]] * n_lead + cycles  # lead-in cycles, then the run's
    slips = np.array([scenario.cycles[0].slip] * n_lead + [c.slip for c in scenario.cycles])
    schedule = _Schedule(ext)
    t0 = schedule.start[n_lead]  # the schedule's time of the run's start
    start = schedule.start - t0  # the run's time: 0 at its first cycle's start
    n_legs = cycles[0].nL
    dt = scenario.dt
    rate = scenario.rate
    k1 = 0
    while k1 < len(cycles):
        k0 = k1
        # the last cycle that ends within MAX_CHUNK_SECONDS of this chunk's start (at least one)
        k_end = int(np.searchsorted(start, start[k0 + n_lead] + MAX_CHUNK_SECONDS, side="right")) - 1 - n_lead
        k1 = max(k0 + 1, min(k0 + chunk_cycles, len(cycles), k_end))
        e0, e1 = (k0 + n_lead if k0 else 0), k1 + n_lead  # the first chunk carries the lead-in
        batch = simulate_batch(ext[e0:e1], dt=dt, waveforms=True)
        # continuous signal on the model grid covering [start e0, start e1)
        n = np.arange(math.ceil(start[e0] / dt - 1e-9), math.ceil(start[e1] / dt - 1e-9))
        t_grid = n * dt
        on_schedule = t_grid + t0 if n_lead else t_grid
        k_grid = schedule.cycle_of(on_schedule, e0, e1)
        phi_grid = schedule.phase(on_schedule, k_grid)
        az_grid = _hub_acceleration(k_grid, phi_grid, e0, schedule, ext[e0:e1], batch) + cycles[0].g
        theta_grid = 2 * math.pi * (k_grid - n_lead) / n_legs + phi_grid
        az_grid, _ = run_stages(stages, "continuous", t_grid, az_grid, theta_grid, rng)
        # IMU samples in [start e0, start e1)
        s = np.arange(math.ceil(start[e0] * rate - 1e-9), math.ceil(start[e1] * rate - 1e-9))
        t = s / rate
        az = np.interp(t, t_grid, az_grid)
        on_schedule = t + t0 if n_lead else t
        k = schedule.cycle_of(on_schedule, e0, e1)
        theta = 2 * math.pi * (k - n_lead) / n_legs + schedule.phase(on_schedule, k)
        az, theta = run_stages(stages, "sampled", t, az, theta, rng)
        run = k >= n_lead
        yield SampleChunk(t=t[run], az=az[run], theta=theta[run], slip=slips[k[run]], cycle=k[run] - n_lead)


def simulate_stream(scenario: Scenario) -> SampleChunk:
    """The whole scenario's samples at once (see :func:`iter_stream` for long runs)."""
    return SampleChunk.concatenate(iter_stream(scenario))


def _hub_acceleration(k, phi, k0, schedule: _Schedule, chunk_params, batch) -> np.ndarray:
    """Hub vertical acceleration zH'' [m/s^2] (z up, gravity-free) at cycles ``k`` and phases ``phi`` [rad]."""
    out = np.empty(phi.shape)
    rigid = phi < 0.0
    # rigid half: z = l cos(phi), z'' = -l (cos(phi) w^2 + sin(phi) w dw/dphi), at each cycle's own leg speed
    for j in range(len(chunk_params)):
        p = chunk_params[j]
        tl = schedule.timelines[k0 + j]
        sel = rigid & (k == k0 + j)
        if sel.any():
            pr = phi[sel]
            w = tl.omega(pr)
            out[sel] = -(p.lS - p.MH * p.g / p.kS) * (np.cos(pr) * w * w + np.sin(pr) * w * tl.domega_dphi(pr))
        # stick-slip half: the stance waveform of the cycle, by phase
        sel = (~rigid) & (k == k0 + j)
        if sel.any():
            m = int(batch.n_steps[j])
            out[sel] = np.interp(phi[sel], batch.theta[j, :m], batch.az[j, :m])
    return out


# Keep the kernel's channel layout visible to readers of this module.
__all__ = ["SampleChunk", "CycleTimeline", "iter_stream", "simulate_stream", "K"]
