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

Each effect is one object (:class:`~slipest.model.effects.base.Effect`, one
module per effect in this package) that holds its parameters, its simulator
part, the batched prediction the diagnosis needs and its fitting
parametrisation; :data:`CATALOG` lists them in application order. Adding an
effect is one new class in a new module here, listed in :data:`CATALOG`,
and its test. The catalog (equations, units, typical / moderate ranges)
follows, generated from the objects.

API: :data:`CATALOG`, :data:`EFFECTS` (name -> effect), :data:`ORDER`,
:func:`compile_effects` (specs -> ``(transform, stages)``),
:func:`parse_effect_arg` (the CLI's ``NAME:param=value,...``),
:func:`normalise_spec` (a spec with every parameter filled in and checked).
Pure computation: no files.
"""

from __future__ import annotations

from typing import Callable

from slipest.model.effects.angle_offset import AngleOffset, AngleOffsetEffect
from slipest.model.effects.base import Effect, FitParam, ParamSpec
from slipest.model.effects.contact_damping import ContactDampingEffect
from slipest.model.effects.imu_lowpass import ImuLowpassEffect, LowPass
from slipest.model.effects.imu_saturation import ImuSaturationEffect, Saturation
from slipest.model.effects.speed_ripple import SpeedRippleEffect
from slipest.model.effects.stribeck import StribeckEffect
from slipest.model.effects.time_skew import TimeSkew, TimeSkewEffect
from slipest.model.effects.touchdown_impact import TouchdownImpact, TouchdownImpactEffect, impact_response
from slipest.model.params import StickSlipParams

#: The catalog, in the order effects are applied within each kind (impact is hub physics, so it comes
#: before the IMU's filter whatever the order given).
CATALOG: tuple[Effect, ...] = (
    ContactDampingEffect(),
    StribeckEffect(),
    SpeedRippleEffect(),
    TouchdownImpactEffect(),
    ImuLowpassEffect(),
    ImuSaturationEffect(),
    AngleOffsetEffect(),
    TimeSkewEffect(),
)
#: Name -> effect.
EFFECTS: dict[str, Effect] = {e.name: e for e in CATALOG}
#: Catalog names in application order.
ORDER: tuple[str, ...] = tuple(e.name for e in CATALOG)

assert len(EFFECTS) == len(CATALOG), "effect names must be unique"

__all__ = [
    "CATALOG", "EFFECTS", "ORDER", "Effect", "FitParam", "ParamSpec", "AngleOffset", "LowPass", "Saturation",
    "TimeSkew", "TouchdownImpact", "impact_response", "compile_effects", "normalise_spec", "normalise_specs",
    "parse_effect_arg",
    "catalog_text",
]


def _effect(name) -> Effect:
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


def normalise_specs(specs, label: str = "effect") -> list[dict]:
    """Each effect spec of ``specs`` normalised (:func:`normalise_spec`), in order; ValueError on a bad one
    (``"<label> <j>: ..."``, ``j`` from 1) or on an effect named more than once."""
    normalised = []
    for j, spec in enumerate(specs or (), start=1):
        try:
            normalised.append(normalise_spec(dict(spec)))
        except ValueError as exc:
            raise ValueError(f"{label} {j}: {exc}") from None
    names = [s["name"] for s in normalised]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"effect(s) named more than once: {', '.join(dupes)} (each effect may be named once)")
    return normalised


def compile_effects(specs) -> tuple[Callable[[StickSlipParams], StickSlipParams], list]:
    """``(transform, stages)`` for a sequence of effect specs (dicts with ``name`` and parameters).

    ``transform(params)`` switches the physics effects on in a parameter set
    (and tells the stages that need it the number of legs); ``stages`` are
    the sensor stages in application order (continuous ones first). Each
    effect may be named once; missing parameters take the catalog defaults.
    """
    normalised = normalise_specs(specs)
    normalised.sort(key=lambda s: ORDER.index(s["name"]))
    physics = [s for s in normalised if EFFECTS[s["name"]].kind == "physics"]
    stages = [EFFECTS[s["name"]].stage(s) for s in normalised if EFFECTS[s["name"]].kind != "physics"]
    stages.sort(key=lambda st: 0 if st.domain == "continuous" else 1)
    configurable = [st for st in stages if hasattr(st, "configure")]

    def transform(params: StickSlipParams) -> StickSlipParams:
        for s in physics:
            params = EFFECTS[s["name"]].physics(params, s)
        for st in configurable:
            st.configure(params)
        return params

    return transform, stages


def catalog_text() -> str:
    """The catalog as text: per effect its kind, equation and parameters (unit, typical / moderate ranges)."""
    lines = []
    for e in CATALOG:
        lines.append(f"``{e.name}`` ({e.kind})")
        lines.append(f"    {e.equation}")
        for p in e.params:
            lines.append(f"    ``{p.name}`` [{p.unit}]: typical [{p.typical[0]:.4g}, {p.typical[1]:.4g}], "
                         f"moderate [{p.moderate[0]:.4g}, {p.moderate[1]:.4g}], default {p.default:g}")
    return "\n".join(lines)


if __doc__ is not None:
    __doc__ += "\nCatalog (typical / moderate ranges; more in each effect's class)::\n\n" + "\n".join(
        "    " + line for line in catalog_text().splitlines()) + "\n"
