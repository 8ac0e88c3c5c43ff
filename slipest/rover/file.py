"""The rover file: one JSON document holding a rover's calibrated model and its calibration report.

Written by ``slipest calibrate`` (:func:`save_rover`), read by ``--rover
FILE`` and the Python API (:func:`load_rover`). Versioned by
``format_version`` (:data:`FORMAT_VERSION`); a file of another version, of
another kind, made for another number of legs or on another inverse model
than the one it is loaded with is refused with a :class:`RoverFileError`
naming the file and what is wrong. Layout (units SI, features in
:data:`slipest.features.FEATURE_UNITS`)::

    format_version  1
    kind            "slipest rover model"
    created_by, created_utc, slipest_version
    n_legs          legs of the rover's wheel-leg
    base_model      {"source": "shipped" | a file path, "sha256": of the inverse-model file}
    discrepancy     the feature discrepancy (slipest.rover.discrepancy.Discrepancy.to_dict)
    extra_cov       (d, d) extra covariance of the features
    eq515           the refitted Eq. 5.15 calibration ({"eq515": {...}, "model": {"params": {"nL", "omega"}}}), or
                    null: none (``--method eq515`` then refuses the file)
    disturbance     null, or the phase-locked az disturbance removed from the samples ({"phase": [rad], "az": [m/s^2]})
    interval_scale  factor (>= 1) on the estimator's standard deviations (absent: 1)
    angle_offset    encoder angle minus true leg angle [rad], subtracted from every theta sample (absent: 0)
    report          what the calibration found (slipest.rover.calibrate.Calibration.report)
"""

from __future__ import annotations

import datetime
import hashlib
import json
from pathlib import Path

import numpy as np

from slipest.json_files import read_json
from slipest.rover.discrepancy import Discrepancy
from slipest.rover.surrogate import RoverSurrogate

#: Version of the rover file format this slipest reads and writes.
FORMAT_VERSION = 1
#: The ``kind`` of a rover file.
KIND = "slipest rover model"
#: Keys every rover file has.
REQUIRED = ("format_version", "kind", "n_legs", "base_model", "discrepancy", "extra_cov", "eq515", "report")


class RoverFileError(ValueError):
    """A rover file is missing, unreadable, of another version or kind, or does not fit what it is used with."""


def model_fingerprint(path=None) -> str:
    """sha256 of an inverse-model file (None: the shipped one)."""
    if path is None:
        from importlib import resources

        data = resources.files("slipest").joinpath("data/inverse_model.npz").read_bytes()
    else:
        data = Path(path).read_bytes()
    return hashlib.sha256(data).hexdigest()


def rover_document(model: RoverSurrogate, report: dict, created_by: str, base_path=None) -> dict:
    """The rover file's document of a calibrated model (``base_path``: the inverse-model file it corrects,
    None: the shipped one)."""
    from slipest import __version__

    return {
        "format_version": FORMAT_VERSION,
        "kind": KIND,
        "created_by": created_by,
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "slipest_version": __version__,
        "n_legs": int(model.n_legs),
        "base_model": {"source": "shipped" if base_path is None else str(Path(base_path).resolve()),
                       "sha256": model_fingerprint(base_path)},
        "discrepancy": model.discrepancy.to_dict(),
        "extra_cov": np.asarray(model.extra_cov).tolist(),
        "eq515": model.eq515,
        "disturbance": model.disturbance,
        "interval_scale": float(model.interval_scale),
        "angle_offset": float(model.angle_offset),
        "report": report,
    }


def save_rover(model: RoverSurrogate, report: dict, path, created_by: str = "slipest calibrate",
               base_path=None) -> Path:
    """Write the rover file (parent directories created; NaN written as null). Returns the path."""
    doc = rover_document(model, report, created_by, base_path)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_json_safe(doc), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return path


def _json_safe(x):
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.ndarray):
        return _json_safe(x.tolist())
    return x


def is_rover_document(doc) -> bool:
    """Whether a JSON document is of the rover file's ``kind`` (whatever its version)."""
    return isinstance(doc, dict) and doc.get("kind") == KIND


def is_rover_file(path) -> bool:
    """Whether ``path`` holds a rover file's JSON (:func:`is_rover_document`); False when it cannot be read, is
    not UTF-8 JSON, or is of another kind (what ``slipest calibrate -o`` may replace without ``--overwrite``)."""
    try:
        with open(path, "rb") as fh:
            return is_rover_document(json.load(fh))
    except (OSError, ValueError):
        return False


def validate_rover(doc, source: str) -> dict:
    """Check the document's kind, version and keys; :class:`RoverFileError` naming ``source`` otherwise."""
    if not is_rover_document(doc):
        what = doc.get("kind") if isinstance(doc, dict) else type(doc).__name__
        raise RoverFileError(f"{source}: not a slipest rover file (kind {what!r}; make one with slipest calibrate)")
    version = doc.get("format_version")
    if version != FORMAT_VERSION:
        raise RoverFileError(f"{source}: format_version {version!r} is not supported (this slipest reads "
                             f"{FORMAT_VERSION}); re-run slipest calibrate on the testbed logs")
    missing = [k for k in REQUIRED if k not in doc]
    if missing:
        raise RoverFileError(f"{source}: missing key(s) {', '.join(missing)}")
    return doc


def load_rover(path, n_legs: int | None = None, base=None) -> RoverSurrogate:
    """The rover model of a rover file, ready for the estimator (``SlipEstimator(model=...)``, its
    ``method="eq515"`` included).

    n_legs: the legs of the wheel-leg it will estimate (checked when given).
    base: the inverse model it corrects (default: the one the file names, the
    shipped one or its file). :class:`RoverFileError` naming the file when
    it is missing, unreadable, not a rover file, of another version, made for
    another number of legs, or made on another inverse model, or when a
    numeric field holds no JSON number (``"interval_scale": "5"``, a boolean:
    refused naming the field, not converted). The model covers
    the testbed's leg speeds within 10 % (the report's ``leg_speed.range``:
    :class:`~slipest.rover.surrogate.RoverSurrogate`'s ``testbed_speeds``); the
    estimator flags a cycle at another speed ``"speed"``."""
    doc, source = read_json(path, "", "rover", "slipest calibrate", RoverFileError)
    source = f"rover file {source}"
    validate_rover(doc, source)
    legs = doc["n_legs"]
    if isinstance(legs, bool) or not isinstance(legs, int) or legs < 1:
        raise RoverFileError(f"{source}: n_legs {legs!r} is not a number of legs")
    if n_legs is not None and legs != int(n_legs):
        raise RoverFileError(f"{source} was made for a {legs}-leg wheel-leg, not {n_legs} legs: calibrate this "
                             "rover's own testbed logs (slipest calibrate --legs N)")
    _check_sections(doc, source)
    interval_scale = _json_number(doc.get("interval_scale", 1.0), "interval_scale", source)
    angle_offset = _json_number(doc.get("angle_offset", 0.0), "angle_offset", source)
    if base is None:
        base = _base_model(doc["base_model"], source)
    try:
        disc = Discrepancy.from_dict(doc["discrepancy"])
        model = RoverSurrogate.of(base, disc, np.asarray(doc["extra_cov"], dtype=float), rover_legs=legs,
                                  eq515=doc["eq515"], source=source, disturbance=doc.get("disturbance"),
                                  interval_scale=interval_scale, angle_offset=angle_offset,
                                  testbed_speeds=_testbed_speeds(doc, source))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise RoverFileError(f"{source}: malformed rover model ({type(exc).__name__}: {exc})") from None
    if base.n_legs != legs:
        raise RoverFileError(f"{source}: the inverse model is for {base.n_legs} legs, the rover file for {legs}")
    return model


def _testbed_speeds(doc: dict, source: str) -> tuple | None:
    """The testbed logs' leg speeds ``(lo, hi)`` [rad/s] the report keeps (``report.leg_speed.range``), which the
    rover model is used within (:data:`slipest.rover.surrogate.SPEED_MARGIN`); None for a file without them."""
    report = doc["report"]
    leg = report.get("leg_speed") if isinstance(report, dict) else None
    speeds = leg.get("range") if isinstance(leg, dict) else None
    if speeds is None:
        return None
    if not (isinstance(speeds, list) and len(speeds) == 2 and all(_number(v) and v > 0 for v in speeds)
            and speeds[0] <= speeds[1]):
        raise RoverFileError(f"{source}: report.leg_speed.range must be the testbed's leg speeds [lo, hi] rad/s, "
                             f"got {speeds!r}")
    return float(speeds[0]), float(speeds[1])


#: Eq. 5.15's coefficients a rover file's ``eq515`` section holds (slipest.inverse.eq515.Eq515Inverse).
EQ515_KEYS = ("amu", "bmu", "cI", "cmu", "cK", "rmse_end_to_end")
#: Largest magnitude of an ``extra_cov`` entry (features' units squared): far above any feature's scatter.
EXTRA_COV_LIMIT = 1e10


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)


def _json_type(x) -> str:
    """What a JSON value is, in a user's words (for the error messages)."""
    if x is None:
        return "null"
    if isinstance(x, bool):
        return "a boolean"
    if isinstance(x, str):
        return "a string"
    return "an object" if isinstance(x, dict) else "an array" if isinstance(x, list) else type(x).__name__


def _json_number(x, field: str, source: str) -> float:
    """A numeric field's value as a float; RoverFileError naming ``field`` when it is no JSON number (a string
    such as ``"5"``, a boolean, null: refused, as ``format_version`` ``"1"`` is, not converted). Whether the
    number is in range is the model's check (:class:`~slipest.rover.surrogate.RoverSurrogate`)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise RoverFileError(f"{source}: {field} {x!r} is {_json_type(x)}, not a number")
    return float(x)


def _check_json_numbers(x, field: str, source: str) -> None:
    """RoverFileError naming the entry (``field[i][j]``) when an array of numbers holds something else than a JSON
    number or null (null: a non-finite value as :func:`save_rover` writes it, which the model's checks refuse
    where it matters): a string or a boolean would otherwise be converted by numpy."""
    if isinstance(x, list):
        for i, v in enumerate(x):
            _check_json_numbers(v, f"{field}[{i}]", source)
    elif x is not None:
        _json_number(x, field, source)


def _check_sections(doc: dict, source: str) -> None:
    """RoverFileError naming the field when a section has the wrong type or a value that cannot be used."""
    if not isinstance(doc["discrepancy"], dict):
        raise RoverFileError(f"{source}: discrepancy must be an object, not {type(doc['discrepancy']).__name__}")
    disc = doc["discrepancy"]
    for key in ("center", "halfwidth", "terms", "coef"):
        _check_json_numbers(disc.get(key), f"discrepancy.{key}", source)
    cov = doc["extra_cov"]
    _check_json_numbers(cov, "extra_cov", source)
    disturbance = doc.get("disturbance")
    if isinstance(disturbance, dict):
        for key in ("phase", "az"):
            _check_json_numbers(disturbance.get(key), f"disturbance.{key}", source)
    try:
        arr = np.asarray(cov, dtype=float)
    except (TypeError, ValueError):
        raise RoverFileError(f"{source}: extra_cov must be a square matrix of numbers") from None
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
        raise RoverFileError(f"{source}: extra_cov must be a square matrix of numbers, not of shape {arr.shape}")
    if not np.isfinite(arr).all() or np.abs(arr).max(initial=0.0) > EXTRA_COV_LIMIT:
        raise RoverFileError(f"{source}: extra_cov holds a value that is not a finite number below "
                             f"{EXTRA_COV_LIMIT:g}")
    if (np.diag(arr) < 0).any() or not np.allclose(arr, arr.T, rtol=1e-6, atol=1e-12):
        raise RoverFileError(f"{source}: extra_cov is not a covariance (symmetric, non-negative diagonal)")
    eq = doc["eq515"]
    if eq is None:  # a rover model made without Eq. 5.15 (the default method only; --method eq515 refuses it)
        return
    coef = eq.get("eq515") if isinstance(eq, dict) else None
    if not isinstance(coef, dict):
        raise RoverFileError(f"{source}: eq515 must hold the refitted Eq. 5.15 coefficients "
                             f"({{\"eq515\": {{{', '.join(EQ515_KEYS)}}}, ...}}); re-run slipest calibrate")
    bad = [k for k in EQ515_KEYS if k not in coef or not (coef[k] is None or _number(coef[k]))]
    if bad:
        raise RoverFileError(f"{source}: eq515.eq515.{bad[0]} is {coef.get(bad[0], 'missing')!r}, not a finite "
                             "number (or null: not fitted)")
    if coef["rmse_end_to_end"] is not None and not coef["rmse_end_to_end"] > 0:
        raise RoverFileError(f"{source}: eq515.eq515.rmse_end_to_end must be > 0 (the interval's width)")
    params = eq.get("model", {})
    params = params.get("params", {}) if isinstance(params, dict) else None
    if not isinstance(params, dict):
        raise RoverFileError(f"{source}: eq515.model.params must be an object")
    if "nL" in params and not (isinstance(params["nL"], int) and not isinstance(params["nL"], bool)
                               and params["nL"] >= 1):
        raise RoverFileError(f"{source}: eq515.model.params.nL {params['nL']!r} is not a number of legs")
    if "omega" in params and not (_number(params["omega"]) and params["omega"] > 0):
        raise RoverFileError(f"{source}: eq515.model.params.omega {params['omega']!r} is not a leg speed [rad/s]")


def model_from_files(model=None, rover=None, n_legs: int | None = None):
    """The estimator's model from what a user names: a rover file (:func:`load_rover`, checked against
    ``n_legs`` when given), an inverse-model file, or neither (None: the shipped model). ValueError when both
    are named; the loaders' errors (ValueErrors naming the file) otherwise."""
    if model and rover:
        raise ValueError("--model and --rover are exclusive: a rover file already names the inverse model it "
                         "corrects")
    if rover:
        return load_rover(rover, n_legs=n_legs)
    if model:
        from slipest.inverse.surrogate import load_inverse_model

        return load_inverse_model(model)
    return None


def _base_model(info, source: str):
    from slipest.inverse.surrogate import InverseModelError, load_inverse_model

    if not isinstance(info, dict) or not isinstance(info.get("source"), str):
        raise RoverFileError(f"{source}: base_model.source must name its inverse model (\"shipped\" or a file)")
    where = None if info["source"] == "shipped" else info["source"]
    try:
        model = load_inverse_model(where)
        fingerprint = model_fingerprint(where)
    except (InverseModelError, OSError) as exc:
        raise RoverFileError(f"{source}: its inverse model cannot be loaded ({exc})") from None
    if info.get("sha256") != fingerprint:
        what = "the shipped inverse model" if where is None else f"the inverse model {where}"
        raise RoverFileError(f"{source} was calibrated on another version of {what} (its file changed since): "
                             "re-run slipest calibrate on the testbed logs")
    return model


__all__ = ["FORMAT_VERSION", "KIND", "RoverFileError", "is_rover_document", "is_rover_file", "load_rover",
           "model_fingerprint", "model_from_files", "rover_document", "save_rover", "validate_rover"]
