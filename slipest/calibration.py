"""Thesis Eq. 5.15 calibration: the fit of its coefficients and the calibration file (pure computation + JSON).

Eq. 5.15 exactly as the thesis states it (:func:`fit_eq515`): per soil a
line ``i = aIV + bIV * Da``, then ``bIV = amu + bmu * dphi`` and ``aIV = cI
+ cmu * dphi + cK * kS``; every goodness of fit is reported, including the
end-to-end R^2/RMSE of the full equation predicting slip. The fit works on a
*sweep table*: 1-D arrays of equal length ``slip`` [-], ``kS`` [N/m],
``phiS``, ``phiD`` [rad] (the soil; ``dphi = phiS - phiD``) and ``Da`` [g]
(``max - min`` of the hub's vertical acceleration over the stance window).
In the project's model the second-level laws fit poorly (the end-to-end R^2
is negative); the figures are reported, nothing is tuned to look good.

The calibration file is a JSON dict (schema :data:`SCHEMA_DOC`), versioned by
``format_version``; :func:`load_calibration` / :func:`save_calibration` are
the only I/O here. The shipped file ``slipest/data/calibration.json`` is
written by ``tools/calibrate.py``, which also fits and documents the forward
calibration (``Da`` as a function of slip and soil) docs/model.md (section 5) recommends
(``tools/forward_calibration.py``); the runtime reads only ``model`` and
``eq515``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipest.json_files import json_number, json_numbers, read_json

#: Version of the calibration file format this module reads and writes.
FORMAT_VERSION = 1

SCHEMA_DOC = """\
Calibration file (JSON object), format_version 1. Units: slip [-], kS [N/m],
phiS, phiD, dphi [rad], Da [g]; R^2 [-], RMSE in the unit of the predicted
quantity.

format_version  int, 1
created_by      str, the command that wrote the file
created_utc     str, ISO 8601 time of writing
slipest_version str
units           {quantity: unit}
model           {"params": StickSlipParams fields used for the sweep (SI), "dt": step [s],
                 "kappa": leg lateral stiffness ratio [-]}
grid            {"slip", "kS", "phiD", "dphi": the levels swept (lists), "phiS": rule text,
                 "n_stances", "n_failed", "n_used", "n_soils",
                 optional "validation": {"n_stances", "n_failed", "seed", "distribution"}}
eq515           {"equation": text, "amu", "bmu", "cI", "cmu", "cK": Eq. 5.15 coefficients,
                 "r2_lines_mean", "r2_lines_median", "r2_lines_min", "r2_lines_max": per-soil
                 line i = aIV + bIV Da, "r2_slope_law": bIV = amu + bmu dphi,
                 "r2_intercept_plane": aIV = cI + cmu dphi + cK kS, "r2_end_to_end",
                 "rmse_end_to_end": full Eq. 5.15 predicting slip over the sweep,
                 "rmse_lines_soil_known": per-soil lines predicting slip, optional
                 "r2_end_to_end_val", "rmse_end_to_end_val": the same on the validation table,
                 "per_soil": {"kS", "phiS", "phiD", "aIV", "bIV", "r2", "n": lists}}
forward         {"name", "kind" ("linear-in-slip" | "polynomial"), "variables": ["slip", "dphi",
                 "kS", "phiS"], "center", "scale": per-variable normalisation u = (x - center)/scale,
                 "terms": exponent lists over the normalised variables, "coef": Da [g] per term,
                 "slip_clip": [lo, hi] for the inversion, "r2_da", "rmse_da", "r2_da_cv",
                 "rmse_da_cv", "rmse_slip", "rmse_slip_cv", "r2_da_val", "rmse_da_val",
                 "rmse_slip_val" (cv: leave one soil out; val: the validation table, null if
                 none), "selection_rule": text, "per_soil_lines": {"r2_mean", "r2_median",
                 "r2_min"} (Da = alpha + beta i per soil), "candidates": [one dict per
                 candidate with the same figures, "n_coef", "identifiable",
                 "monotone_fraction" and, for alpha/beta surfaces, "r2_alpha", "r2_beta"
                 and, for planes, "alpha_plane"/"beta_plane" coefficients in SI]}
"""

#: Keys every calibration file must have (top level, then per section).
REQUIRED_KEYS = {
    None: ("format_version", "created_by", "model", "grid", "eq515", "forward"),
    "model": ("params", "dt", "kappa"),
    "grid": ("slip", "kS", "phiD", "dphi", "n_stances", "n_failed", "n_used", "n_soils"),
    "eq515": (
        "amu",
        "bmu",
        "cI",
        "cmu",
        "cK",
        "r2_lines_mean",
        "r2_lines_median",
        "r2_slope_law",
        "r2_intercept_plane",
        "r2_end_to_end",
        "rmse_end_to_end",
        "per_soil",
    ),
    "forward": (
        "name",
        "kind",
        "variables",
        "center",
        "scale",
        "terms",
        "coef",
        "slip_clip",
        "r2_da",
        "rmse_da",
        "rmse_slip",
        "candidates",
    ),
}


class CalibrationError(ValueError):
    """A calibration file is missing, of another format version, or malformed."""


# --------------------------------------------------------------------------- basic statistics


def r2_score(y, pred) -> float:
    """Coefficient of determination ``1 - SS_res / SS_tot`` [-] (NaN if ``y`` is constant).

    Negative when ``pred`` does worse than the mean of ``y``.
    """
    y = np.asarray(y, dtype=float)
    pred = np.asarray(pred, dtype=float)
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0.0:
        return math.nan
    return 1.0 - float(np.sum((y - pred) ** 2)) / ss_tot


def rmse(y, pred) -> float:
    """Root-mean-square error, in the unit of ``y``."""
    y = np.asarray(y, dtype=float)
    return float(np.sqrt(np.mean((y - np.asarray(pred, dtype=float)) ** 2)))


def linear_fit(x, y) -> tuple[float, float, float]:
    """Least-squares line ``y = intercept + slope * x``: returns ``(intercept, slope, R^2)``."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.size < 2 or np.ptp(x) == 0.0:
        raise ValueError("a line needs at least two distinct x values")
    a = np.column_stack([np.ones_like(x), x])
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    return float(coef[0]), float(coef[1]), r2_score(y, a @ coef)


def linear_model_fit(columns, y) -> tuple[np.ndarray, float]:
    """Least squares ``y = c0 + c1 x1 + c2 x2 + ...``: returns ``(coef, R^2)``.

    ``columns``: a sequence of 1-D arrays ``x1, x2, ...`` (an intercept is added).
    """
    y = np.asarray(y, dtype=float)
    a = np.column_stack([np.ones_like(y)] + [np.asarray(c, dtype=float) for c in columns])
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    return coef, r2_score(y, a @ coef)


def _sweep_arrays(slip, kS, phiS, phiD, da_g):
    arrays = [np.asarray(v, dtype=float).ravel() for v in (slip, kS, phiS, phiD, da_g)]
    n = arrays[0].size
    if any(a.size != n for a in arrays):
        raise ValueError("slip, kS, phiS, phiD and Da must have the same length")
    if n == 0:
        raise ValueError("empty sweep table")
    if not all(np.all(np.isfinite(a)) for a in arrays):
        raise ValueError("the sweep table has non-finite values: drop failed stances (NaN Da) before fitting")
    return arrays


def soil_index(kS, phiS, phiD, decimals: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """Group rows by soil: returns ``(index, soils)``.

    ``index[j]`` is the soil of row ``j``; ``soils`` is ``(S, 3)`` with
    columns ``kS`` [N/m], ``phiS``, ``phiD`` [rad], sorted.
    """
    keys = np.column_stack([np.asarray(v, dtype=float).ravel() for v in (kS, phiS, phiD)])
    soils, index = np.unique(np.round(keys, decimals), axis=0, return_inverse=True)
    return index.ravel(), soils


# --------------------------------------------------------------------------- Eq. 5.15 (thesis)


@dataclass(frozen=True)
class Eq515Fit:
    """Thesis Eq. 5.15 fitted to a sweep, with every goodness of fit.

    Per soil (arrays over soils): ``soils`` ``(S, 3)`` = kS [N/m], phiS, phiD
    [rad]; ``aIV`` [-], ``bIV`` [1/g] and ``r2`` of ``i = aIV + bIV Da``;
    ``n`` points. Second level: ``bIV = amu + bmu dphi`` (``r2_slope_law``),
    ``aIV = cI + cmu dphi + cK kS`` (``r2_intercept_plane``; ``cmu`` [1/rad],
    ``cK`` [m/N]). End to end: the full equation predicting slip over the
    sweep (``r2_end_to_end``, ``rmse_end_to_end`` [-]); with each soil's own
    line instead (soil known): ``rmse_lines_soil_known``.
    """

    soils: np.ndarray
    aIV: np.ndarray
    bIV: np.ndarray
    r2: np.ndarray
    n: np.ndarray
    amu: float
    bmu: float
    r2_slope_law: float
    cI: float
    cmu: float
    cK: float
    r2_intercept_plane: float
    r2_end_to_end: float
    rmse_end_to_end: float
    rmse_lines_soil_known: float
    n_soils_skipped: int = 0

    @property
    def dphi(self) -> np.ndarray:
        """Per-soil ``phiS - phiD`` [rad]."""
        return self.soils[:, 1] - self.soils[:, 2]

    def coefficients(self) -> dict:
        """``{"amu", "bmu", "cI", "cmu", "cK"}``."""
        return dict(amu=self.amu, bmu=self.bmu, cI=self.cI, cmu=self.cmu, cK=self.cK)

    def to_dict(self) -> dict:
        """The ``eq515`` section of a calibration file."""
        r2 = self.r2[np.isfinite(self.r2)]
        return {
            "equation": "i = aIV + bIV*Da;  bIV = amu + bmu*dphi;  aIV = cI + cmu*dphi + cK*kS  "
            "(Da [g], dphi [rad], kS [N/m])",
            **{k: json_number(v) for k, v in self.coefficients().items()},
            "r2_lines_mean": json_number(np.mean(r2)),
            "r2_lines_median": json_number(np.median(r2)),
            "r2_lines_min": json_number(np.min(r2)),
            "r2_lines_max": json_number(np.max(r2)),
            "r2_slope_law": json_number(self.r2_slope_law),
            "r2_intercept_plane": json_number(self.r2_intercept_plane),
            "r2_end_to_end": json_number(self.r2_end_to_end),
            "rmse_end_to_end": json_number(self.rmse_end_to_end),
            "rmse_lines_soil_known": json_number(self.rmse_lines_soil_known),
            "n_soils_skipped": int(self.n_soils_skipped),
            "per_soil": {
                "kS": self.soils[:, 0].tolist(),
                "phiS": self.soils[:, 1].tolist(),
                "phiD": self.soils[:, 2].tolist(),
                "aIV": json_numbers(self.aIV),
                "bIV": json_numbers(self.bIV),
                "r2": json_numbers(self.r2),
                "n": self.n.astype(int).tolist(),
            },
        }


def eq515_slip(coeffs, da_g, dphi, kS) -> np.ndarray:
    """Slip [-] predicted by Eq. 5.15 from ``Da`` [g], ``dphi`` [rad] and ``kS`` [N/m] (not clipped).

    ``coeffs``: an :class:`Eq515Fit`, a calibration dict, its ``eq515``
    section, or any mapping with ``amu, bmu, cI, cmu, cK``. Broadcasts.
    """
    if isinstance(coeffs, Eq515Fit):
        c = coeffs.coefficients()
    else:
        c = coeffs["eq515"] if "eq515" in coeffs else coeffs
    da_g, dphi, kS = (np.asarray(v, dtype=float) for v in (da_g, dphi, kS))
    a_iv = c["cI"] + c["cmu"] * dphi + c["cK"] * kS
    b_iv = c["amu"] + c["bmu"] * dphi
    return a_iv + b_iv * da_g


def fit_eq515(slip, kS, phiS, phiD, da_g, min_points: int = 3) -> Eq515Fit:
    """Fit thesis Eq. 5.15 exactly as stated to a sweep table (see module docstring).

    Per soil, ``i = aIV + bIV * Da`` by least squares (slip regressed on
    ``Da``); soils with fewer than ``min_points`` rows or a constant ``Da``
    are skipped (counted in ``n_soils_skipped``). Then ``bIV`` on ``dphi``
    and ``aIV`` on ``(dphi, kS)``, one point per soil, unweighted.
    """
    # The thesis text calls aI,V the "slope" and bI,V the "intercept" in one
    # sentence; its equation is authoritative and is what is fitted here:
    # i = aIV + bIV*Da (aIV intercept, bIV slope), bIV = amu + bmu*dphi,
    # aIV = cI + cmu*dphi + cK*kS.
    slip, kS, phiS, phiD, da_g = _sweep_arrays(slip, kS, phiS, phiD, da_g)
    index, soils = soil_index(kS, phiS, phiD)
    s_count = soils.shape[0]
    a_iv = np.full(s_count, np.nan)
    b_iv = np.full(s_count, np.nan)
    r2 = np.full(s_count, np.nan)
    counts = np.bincount(index, minlength=s_count)
    for s in range(s_count):
        m = index == s
        if counts[s] < min_points or np.ptp(da_g[m]) == 0.0:
            continue
        a_iv[s], b_iv[s], r2[s] = linear_fit(da_g[m], slip[m])
    ok = np.isfinite(a_iv)
    if ok.sum() < 4:
        raise ValueError(f"only {ok.sum()} soil(s) could be fitted: Eq. 5.15's plane needs at least 4")
    dphi_s = soils[:, 1] - soils[:, 2]
    amu, bmu, r2_slope = linear_fit(dphi_s[ok], b_iv[ok]) if np.ptp(dphi_s[ok]) > 0 else (np.nan,) * 3
    plane, r2_plane = linear_model_fit([dphi_s[ok], soils[ok, 0]], a_iv[ok])
    coeffs = dict(amu=amu, bmu=bmu, cI=plane[0], cmu=plane[1], cK=plane[2])
    pred = eq515_slip(coeffs, da_g, phiS - phiD, kS)
    rows = ok[index]
    lines = a_iv[index[rows]] + b_iv[index[rows]] * da_g[rows]
    return Eq515Fit(
        soils=soils,
        aIV=a_iv,
        bIV=b_iv,
        r2=r2,
        n=counts,
        amu=float(amu),
        bmu=float(bmu),
        r2_slope_law=float(r2_slope),
        cI=float(plane[0]),
        cmu=float(plane[1]),
        cK=float(plane[2]),
        r2_intercept_plane=float(r2_plane),
        r2_end_to_end=r2_score(slip, pred),
        rmse_end_to_end=rmse(slip, pred),
        rmse_lines_soil_known=rmse(slip[rows], lines),
        n_soils_skipped=int((~ok).sum()),
    )


# --------------------------------------------------------------------------- calibration file


def validate_calibration(cal, source: str = "calibration") -> dict:
    """Check ``format_version`` and every required key; raise :class:`CalibrationError` naming the problem."""
    if not isinstance(cal, dict):
        raise CalibrationError(f"{source}: expected a JSON object, got {type(cal).__name__}")
    version = cal.get("format_version")
    if version is None:
        raise CalibrationError(f"{source}: no 'format_version' key (not a slipest calibration file?)")
    if version != FORMAT_VERSION:
        raise CalibrationError(
            f"{source}: format_version {version!r} is not supported (this slipest reads format_version "
            f"{FORMAT_VERSION}); regenerate it with tools/calibrate.py"
        )
    missing = []
    for section, keys in REQUIRED_KEYS.items():
        node = cal if section is None else cal.get(section)
        if not isinstance(node, dict):
            if section in cal:  # present but not an object (absent: already reported)
                missing.append(f"{section} (not an object)")
            continue
        missing += [k if section is None else f"{section}.{k}" for k in keys if k not in node]
    if missing:
        raise CalibrationError(f"{source}: missing key(s): {', '.join(missing)}")
    return cal


def load_calibration(path=None) -> dict:
    """Load a calibration file (default: the shipped ``slipest/data/calibration.json``) and validate it.

    Raises :class:`CalibrationError` when the file is missing, is not JSON,
    has another ``format_version`` or lacks a documented key.
    """
    cal, source = read_json(path, "calibration.json", "calibration", "tools/calibrate.py --write-package-data",
                            CalibrationError)
    return validate_calibration(cal, source)


def save_calibration(cal: dict, path) -> Path:
    """Validate and write a calibration dict as JSON (parent directories created). Returns the path."""
    validate_calibration(cal)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(cal, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return path
