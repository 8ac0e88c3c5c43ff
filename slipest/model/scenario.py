"""Scenarios: what a simulated run drives over, cycle by cycle.

A :class:`Scenario` is the list of per-leg-cycle model parameters (slip and
soil may change every cycle) plus the IMU settings (sample rate, noise, seed)
and the optional effects of the sim-to-real catalog. It is pure data; a TOML
file is parsed by the CLI and handed here as a dict (:meth:`Scenario.from_dict`).

TOML/dict layout (every key optional except the segments)::

    [model]          # StickSlipParams fields shared by all cycles (SI)
    kappa = 0.3
    nL = 4
    [imu]
    rate = 1000.0    # sample rate [Hz]
    noise = 0.01     # Gaussian noise, standard deviation [g]
    seed = 1
    [[segment]]      # cycles driven with one slip and soil
    cycles = 10
    slip = 0.2       # or [0.1, 0.4]: a linear ramp over the segment's cycles
    kS = 1000.0      # [N/m]
    phiS = 0.52      # [rad]
    phiD = 0.35      # [rad]
    omega = 0.8      # leg speed [rad/s] (a ramp too)

    [[effect]]       # effects of the sim-to-real catalog (slipest.model.effects)
    name = "imu_lowpass"
    cutoff = 40.0

A key a segment omits takes its value from ``[model]`` (or the model's
default), not from the previous segment. ``[model]`` and ``[imu]`` are
tables, ``segment`` and ``effect`` arrays of tables (``[[segment]]``); every
number is a finite number (a boolean is not one), ``cycles`` a positive
integer, ``seed`` a non-negative integer. Effects are checked (names,
parameters, each effect named once) when the scenario is built, so a bad
one fails before anything is simulated or written. A scenario holds at most
:data:`MAX_CYCLES` leg cycles, counted before any is built (each cycle's
parameters are kept in memory).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Sequence

import numpy as np

from slipest.model.params import PARAM_NAMES, StickSlipParams
from slipest.model.stance import DEFAULT_DT

#: Default IMU sample rate [Hz].
DEFAULT_RATE = 1000.0

#: Default value of every model parameter (the header lists those a run changes).
_DEFAULTS = {f.name: f.default for f in fields(StickSlipParams)}

#: Most leg cycles a scenario may hold. Each cycle keeps its own parameters (about 300 bytes, and some 35 us to
#: build and check), so a million take about 0.3 GB and half a minute before the first sample is simulated; at
#: the default leg speed (2.5 s a cycle) they are 29 days of driving.
MAX_CYCLES = 1_000_000
#: Memory a scenario's cycle takes [bytes] (a StickSlipParams of its own), for the message of :data:`MAX_CYCLES`.
_CYCLE_BYTES = 300


def check_cycle_count(n: int, what: str) -> None:
    """ValueError when ``n`` leg cycles are more than :data:`MAX_CYCLES` (call it before building them); ``what``
    names where the count comes from, for the message (``"--cycles=N"``, ``"segment 2: cycles = N"``)."""
    if n > MAX_CYCLES:
        raise ValueError(f"{what}: {n:,} leg cycles would take up to {n * _CYCLE_BYTES / 1e9:.3g} GB of memory "
                         f"before the first sample (each cycle's parameters are kept, up to {_CYCLE_BYTES} bytes a "
                         f"cycle); a scenario may hold at most {MAX_CYCLES:,} leg cycles: simulate fewer")


#: Per-cycle fields a segment may set (``omega``: the leg speed [rad/s]); the rest belong to [model].
SEGMENT_FIELDS = ("slip", "kS", "phiS", "phiD", "omega")


def _number(where: str, key: str, value) -> float:
    """A scenario value as a finite float, or a ValueError naming the section (or segment) and the key."""
    if isinstance(value, bool):  # a bool is an int to Python, not to the user who wrote "true"
        raise ValueError(f"{where}: {key} = {str(value).lower()} is a boolean: it must be a number")
    if not isinstance(value, (int, float)):
        raise ValueError(f"{where}: {key} = {value!r} must be a number")
    if not math.isfinite(value):
        raise ValueError(f"{where}: {key} = {value!r} must be a finite number")
    return float(value)


def _toml_type(value) -> str:
    """What a TOML value is, in a user's words (for the error messages)."""
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, (list, tuple)):
        return "an array"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, str):
        return "a string"
    return "a number" if isinstance(value, (int, float)) else type(value).__name__


def _table(doc: dict, key: str) -> dict:
    """Section ``[key]`` of a scenario document as a dict (empty when absent), or a ValueError naming it."""
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise ValueError(f"{key} = {value!r} is {_toml_type(value)}: [{key}] must be a table (a [{key}] section "
                         f"of key = value lines)")
    return value


def _array_of_tables(doc: dict, key: str) -> list:
    """Section ``[[key]]`` of a scenario document as a list of dicts (empty when absent), or a ValueError."""
    value = doc.get(key, [])
    if isinstance(value, dict):
        raise ValueError(f"[{key}] is a single table: write [[{key}]] (an array of tables, one [[{key}]] "
                         f"per {key})")
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{key} = {value!r} is {_toml_type(value)}: {key} must be an array of tables "
                         f"([[{key}]] sections)")
    for j, item in enumerate(value, start=1):
        if not isinstance(item, dict):
            raise ValueError(f"{key} = {list(value)!r}: {key} {j} is {_toml_type(item)}, not a table: "
                             f"write each {key} as a [[{key}]] section")
    return list(value)


@dataclass(frozen=True)
class Scenario:
    """A simulated run: per-cycle model parameters and IMU settings.

    cycles: one :class:`StickSlipParams` per leg cycle, in driving order.
    rate: IMU sample rate [Hz]. noise_g: IMU noise standard deviation [g].
    seed: random seed of the noise, an integer >= 0 (None: fresh entropy).
    dt: model integration step [s], not coarser than the IMU period ``1 / rate``.
    effects: effect specifications (``{"name": ..., params...}`` dicts) of
        the sim-to-real catalog, applied by :mod:`slipest.model.stream`;
        checked here (:func:`slipest.model.effects.normalise_specs`).
    ValueError naming the field when one is not valid (more than
    :data:`MAX_CYCLES` cycles among them).
    """

    cycles: tuple[StickSlipParams, ...]
    rate: float = DEFAULT_RATE
    noise_g: float = 0.0
    seed: int | None = None
    dt: float = DEFAULT_DT
    effects: tuple = field(default_factory=tuple)

    def __post_init__(self):
        if not self.cycles:
            raise ValueError("a scenario needs at least one leg cycle")
        check_cycle_count(len(self.cycles), "cycles")
        first = self.cycles[0]
        for j, c in enumerate(self.cycles):
            if c.nL != first.nL:
                raise ValueError(f"cycle {j}: nL must be the same for every cycle of a run")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ValueError(f"IMU rate={self.rate} Hz must be positive")
        if not (math.isfinite(self.noise_g) and self.noise_g >= 0):
            raise ValueError(f"IMU noise={self.noise_g} g must be >= 0")
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer))
                                      or self.seed < 0):
            raise ValueError(f"IMU seed={self.seed!r} must be a non-negative integer")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"model step dt={self.dt} s must be a positive finite number")
        if self.dt > 1.0 / self.rate:
            raise ValueError(
                f"model step dt={self.dt:g} s is coarser than the IMU period 1/rate = {1.0 / self.rate:g} s "
                f"(rate {self.rate:g} Hz): give a model step dt <= {1.0 / self.rate:g} s (--dt, or dt in a "
                "scenario's [imu]) or a lower rate")
        from slipest.model.effects import normalise_specs

        normalise_specs(self.effects)

    @property
    def n_legs(self) -> int:
        return self.cycles[0].nL

    @property
    def omega(self) -> float:
        """Leg angular speed of the first cycle [rad/s] (each cycle has its own, :attr:`omegas`)."""
        return self.cycles[0].omega

    @property
    def omegas(self) -> np.ndarray:
        """Leg angular speed of every cycle [rad/s]."""
        return np.array([c.omega for c in self.cycles])

    @property
    def slips(self) -> np.ndarray:
        """Slip of every cycle [-]."""
        return np.array([c.slip for c in self.cycles])

    @classmethod
    def constant(cls, n_cycles: int, params: StickSlipParams | None = None, **imu) -> "Scenario":
        """``n_cycles`` identical cycles (at most :data:`MAX_CYCLES`)."""
        if n_cycles < 1:
            raise ValueError(f"cycles={n_cycles} must be >= 1")
        check_cycle_count(n_cycles, f"cycles={n_cycles}")
        return cls(cycles=(params or StickSlipParams(),) * int(n_cycles), **imu)

    @classmethod
    def per_cycle(cls, base: StickSlipParams | None = None, imu: dict | None = None, **arrays) -> "Scenario":
        """One cycle per element of the given per-cycle arrays, e.g. ``slip=[...], kS=[...]``."""
        base = base or StickSlipParams()
        lengths = {len(np.atleast_1d(v)) for v in arrays.values()}
        if len(lengths) != 1:
            raise ValueError(f"per-cycle arrays must have one length, got {sorted(lengths)}")
        n = lengths.pop()
        cycles = tuple(
            replace(base, **{k: float(np.atleast_1d(v)[j]) for k, v in arrays.items()}) for j in range(n)
        )
        return cls(cycles=cycles, **(imu or {}))

    @classmethod
    def from_segments(
        cls, segments: Sequence[dict], base: StickSlipParams | None = None, imu: dict | None = None, effects=()
    ) -> "Scenario":
        """Segments of ``cycles`` cycles each with their slip (number or ``[start, end]`` ramp) and soil; a segment
        that would bring the cycles over :data:`MAX_CYCLES` is refused, naming it, before its cycles are built."""
        base = base or StickSlipParams()
        cycles: list[StickSlipParams] = []
        for s, seg in enumerate(segments, start=1):
            if not isinstance(seg, dict):
                raise ValueError(f"segment {s} is {_toml_type(seg)}, not a table of cycles, slip, ...")
            seg = dict(seg)
            unknown = set(seg) - set(SEGMENT_FIELDS) - {"cycles"}
            if unknown:
                raise ValueError(f"segment {s}: unknown key(s) {sorted(unknown)}; allowed: cycles, {', '.join(SEGMENT_FIELDS)}")
            if "cycles" not in seg:
                raise ValueError(f"segment {s}: 'cycles' is required")
            n = seg.pop("cycles")
            if isinstance(n, bool):  # a bool is an int to Python, not to the user who wrote "true"
                raise ValueError(f"segment {s}: cycles = {str(n).lower()} is a boolean: cycles must be a "
                                 "positive integer (a number of leg cycles)")
            if not isinstance(n, int) or n < 1:
                raise ValueError(f"segment {s}: cycles={n!r} must be a positive integer")
            total = f" (the scenario's cycles in all: {len(cycles) + n:,})" if cycles else ""
            check_cycle_count(len(cycles) + n, f"segment {s}: cycles = {n}{total}")
            ramps = {}
            for key, value in seg.items():
                if isinstance(value, (list, tuple)):
                    if len(value) != 2:
                        raise ValueError(f"segment {s}: {key} ramp must be [start, end], got {value!r}")
                    ramps[key] = np.linspace(_number(f"segment {s}", key, value[0]),
                                             _number(f"segment {s}", key, value[1]), n)
                else:
                    ramps[key] = np.full(n, _number(f"segment {s}", key, value))
            try:
                for j in range(n):
                    cycles.append(replace(base, **{k: float(v[j]) for k, v in ramps.items()}))
            except ValueError as exc:
                raise ValueError(f"segment {s}: {exc}") from None
        return cls(cycles=tuple(cycles), effects=tuple(effects), **(imu or {}))

    @classmethod
    def from_dict(cls, doc: dict) -> "Scenario":
        """Build from a parsed scenario document (see the module docstring for the layout)."""
        unknown = set(doc) - {"model", "imu", "segment", "effect"}
        if unknown:
            raise ValueError(f"unknown scenario section(s) {sorted(unknown)}; allowed: model, imu, segment, effect")
        model = dict(_table(doc, "model"))
        bad = set(model) - set(PARAM_NAMES)
        if bad:
            raise ValueError(f"[model]: unknown parameter(s) {sorted(bad)}")
        for key, value in model.items():
            model[key] = _number("[model]", key, value)
            if key == "nL":
                if model[key] != int(model[key]):
                    raise ValueError(f"[model]: nL = {value!r} must be an integer")
                model[key] = int(model[key])
        try:
            base = StickSlipParams(**model)
        except ValueError as exc:
            raise ValueError(f"[model]: {exc}") from None
        imu_doc = dict(_table(doc, "imu"))
        imu = {}
        for key, target in (("rate", "rate"), ("noise", "noise_g"), ("seed", "seed"), ("dt", "dt")):
            if key in imu_doc:
                value = imu_doc.pop(key)
                if key == "seed":
                    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                        raise ValueError(f"[imu]: seed = {value!r} must be a non-negative integer")
                    imu[target] = value
                else:
                    imu[target] = _number("[imu]", key, value)
        if imu_doc:
            raise ValueError(f"[imu]: unknown key(s) {sorted(imu_doc)}; allowed: rate, noise, seed, dt")
        segments = _array_of_tables(doc, "segment")
        if not segments:
            raise ValueError("a scenario needs at least one [[segment]]")
        effects = tuple(dict(e) for e in _array_of_tables(doc, "effect"))
        for j, e in enumerate(effects, start=1):
            if "name" not in e:
                raise ValueError(f"[[effect]] {j} without a name: {e}")
        from slipest.model.effects import normalise_specs

        try:
            normalise_specs(effects, label="[[effect]]")
        except ValueError as exc:  # a bad effect names itself ("[[effect]] 2: ..."); a duplicate is the section's
            text = str(exc)
            raise ValueError(text if text.startswith("[[effect]] ") else f"[[effect]]: {text}") from None
        return cls.from_segments(segments, base=base, imu=imu, effects=effects)

    def metadata(self) -> dict[str, str]:
        """``key=value`` metadata describing the run, for the log's ``#`` comments.

        The IMU settings, ``nL``, ``kappa``, ``MH``, ``mF``, ``lS`` and the
        segment fields always; every other model parameter (``g``, damping,
        Stribeck, ripple) when some cycle's differs from its default, so the
        log says what was simulated. A parameter that changes from cycle to
        cycle is written ``varies``.
        """
        first = self.cycles[0]
        meta = {
            "nL": str(first.nL),
            "rate": f"{self.rate:g}",
            "noise_g": f"{self.noise_g:g}",
            "dt": f"{self.dt:g}",
            "cycles": str(len(self.cycles)),
        }
        if self.seed is not None:
            meta["seed"] = str(self.seed)

        def value(name: str) -> str:
            values = {getattr(c, name) for c in self.cycles}
            return f"{values.pop():.15g}" if len(values) == 1 else "varies"

        for name in ("kappa", "MH", "mF", "lS"):
            meta[name] = value(name)
        for name in SEGMENT_FIELDS:  # omega among them: "varies" when the drive changes speed
            meta[name] = value(name)
        for name in PARAM_NAMES:  # the rest (gravity, the model's extensions): when not the default
            if name in meta:
                continue
            default = _DEFAULTS[name]
            if any(getattr(c, name) != default for c in self.cycles):
                meta[name] = value(name)
        if self.effects:
            meta["effects"] = ";".join(
                e["name"] + ":" + ",".join(f"{k}={v}" for k, v in e.items() if k != "name") for e in self.effects
            )
        return meta
