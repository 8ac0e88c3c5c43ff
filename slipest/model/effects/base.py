"""What an effect of the sim-to-real catalog is: one object per effect (see :mod:`slipest.model.effects`).

An :class:`Effect` holds, for its effect:

* its physical parameters (:class:`ParamSpec`: unit, default, typical and
  moderate ranges, neutral value, hard bounds) and its equation;
* its simulator part: a physics effect changes the stance's parameters
  (:meth:`Effect.physics`, kernel fields), a sensor effect builds a stage of
  the sensor chain (:meth:`Effect.stage`, :mod:`slipest.model.sensor`);
* the batched prediction the diagnosis needs (the hooks
  :meth:`Effect.kernel_columns`, :meth:`Effect.drive_speed`,
  :meth:`Effect.rigid`, :meth:`Effect.sense`): many candidate parameter
  sets ``(P,)`` at once, on the phase grid of :mod:`slipest.diagnosis.predict`;
* its fitting parametrisation (:class:`FitParam` search ranges, which may
  differ from the catalog's parameters, and :meth:`Effect.catalog_values`
  back to them) and, where the data show the effect directly, values read
  off them to seed the fit (:meth:`Effect.signature_seeds`).

Units are SI throughout (``az`` [m/s^2] specific force with gravity, z up;
angles [rad]; times [s]). Pure computation: no files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from slipest.model.params import StickSlipParams


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
    bounds: hard validity limits (inclusive, see ``check``).
    integer: the parameter takes integer values.
    log_scale: draw / search it on a log scale.
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
class FitParam:
    """One fitted quantity: SI unit, search range ``[lo, hi]``, log-scaled search, integer.

    choices: the values of a categorical parameter (one search instance each).
    linear: solved in closed form during the fit (least squares with the
        bias, by the effect's :meth:`Effect.sense`), not searched.
    off: the value at which its effect is (nearly) off, where a search from
        a soil alone starts (None: the middle of the range).
    """

    name: str
    unit: str
    lo: float
    hi: float
    log: bool = False
    integer: bool = False
    choices: tuple = ()
    linear: bool = False
    off: float | None = None

    @property
    def categorical(self) -> bool:
        return bool(self.choices)

    @property
    def start(self) -> float:
        """:attr:`off` (or the middle of the range) clipped to the range."""
        v = 0.5 * (self.lo + self.hi) if self.off is None else self.off
        return float(np.clip(v, self.lo, self.hi))

    def to_z(self, x):
        """Search coordinate of a value (its log for a log-scaled parameter)."""
        return np.log(x) if self.log else np.asarray(x, dtype=float)

    def from_z(self, z):
        """Value of a search coordinate (rounded for an integer parameter)."""
        x = np.exp(z) if self.log else np.asarray(z, dtype=float)
        return np.round(x) if self.integer else x

    @property
    def zbounds(self) -> tuple[float, float]:
        if self.log:
            return (math.log(self.lo), math.log(self.hi))
        return (self.lo, self.hi)


class PredictionContext(Protocol):
    """What the diagnosis's prediction (:class:`slipest.diagnosis.predict.Evaluator`) gives an effect's :meth:`Effect.sense`.

    grid: the phase grid (:class:`slipest.diagnosis.predict.Grid`); bias0
    [m/s^2]: accelerometer bias assumed before sampled stages; noise_sigma
    [m/s^2]: white noise of one logged sample; solve_linear: solve the
    effect's ``linear`` fit parameters in closed form; g_touchdowns: see
    :attr:`Effect.history_s`.
    """

    grid: object
    bias0: float
    noise_sigma: float
    solve_linear: bool
    #: ``(G,)`` cycle boundaries since the log's start up to each group's cycle (inf: a long history).
    g_touchdowns: np.ndarray

    def speed_groups(self, previous: bool = False):
        """``(omega [rad/s], mask (G,))`` per distinct leg speed of the predicted groups; ``previous``:
        ``(omega, prev_omega, mask)`` per distinct pair with the previous cycles' speed."""
        ...

    def bin_average(self, x: np.ndarray, offset=None) -> np.ndarray:
        """``(P, G, n_ext)`` extended-grid signal -> ``(P, G, nb)`` analysis bins (encoder offset [rad]: ``(P,)``,
        or ``(P, nb + 1)`` per bin edge)."""
        ...

    def solve_amplitude(self, param: "FitParam", m0: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Least-squares amplitude ``(P,)`` of ``m0 + A h`` (bins) with the bias, clipped to ``param``'s range."""
        ...

    def solve_amplitudes(self, params, m0: np.ndarray, hs) -> list[np.ndarray]:
        """Least-squares amplitudes ``(P,)`` each of ``m0 + sum_k A_k h_k`` with the bias, clipped to ``params[k]``'s range."""
        ...


class Effect:
    """One effect of the catalog (subclasses set the class attributes and override the hooks).

    name, kind ("physics", "continuous" or "sampled"), equation,
    description, params: the catalog's parameters (:class:`ParamSpec`).
    fit_params: the fitted parameters (:class:`FitParam`).
    memory: the prediction of a cycle depends on the previous cycle's slip
        (the effect carries the previous stance across the cycle boundary).
    bias_inside: the prediction depends on the accelerometer bias (a
        nonlinear sampled stage acting after it: clipping).
    search_steps: integration steps ``(coarse, search)`` [s] the fit needs
        instead of its defaults, or None.
    history_s: how far back [s] the prediction of a cycle depends on the
        log's start (transients that build up over many cycles), or None
        (not at all): cycles closer to the start are predicted with their
        count of touchdowns since it.
    """

    name: str = ""
    kind: str = ""
    equation: str = ""
    description: str = ""
    params: tuple[ParamSpec, ...] = ()
    fit_params: tuple[FitParam, ...] = ()
    memory: bool = False
    bias_inside: bool = False
    search_steps: tuple[float, float] | None = None
    history_s: float | None = None

    def __repr__(self) -> str:
        return f"<effect {self.name}>"

    # --- catalog ---------------------------------------------------------------------------------
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

    # --- simulator -------------------------------------------------------------------------------
    def physics(self, params: StickSlipParams, values: dict) -> StickSlipParams:
        """The stance parameters with this (physics) effect switched on at ``values`` (catalog parameters)."""
        raise ValueError(f"{self.name} is not a physics effect")

    def stage(self, values: dict):
        """A fresh sensor stage (:class:`slipest.model.sensor.SensorStage`) of this sensor effect at ``values``."""
        raise ValueError(f"{self.name} is not a sensor effect")

    # --- fitting parametrisation -------------------------------------------------------------------
    def catalog_values(self, fitted: dict, soil: dict, geometry) -> dict:
        """The catalog's parameters from the fitted ones (arrays or floats, elementwise).

        soil: the fitted soil (``kS`` [N/m], ...); geometry: the known
        hardware (``MH`` [kg], ``g`` [m/s^2], ...). Default: the same names.
        """
        return {p.name: fitted[p.name] for p in self.params}

    def angle_offset_at(self, values: dict, omega: float) -> float | None:
        """The encoder angle offset [rad] (encoder angle minus true angle) this effect at ``values`` amounts to at
        steady leg speed ``omega`` [rad/s], when all it does is move the angle against the ``az`` samples;
        None otherwise (default): a calibration then removes it from ``theta``."""
        return None

    def equivalent_on(self, omega) -> str | None:
        """The catalog effect this one cannot be told from on cycles of leg speeds ``omega`` [rad/s] (default None).

        The diagnosis then fits only that one (e.g. a time skew is an angle
        offset while the leg speed does not change).
        """
        return None

    def signature_seeds(self, data) -> list[dict]:
        """Fitted parameters read off the data directly, to seed the fit (partial value dicts; default none).

        ``data``: :class:`slipest.diagnosis.fit.Signature` (the training
        cycles' bin means and encoder speeds, and the nominal fit's residual).
        """
        return []

    # --- prediction on the phase grid (P candidates, G groups of cycles) ---------------------------
    def kernel_columns(self, values: dict) -> dict:
        """Kernel parameter columns (``slipest.model.kernel.P_*``) -> values, from catalog values (physics)."""
        return {}

    def drive_speed(self, omega, values: dict):
        """The drive's nominal leg speed [rad/s] that gives the observed mean speed ``omega`` (default: itself)."""
        return omega

    def rigid(self, grid, leg: np.ndarray, omega: np.ndarray, values: dict):
        """Rigid-half ``zH''`` ``(P, G, m)`` [m/s^2] if this effect changes it, else None (the nominal one)."""
        return None

    def sense(self, x: np.ndarray, values: dict, ctx: PredictionContext) -> np.ndarray:
        """The sensor's bin averages ``(P, G, nb)`` of the extended-grid specific force ``x (P, G, n_ext)``.

        Default: no sensor effect, plain bin averages. ``x`` may be changed in place.
        """
        return ctx.bin_average(x)


class PhysicsEffect(Effect):
    """An effect of the stance's physics: catalog parameters map onto kernel fields.

    fields: ``(catalog parameter, StickSlipParams field, kernel column)`` triples.
    """

    kind = "physics"
    fields: tuple[tuple[str, str, int], ...] = ()

    def physics(self, params: StickSlipParams, values: dict) -> StickSlipParams:
        return params.with_(**{field: values[name] for name, field, _ in self.fields})

    def kernel_columns(self, values: dict) -> dict:
        return {column: values[name] for name, _, column in self.fields}
