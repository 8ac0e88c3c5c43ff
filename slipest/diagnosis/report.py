"""The diagnosis as a JSON-ready dict and as a readable summary (pure: strings and dicts, no files)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from slipest.diagnosis.run import Diagnosis

#: One-paragraph definition of the gap, copied into every report.
GAP_DEFINITION = (
    "gap = sqrt(max(0, mean over held-out cycles and phase bins of r^2 - s_noise^2)) / g [g], where r is the "
    "difference between a logged cycle's az averaged over the analysis bins of leg phase ([-pi/nL, pi/nL) in "
    "equal bins) and the fitted model's prediction for that cycle's slip (after a fitted constant bias), and "
    "s_noise^2 the variance of one cycle's bin average from noise alone (repeatability of cycles with equal "
    "slip, or the raw samples' white noise); 0 means the model explains the data within noise. "
    "shrink = 1 - gap_after / gap_before."
)


def _clean(x):
    """JSON-safe copy (numpy scalars to Python, non-finite floats to None)."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    return x


def to_dict(d: Diagnosis, logs=()) -> dict:
    """The report: ``verdict``, ``gap_nominal``, ``where``, ``ranking`` (best first), and context."""
    best = d.best
    out = {
        "verdict": d.verdict,
        "gap_nominal": d.gap_nominal,
        "gap_after": d.gap_after,
        "shrink": d.shrink,
        "best_effect": best.effect if best else None,
        "where": d.where,
        "ranking": [c.as_dict() for c in d.ranking],
        "effects_fitted": d.effects_fitted,
        "effects_skipped": d.skipped,
        "nominal": {
            "soil": d.nominal.soil(),
            "bias": d.nominal.bias,
            "gap_train": d.gap_nominal_train,
            "units": {"kS": "N/m", "phiS": "rad", "dphi": "rad", "kappa": "-", "bias": "m/s^2"},
        },
        "noise": {
            "source": d.noise.source,
            "bin_g": d.noise.bin_g,
            "sample_g": d.noise.sample_g,
            "repeat_bin_g": d.noise.repeat_g,
            "white_bin_g": d.noise.white_bin_g,
        },
        "split": {
            "train_cycles": int(len(d.split.train)),
            "heldout_cycles": int(len(d.split.test)),
            "train_levels": list(d.split.train_levels),
            "heldout_levels": list(d.split.heldout_levels),
        },
        "thresholds": {
            "none_level_g": d.thresholds.none_level(d.noise.bin_g),
            "none_factor": d.thresholds.none_factor,
            "none_floor_g": d.thresholds.none_floor_g,
            "min_shrink": d.thresholds.min_shrink,
            "min_gain_factor": d.thresholds.min_gain_factor,
        },
        "geometry": {"MH": d.geometry.MH, "mF": d.geometry.mF, "lS": d.geometry.lS, "nL": d.geometry.nL},
        "cycles": int(len(d.cycles)),
        "cycles_dropped": int(d.cycles.dropped),
        "cycles_left_out": {str(k): int(v) for k, v in d.cycles.left_out.items()},
        "samples_repaired": int(d.cycles.repaired),
        "bins_per_cycle": int(d.cycles.grid.nb),
        "gap_definition": GAP_DEFINITION,
        "units": "gaps in g, angles in rad, parameters SI",
        "logs": [str(x) for x in logs],
        "swaps": [{"log": str(label), **dataclasses.asdict(sw), "off": sw.off, "sluggish": sw.sluggish,
                   "units": {"offset_s": "s", "offset_rad": "rad", "settling": "-"}} for label, sw in d.swaps],
        "elapsed_s": d.elapsed_s,
    }
    return _clean(out)


def _fmt_params(params: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in params.items())


def data_line(cycles) -> str | None:
    """What the diagnosis left out of the logs, or None when nothing: the leg cycles replay's segmenter flags
    (by flag: ``gap``, ``reverse``, ...) and the glitch samples (isolated outliers, any size) left out of the
    kept cycles."""
    parts = []
    if cycles.left_out:
        n = sum(cycles.left_out.values())
        parts.append(f"{n} leg cycle{'s' if n != 1 else ''} left out, flagged as replay flags them ("
                     + ", ".join(f"{f} {m}" for f, m in cycles.left_out.items()) + ")")
    if cycles.repaired:
        parts.append(f"{cycles.repaired} glitch sample{'s' if cycles.repaired != 1 else ''} left out "
                     "(isolated outliers of az)")
    return "data: " + "; ".join(parts) if parts else None


def summary(d: Diagnosis) -> str:
    """A readable multi-line summary."""
    lines = []
    lines.append(f"verdict: {d.verdict}")
    lines.append(
        f"cycles: {len(d.cycles)} ({len(d.split.train)} fitted, {len(d.split.test)} held out; "
        f"slip levels never fitted: {', '.join(f'{s:g}' for s in d.split.heldout_levels) or '-'})"
    )
    data = data_line(d.cycles)
    if data:
        lines.append(data)
    lines.append(
        f"noise floor: {d.noise.bin_g * 1000:.2f} mg per phase bin ({d.noise.source}; raw samples "
        f"{d.noise.sample_g * 1000:.2f} mg)"
    )
    soil = d.nominal.soil()
    lines.append(
        f"nominal fit: kS={soil['kS']:.0f} N/m, phiS={soil['phiS']:.3f} rad, phiD={soil['phiS'] - soil['dphi']:.3f} rad, "
        f"kappa={soil['kappa']:.3f}, bias={d.nominal.bias:+.3f} m/s^2"
    )
    lines.append(
        f"gap of the nominal model: {d.gap_nominal * 1000:.2f} mg held out ({d.gap_nominal_train * 1000:.2f} mg "
        f"on the fitted cycles); 'none' below {d.thresholds.none_level(d.noise.bin_g) * 1000:.2f} mg"
    )
    lines.append("where (nominal model, held-out cycles):")
    win = d.where["angle_windows"]
    lines.append(
        "  leg angle [rad]: "
        + "  ".join(f"[{w['from']:+.2f},{w['to']:+.2f}) {w['share'] * 100:3.0f}%" for w in win)
    )
    feats = sorted(d.where["features"], key=lambda f: -f["share"])[:5]
    lines.append(
        "  features: "
        + ", ".join(
            f"{f['feature']} {f['share'] * 100:.0f}% (data {f['data']:.3g} vs model {f['model']:.3g} {f['unit']})"
            for f in feats
        )
    )
    lv = d.where["slip_levels"]
    lines.append(
        "  slip: "
        + ", ".join(f"{s['slip']:g}{'*' if s['heldout_level'] else ''} {s['share'] * 100:.0f}%" for s in lv)
        + "   (* never fitted)"
    )
    if d.ranking:
        lines.append("which (held-out gap after fitting soil + effect; best first):")
        for c in d.ranking:
            mark = "  <- named" if c.named else ""
            lines.append(
                f"  {c.effect:17s} gap {c.gap_heldout * 1000:7.2f} mg  shrink {c.shrink * 100:6.1f}%  "
                f"[{_fmt_params(c.params)}]{mark}"
            )
        lines.append(
            f"how far: gap {d.gap_nominal * 1000:.2f} -> {d.gap_after * 1000:.2f} mg, shrink {d.shrink * 100:.1f}% "
            f"(naming needs >= {d.thresholds.min_shrink * 100:.0f}%)"
        )
    elif not d.effects_fitted:
        lines.append("which: not fitted (the nominal model explains the data within noise)")
    for name, why in d.skipped.items():
        lines.append(f"  not fitted: {name}, {why}")
    if d.swaps:
        lines.append("IMU against the encoder at the leg swaps (model-free):")
        for label, sw in d.swaps:
            lines.append(f"  {label}: {sw.explanation()}")
    lines.append(f"elapsed: {d.elapsed_s:.1f} s")
    return "\n".join(lines)


__all__ = ["GAP_DEFINITION", "to_dict", "summary"]
