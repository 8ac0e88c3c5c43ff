"""The sim-to-real effect catalog: optional extensions of the stick-slip model and of the IMU.

Every effect is off unless a scenario (``[[effect]]``) or
``slipest simulate --effect NAME:param=value,...`` names it; each has
physical parameters in SI, an equation, the range its parameters typically
take on real hardware (``typical``) and a *moderate* range (``moderate``):
the range ``tools/check_withheld_effects.py`` draws from, sized so that the
effect changes ``Da`` by about 10% or more (``Da`` as the project defines
it, :mod:`slipest.features`: max - min of ``az`` over the stance window of
the logged phase). Within a moderate range the change still depends on the
soil, the slips and the other parameters (a ripple's phase, a low-pass
order), so the check tool redraws any draw that changes ``Da`` by less than
10%. When an effect is named without a parameter, the parameter takes the
catalog default, a moderate value; at the default soil and slips 0.05-0.5
every default changes ``Da`` by 15-28% (``tests/test_effects.py``).

Three kinds, applied at different places of the simulated chain
(:mod:`slipest.model.stream`)::

    physics     StickSlipParams -> StickSlipParams        (kernel fields)
    continuous  on the model-step signal, before the IMU samples it
    sampled     on the IMU samples, after the IMU noise

Effects (``t`` [s], ``az`` [m/s^2] specific force with gravity, z up,
``theta`` [rad]); typical / moderate ranges:

``contact_damping`` (physics)
    Hunt-Crossley damping that thesis Eq. 5.10 drops:
    ``FS = kS d + b_hc d^n_hc d'`` (``d`` compression [m], clamped ``FS >= 0``).
    ``b_hc`` [N s/m^(1+n_hc)] 0-2000 / 150-600 (for ``n_hc = 1``),
    ``n_hc`` [-] 1-1.5 / 1. The damping it adds near the static sinkage
    ``d0 = MH g / kS`` is ``c = b_hc d0^n_hc`` [N s/m] (about 3 N s/m at
    ``b_hc = 300``, a damping ratio of ~5% on the hub).
``stribeck`` (physics)
    Speed-dependent dynamic friction with a viscous term:
    ``mu(v) = muD + (muS - muD) exp(-(|v|/vs)^delta)``, friction force
    ``mu(v) FN sgn(v) + viscous v``. ``vs`` [m/s] 0.001-0.1 / 0.01-0.05,
    ``delta`` [-] 0.5-2 / 1-2, ``viscous`` [N s/m] 0-5 / 0-1. No value is
    neutral: ``mu(0) = muS`` changes the break-away even for a tiny ``vs``.
``speed_ripple`` (physics)
    Leg angular speed not constant over a cycle (drive ripple, once per leg):
    ``omega(theta) = omega0 (1 + A sin(nL theta + phase))``. ``amplitude``
    ``A`` [-] 0-0.3 / 0.15-0.3, ``phase`` [rad] any.
``touchdown_impact`` (continuous)
    The next leg's touchdown at every cycle boundary (phase ``-pi/nL``,
    time ``tb``) excites a decaying hub transient:
    ``az += A exp(-(t - tb)/tau) sin(2 pi f (t - tb))`` for ``t >= tb``.
    ``amplitude`` [m/s^2] 2-30 / 12-20 (either sign), ``tau`` [s]
    0.01-1.5 / 0.8-1.2, ``freq`` [Hz] 5-60 / 8-20. The transient starts in
    the rigid half; it reaches the stance window's ``Da`` only when it
    rings for about a second (a lightly damped chassis mode, damping ratio
    ~1.5%); a short one is visible to the diagnosis but not to ``Da``.
``imu_lowpass`` (continuous)
    The IMU's bandwidth: a Butterworth low-pass of order ``n`` and cut-off
    ``fc`` [Hz] (-3 dB, gain ``1/sqrt(2)`` at ``fc``) on the continuous
    signal before sampling (``scipy.signal.butter`` + ``lfilter``; the
    filter state carries across chunks; it starts in steady state).
    ``cutoff`` 5-100 / 3-6 Hz (the stick-slip oscillation is at 4-7 Hz),
    ``order`` 1-4.
``imu_saturation`` (sampled)
    Accelerometer full-scale clipping: ``az = clip(az, -FS, +FS)``.
    ``full_scale`` [m/s^2] 19.6-157 (2-16 g parts) / 11.5-13.5 (the hub's
    specific force peaks at 1.4-1.8 g, so only a low range, an analog
    front end's or a +-2 g part's with an offset, clips it).
``angle_offset`` (sampled)
    Encoder zero not at the true midstance: ``theta_log = theta + offset``,
    equivalently a time skew ``offset / omega`` [s] between IMU and encoder
    (the encoder's angle reported ``offset/omega`` seconds early).
    ``offset`` [rad] -0.15-0.15 / 0.12-0.2. Only a positive offset moves
    ``Da``'s window off the end of the stance, where the oscillation is
    largest; a negative one moves it into the quiet rigid half and changes
    ``Da`` little (the diagnosis sees both in the waveform).

API: :data:`EFFECTS` (name -> :class:`EffectSpec`), :func:`compile_effects`
(specs -> ``(transform, stages)``), :func:`parse_effect_arg` (the CLI's
``NAME:param=value,...``), :func:`normalise_spec` (a spec with every
parameter filled in and checked). Pure computation: no files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import signal

from slipest.model.params import DEFAULT_LEGS, StickSlipParams

#: Canonical order in which effects are applied within each kind (impact is
#: hub physics, so it comes before the IMU's filter whatever the order given).
ORDER = (
    "contact_damping",
    "stribeck",
    "speed_ripple",
    "touchdown_impact",
    "imu_lowpass",
    "imu_saturation",
    "angle_offset",
)


@dataclass(frozen=True)
class ParamSpec:
    """One physical parameter of an effect.

    default: value when the effect is named without it (a moderate value).
    neutral: value at which the effect does nothing (None: no such value
        within the parameter's range, the effect is then off only when
        not named).
    typical: the range real hardware/soils typically show.
    moderate: the range in which the effect changes ``Da`` by >= 10% at
        the default soil over slips 0.05-0.5 (measured, see the tests).
    bounds: hard validity limits (inclusive or not, see ``check``).
    integer: the parameter takes integer values.
    """

    name: str
    unit: str
    default: float
    typical: tuple[float, float]
    moderate: tuple[float, float]
    bounds: tuple[float, float]
    description: str
    neutral: float | None = None
    integer: bool = False
    log_scale: bool = False

    def check(self, effect: str, value) -> float:
        """The value as a float (int for integer parameters), or ValueError naming the problem."""
        if isinstance(value, bool):
            raise ValueError(f"{effect}: {self.name}={value!r} is not a number")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{effect}: {self.name}={value!r} is not a number") from None
        if not math.isfinite(v):
            raise ValueError(f"{effect}: {self.name}={value!r} must be finite")
        lo, hi = self.bounds
        if not lo <= v <= hi:
            raise ValueError(f"{effect}: {self.name}={v:g} {self.unit} is outside [{lo:g}, {hi:g}]")
        if self.integer:
            if v != int(v):
                raise ValueError(f"{effect}: {self.name}={v:g} must be an integer")
            return int(v)
        return v


@dataclass(frozen=True)
class EffectSpec:
    """One effect of the catalog: kind, equation, parameters."""

    name: str
    kind: str  # "physics", "continuous" or "sampled"
    equation: str
    description: str
    params: tuple[ParamSpec, ...]

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def param(self, name: str) -> ParamSpec:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def defaults(self) -> dict:
        return {p.name: (int(p.default) if p.integer else float(p.default)) for p in self.params}

    def as_dict(self) -> dict:
        """JSON-friendly description (for ``--help`` texts and reports)."""
        return {
            "name": self.name,
            "kind": self.kind,
            "equation": self.equation,
            "description": self.description,
            "params": [
                {
                    "name": p.name,
                    "unit": p.unit,
                    "default": p.default,
                    "neutral": p.neutral,
                    "typical": list(p.typical),
                    "moderate": list(p.moderate),
                    "description": p.description,
                }
                for p in self.params
            ],
        }


_INF = math.inf

EFFECTS: dict[str, EffectSpec] = {
    "contact_damping": EffectSpec(
        name="contact_damping",
        kind="physics",
        equation="FS = kS d + b_hc d^n_hc d'  (clamped FS >= 0)",
        description="Hunt-Crossley damping of the leg/soil contact that thesis Eq. 5.10 drops "
        "(bHC > 0; nHC = 1 is damping proportional to the compression, 1.5 the Hertzian value)",
        params=(
            ParamSpec(
                "b_hc", "N s/m^(1+n_hc)", 300.0, (0.0, 2000.0), (150.0, 600.0), (0.0, 1e7),
                "Hunt-Crossley damping coefficient; c = b_hc d0^n_hc [N s/m] at the static sinkage d0 = MH g/kS",
                neutral=0.0,
            ),
            ParamSpec("n_hc", "-", 1.0, (1.0, 1.5), (1.0, 1.0), (0.0, 3.0),
                      "Hunt-Crossley exponent (the moderate range of b_hc is for n_hc = 1)"),
        ),
    ),
    "stribeck": EffectSpec(
        name="stribeck",
        kind="physics",
        equation="mu(v) = muD + (muS - muD) exp(-(|v|/vs)^delta);  F = mu(v) FN sgn(v) + sigma_v v",
        description="speed-dependent dynamic friction of the sliding foot (Stribeck curve) with an optional "
        "viscous term",
        params=(
            ParamSpec(
                "vs", "m/s", 0.03, (0.001, 0.1), (0.01, 0.05), (0.0, 10.0),
                "Stribeck velocity (0: constant muD)", neutral=0.0, log_scale=True,
            ),
            ParamSpec("delta", "-", 2.0, (0.5, 2.0), (1.0, 2.0), (0.1, 5.0), "Stribeck exponent"),
            ParamSpec(
                "viscous", "N s/m", 0.0, (0.0, 5.0), (0.0, 1.0), (0.0, 1e4),
                "viscous friction coefficient sigma_v", neutral=0.0,
            ),
        ),
    ),
    "speed_ripple": EffectSpec(
        name="speed_ripple",
        kind="physics",
        equation="omega(theta) = omega0 (1 + A sin(nL theta + phase))",
        description="leg angular speed not constant over the cycle (drive/gear ripple once per leg)",
        params=(
            ParamSpec("amplitude", "-", 0.2, (0.0, 0.3), (0.15, 0.3), (0.0, 0.9), "relative ripple amplitude A",
                      neutral=0.0),
            ParamSpec("phase", "rad", 0.0, (-math.pi, math.pi), (-math.pi, math.pi), (-2 * math.pi, 2 * math.pi),
                      "ripple phase"),
        ),
    ),
    "touchdown_impact": EffectSpec(
        name="touchdown_impact",
        kind="continuous",
        equation="az += A exp(-(t - tb)/tau) sin(2 pi f (t - tb)),  t >= tb, tb: each boundary at phase -pi/nL",
        description="the next leg's touchdown at each cycle boundary excites a decaying hub transient",
        params=(
            ParamSpec("amplitude", "m/s^2", 15.0, (2.0, 30.0), (12.0, 20.0), (-1e3, 1e3),
                      "transient amplitude A (either sign; ranges are of |A|)", neutral=0.0),
            ParamSpec("tau", "s", 1.0, (0.01, 1.5), (0.8, 1.2), (1e-4, 10.0),
                      "decay time constant (a lightly damped hub/chassis mode rings for up to ~1 s)", log_scale=True),
            ParamSpec("freq", "Hz", 12.0, (5.0, 60.0), (8.0, 20.0), (0.1, 500.0), "ringing frequency",
                      log_scale=True),
        ),
    ),
    "imu_lowpass": EffectSpec(
        name="imu_lowpass",
        kind="continuous",
        equation="Butterworth low-pass, order n, -3 dB at fc, before sampling",
        description="IMU bandwidth (digital low-pass / anti-alias filter) below the stick-slip oscillation",
        params=(
            ParamSpec("cutoff", "Hz", 5.0, (5.0, 100.0), (3.0, 6.0), (0.1, 1e5), "cut-off (-3 dB) frequency fc",
                      log_scale=True),
            ParamSpec("order", "-", 2, (1, 4), (1, 4), (1, 8), "filter order n", integer=True),
        ),
    ),
    "imu_saturation": EffectSpec(
        name="imu_saturation",
        kind="sampled",
        equation="az = clip(az, -FS, +FS)",
        description="accelerometer full-scale clipping of the specific force (gravity included)",
        params=(
            ParamSpec("full_scale", "m/s^2", 12.5, (19.6, 160.0), (11.5, 13.5), (0.1, 1e4),
                      "full-scale range FS (commercial parts: 2-16 g = 19.6-157 m/s^2; the moderate range "
                      "stands for an analog front end or a +-2 g part mounted with an offset)"),
        ),
    ),
    "angle_offset": EffectSpec(
        name="angle_offset",
        kind="sampled",
        equation="theta_log = theta + offset  (= time skew offset/omega)",
        description="offset between the encoder's zero and the true midstance, or equally a time skew "
        "between IMU and encoder",
        params=(
            ParamSpec("offset", "rad", 0.18, (-0.15, 0.15), (0.12, 0.2), (-math.pi, math.pi),
                      "encoder angle minus true angle (a negative offset moves the Da window into the quiet "
                      "rigid half and changes Da little)", neutral=0.0),
        ),
    ),
}

assert tuple(sorted(EFFECTS)) == tuple(sorted(ORDER))


def effect_names() -> tuple[str, ...]:
    """Catalog names in application order."""
    return ORDER


def _effect(name) -> EffectSpec:
    if not isinstance(name, str) or name not in EFFECTS:
        raise ValueError(f"unknown effect {name!r}; known effects: {', '.join(ORDER)}")
    return EFFECTS[name]


def normalise_spec(spec: dict) -> dict:
    """``{"name": ..., params}`` with every parameter present and checked (defaults filled in)."""
    if not isinstance(spec, dict) or "name" not in spec:
        raise ValueError(f"an effect specification needs a 'name': {spec!r}")
    eff = _effect(spec["name"])
    unknown = set(spec) - {"name"} - set(eff.param_names)
    if unknown:
        raise ValueError(
            f"{eff.name}: unknown parameter(s) {', '.join(sorted(unknown))}; "
            f"parameters: {', '.join(eff.param_names)}"
        )
    out = {"name": eff.name}
    for p in eff.params:
        out[p.name] = p.check(eff.name, spec.get(p.name, p.default))
    return out


def parse_effect_arg(text: str) -> dict:
    """Parse the CLI's ``NAME`` or ``NAME:param=value,param=value`` into a spec dict.

    Only the parameters given are in the result (the rest take the catalog
    defaults when compiled); names, parameters and values are checked here so
    that a typo fails on the command line with a message naming it.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError("empty effect; expected NAME or NAME:param=value,...")
    name, _, rest = text.strip().partition(":")
    eff = _effect(name.strip())
    out: dict = {"name": eff.name}
    if rest.strip():
        for item in rest.split(","):
            item = item.strip()
            if not item:
                continue
            key, eq, value = item.partition("=")
            key = key.strip()
            if not eq or not key:
                raise ValueError(f"{eff.name}: expected param=value, got {item!r}")
            if key not in eff.param_names:
                raise ValueError(
                    f"{eff.name}: unknown parameter {key!r}; parameters: {', '.join(eff.param_names)}"
                )
            if key in out:
                raise ValueError(f"{eff.name}: parameter {key!r} given twice")
            out[key] = eff.param(key).check(eff.name, value.strip())
    elif _:
        raise ValueError(f"{eff.name}: nothing after ':'; expected param=value,...")
    return out


# --- physics effects: kernel fields -----------------------------------------


def apply_physics(params: StickSlipParams, spec: dict) -> StickSlipParams:
    """The parameters with one (normalised) physics effect switched on."""
    name = spec["name"]
    if name == "contact_damping":
        return params.with_(b_hc=spec["b_hc"], n_hc=spec["n_hc"])
    if name == "stribeck":
        return params.with_(stribeck_vs=spec["vs"], stribeck_exp=spec["delta"], viscous=spec["viscous"])
    if name == "speed_ripple":
        return params.with_(ripple_amp=spec["amplitude"], ripple_phase=spec["phase"])
    raise ValueError(f"{name} is not a physics effect")


# --- sensor stages ------------------------------------------------------------


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


class Saturation:
    """Full-scale clipping at ``+-full_scale`` [m/s^2] ("sampled" stage)."""

    domain = "sampled"

    def __init__(self, full_scale: float):
        self.full_scale = float(full_scale)

    def apply(self, t, az, theta, rng):
        return np.clip(az, -self.full_scale, self.full_scale), theta


class AngleOffset:
    """Encoder angle = true angle + ``offset`` [rad] ("sampled" stage)."""

    domain = "sampled"

    def __init__(self, offset: float):
        self.offset = float(offset)

    def apply(self, t, az, theta, rng):
        return az, theta + self.offset


def impact_response(tau_since, amplitude, tau, freq):
    """The touchdown transient ``A exp(-s/tau) sin(2 pi f s)`` at ``s >= 0`` [s], 0 before [m/s^2]."""
    s = np.asarray(tau_since, dtype=float)
    out = np.zeros_like(s)
    on = s >= 0
    out[on] = amplitude * np.exp(-s[on] / tau) * np.sin(2 * math.pi * freq * s[on])
    return out


class TouchdownImpact:
    """A decaying transient after every cycle boundary (leg phase ``-pi/nL``) ("continuous" stage).

    Boundaries are found from ``theta`` (unwrapped, 0 at midstances, legs
    ``n_legs`` apart); the stream's first sample counts as a boundary when
    it sits on one (the first leg touching down). Transients still ringing
    at the end of a chunk carry over into the next.
    """

    domain = "continuous"

    def __init__(self, amplitude: float, tau: float, freq: float, n_legs: int = DEFAULT_LEGS):
        self.amplitude = float(amplitude)
        self.tau = float(tau)
        self.freq = float(freq)
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
                out[sel] += impact_response(t[sel] - tb, self.amplitude, self.tau, self.freq)
        horizon = 12.0 * self.tau  # exp(-12) ~ 6e-6 of the amplitude: done
        self._active = [tb for tb in active if t[-1] - tb < horizon]
        return out, theta


def build_stage(spec: dict):
    """The sensor stage of a normalised continuous or sampled effect spec."""
    name = spec["name"]
    if name == "imu_lowpass":
        return LowPass(spec["cutoff"], spec["order"])
    if name == "imu_saturation":
        return Saturation(spec["full_scale"])
    if name == "angle_offset":
        return AngleOffset(spec["offset"])
    if name == "touchdown_impact":
        return TouchdownImpact(spec["amplitude"], spec["tau"], spec["freq"])
    raise ValueError(f"{name} is not a sensor effect")


def compile_effects(specs) -> tuple[Callable[[StickSlipParams], StickSlipParams], list]:
    """``(transform, stages)`` for a sequence of effect specs (dicts with ``name`` and parameters).

    ``transform(params)`` switches the physics effects on in a parameter set
    (and tells the stages that need it the number of legs); ``stages`` are
    the sensor stages in application order (continuous ones first). Each
    effect may be named once; missing parameters take the catalog defaults.
    """
    normalised = [normalise_spec(dict(s)) for s in (specs or ())]
    names = [s["name"] for s in normalised]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"effect(s) named more than once: {', '.join(dupes)}")
    normalised.sort(key=lambda s: ORDER.index(s["name"]))
    physics = [s for s in normalised if EFFECTS[s["name"]].kind == "physics"]
    stages = [build_stage(s) for s in normalised if EFFECTS[s["name"]].kind != "physics"]
    stages.sort(key=lambda st: 0 if st.domain == "continuous" else 1)
    configurable = [st for st in stages if hasattr(st, "configure")]

    def transform(params: StickSlipParams) -> StickSlipParams:
        for s in physics:
            params = apply_physics(params, s)
        for st in configurable:
            st.configure(params)
        return params

    return transform, stages
