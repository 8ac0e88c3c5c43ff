"""The feature surrogate: the measurement model of the multi-feature inverse (pure computation + its JSON file).

Fitted offline on simulated cycles over the estimator's envelope
(:mod:`slipest.inverse.simdata`, ``tools/train_inverse.py``), it gives the
distribution of one cycle's modelled features (:data:`MODEL_FEATURES`, from
:mod:`slipest.features`) given the slip, the soil, the leg speed and the
IMU's smoothed noise level::

    f ~ N(mu(x), R(omega, noise_smooth)),   x = (slip, kS, phiS, dphi, omega, noise_smooth)

* ``mu``: per feature, a polynomial in the normalised ``x`` in the tensor
  Legendre basis (well conditioned at high degree; least squares), with a
  *term schedule*: the total degree in (slip, kS, phiS, dphi) allowed for each
  pair of degrees in ``omega`` and ``noise_smooth`` (:func:`schedule_terms`);
* ``R``: the covariance of the residuals, linear in
  ``(1, u, u^2, s^2, s^2 u)`` (:data:`COV_BASIS`; ``u`` the normalised leg
  speed, ``s = noise_smooth`` [g]): what the IMU noise leaves on the features
  and what a smooth law cannot follow (the oscillation's phase at the end of
  the stance jumps about with small parameter changes, so amplitude features
  scatter by about 30 % around any smooth law while the break-away angle is
  followed to a few percent).

Units: slip [-], kS [N/m], phiS, phiD, dphi [rad], omega [rad/s],
noise_smooth [g]; features in :data:`slipest.features.FEATURE_UNITS`. The
model is valid over ``ranges`` with ``phiS - dphi >= phid_min``; ``covered``
says what the estimator promises (the rest is a margin).

The shipped model is ``slipest/data/inverse_model.json`` (versioned,
:data:`FORMAT_VERSION`), read by :func:`load_inverse_model`.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipest.features import FEATURE_NAMES
from slipest.json_files import read_json

#: Version of the inverse model file format (3: speed and noise inputs; 1 and 2 are refused).
FORMAT_VERSION = 3
#: Variables of the surrogate, in order.
VARIABLES = ("slip", "kS", "phiS", "dphi", "omega", "noise_smooth")
#: Features the shipped model uses: the smoothed, noise-referred ones (``delta_a``, the raw max - min, grows
#: with the IMU's noise and rate; ``n_crossings`` repeats ``zc_rate``; ``noise``, ``omega``, ``noise_smooth``
#: are inputs; ``stick_mean`` was too noisy to help).
MODEL_FEATURES = ("peak_pos", "peak_neg", "rms", "rms_q1", "rms_q2", "rms_q3", "rms_q4", "onset", "energy_q10",
                  "energy_q50", "energy_q90", "zc_rate", "osc_freq", "rice_freq")
#: Basis of the residual covariance in the normalised speed ``u`` and the smoothed noise ``s`` [g].
COV_BASIS = ("1", "u", "u^2", "s^2", "s^2 u")

#: Rows per block when building design matrices [-].
_CHUNK = 20000


class InverseModelError(ValueError):
    """The inverse model file is missing, of another format version, or malformed."""


def schedule_terms(schedule: dict) -> np.ndarray:
    """Tensor Legendre terms ``(T, 6)`` (degrees of the :data:`VARIABLES`) of a term schedule.

    ``schedule``: ``{(omega degree, noise degree): total degree in (slip, kS, phiS, dphi)}``.
    """
    out = []
    for (jw, js), d in schedule.items():
        for e in itertools.product(range(int(d) + 1), repeat=4):
            if sum(e) <= d:
                out.append(e + (int(jw), int(js)))
    out.sort(key=lambda e: (sum(e), e[4], e[5], tuple(-v for v in e)))
    return np.array(out, dtype=np.int64)


def _design(u: np.ndarray, terms: np.ndarray) -> np.ndarray:
    """Design matrix ``(n, T)`` of the tensor terms at normalised points ``u`` ``(n, 6)``."""
    b = np.polynomial.legendre.legvander(u, int(terms.max()))  # (n, 6, degree + 1)
    out = b[:, 0, terms[:, 0]].copy()
    for v in range(1, u.shape[1]):
        out *= b[:, v, terms[:, v]]
    return out


def _cov_basis(u_omega, s) -> np.ndarray:
    """The :data:`COV_BASIS` values ``(..., 5)`` at normalised speed ``u_omega`` and smoothed noise ``s`` [g]."""
    u = np.asarray(u_omega, dtype=float)
    s2 = np.asarray(s, dtype=float) ** 2
    return np.stack(np.broadcast_arrays(np.ones_like(u), u, u * u, s2, s2 * u), axis=-1)


@dataclass(frozen=True)
class FeatureSurrogate:
    """``mu`` and ``R`` of the module docstring.

    features: names of the modelled features (subset of ``FEATURE_NAMES``).
    center, halfwidth: ``(6,)`` normalisation ``u = (x - center) / halfwidth`` (SI).
    ranges: ``(6, 2)`` [lo, hi] of the training draw; phid_min [rad]: its
    smallest ``phiS - dphi``. terms: ``(T, 6)`` Legendre degrees per
    variable; coef: ``(T, d)``. cov_coef: ``(5, d, d)`` covariance
    coefficients of :data:`COV_BASIS` (feature units squared). covered:
    what the estimator promises, ``{name: [lo, hi]}`` for some of the
    variables and ``"phid_min"``. meta: provenance (free-form).
    """

    features: tuple
    center: np.ndarray
    halfwidth: np.ndarray
    ranges: np.ndarray
    phid_min: float
    terms: np.ndarray
    coef: np.ndarray
    cov_coef: np.ndarray
    covered: dict
    meta: dict

    def __post_init__(self):
        d = len(self.features)
        unknown = [f for f in self.features if f not in FEATURE_NAMES]
        if unknown:
            raise InverseModelError(f"inverse model uses unknown feature(s) {unknown}")
        t = self.terms
        if t.ndim != 2 or t.shape[1] != len(VARIABLES) or (t < 0).any():
            raise InverseModelError(f"inverse model terms must be (T, {len(VARIABLES)}) degrees >= 0")
        shape_ok = self.center.shape == self.halfwidth.shape == (len(VARIABLES),) and self.ranges.shape == (len(VARIABLES), 2)
        if not shape_ok or not np.all(np.isfinite(self.center)) or not np.all(np.isfinite(self.halfwidth) & (self.halfwidth > 0)):
            raise InverseModelError(f"inverse model center, halfwidth and ranges must be {len(VARIABLES)} finite values "
                                    "(halfwidth > 0)")
        if self.coef.shape != (self.terms.shape[0], d) or self.cov_coef.shape != (len(COV_BASIS), d, d):
            raise InverseModelError(
                f"inverse model shapes do not agree: {self.terms.shape[0]} terms, coef {self.coef.shape}, "
                f"cov_coef {self.cov_coef.shape}, {d} features"
            )
        if not (np.all(np.isfinite(self.coef)) and np.all(np.isfinite(self.cov_coef))):
            raise InverseModelError("inverse model has non-finite coefficients")
        for name in self.covered:
            if name != "phid_min" and name not in VARIABLES:
                raise InverseModelError(f"inverse model 'covered' names an unknown variable {name!r}")

    # ------------------------------------------------------------------ what it is for
    @property
    def n_legs(self) -> int:
        """Legs of the wheel-leg the model was trained for [-]."""
        return int(self.meta.get("training", {}).get("n_legs", 4))

    def covered_range(self, name: str) -> tuple[float, float]:
        """``(lo, hi)`` of a variable the estimator promises (the training range when ``covered`` omits it)."""
        if name in self.covered:
            lo, hi = self.covered[name]
            return float(lo), float(hi)
        j = VARIABLES.index(name)
        return float(self.ranges[j, 0]), float(self.ranges[j, 1])

    @property
    def omega(self) -> float:
        """Middle of the covered leg-speed range [rad/s] (what a single-speed caller should drive at)."""
        lo, hi = self.covered_range("omega")
        return 0.5 * (lo + hi)

    @property
    def columns(self) -> np.ndarray:
        """Column of each modelled feature in a full feature row."""
        return np.array([FEATURE_NAMES.index(f) for f in self.features])

    def observe(self, rows) -> np.ndarray:
        """The modelled features ``(..., d)`` of full feature rows ``(..., len(FEATURE_NAMES))``."""
        return np.asarray(rows, dtype=float)[..., self.columns]

    # ------------------------------------------------------------------ evaluation
    def normalise(self, x) -> np.ndarray:
        """``u`` of points ``x`` ``(..., 6)`` in the order of :data:`VARIABLES` (SI)."""
        return (np.asarray(x, dtype=float) - self.center) / self.halfwidth

    def mean(self, x) -> np.ndarray:
        """Modelled mean features ``(..., d)`` at points ``x`` ``(..., 6)`` (order of :data:`VARIABLES`, SI)."""
        u = self.normalise(x)
        flat = u.reshape(-1, len(VARIABLES))
        out = np.empty((flat.shape[0], self.coef.shape[1]))
        for i in range(0, flat.shape[0], _CHUNK):
            out[i : i + _CHUNK] = _design(flat[i : i + _CHUNK], self.terms) @ self.coef
        return out.reshape(u.shape[:-1] + (self.coef.shape[1],))

    def cov(self, omega: float, noise_smooth: float) -> np.ndarray:
        """``R`` ``(d, d)`` at leg speed ``omega`` [rad/s] and smoothed noise ``noise_smooth`` [g]
        (made positive definite: eigenvalues at least 1e-6 of the largest)."""
        u = (float(omega) - self.center[4]) / self.halfwidth[4]
        r = np.tensordot(_cov_basis(u, float(noise_smooth)), self.cov_coef, axes=(0, 0))
        r = 0.5 * (r + r.T)
        ev, vec = np.linalg.eigh(r)
        ev = np.maximum(ev, 1e-6 * max(float(ev.max()), 1e-300))
        return (vec * ev) @ vec.T

    def mean_on_grid(self, slip_nodes, kS_levels, phiS_levels, dphi_levels, omega: float, noise_smooth: float) -> np.ndarray:
        """Mean features on a tensor grid at one leg speed [rad/s] and smoothed noise [g]:
        ``(nk, nphiS, ndphi, K, d)``, contracted one variable at a time (fast for large grids)."""
        deg = int(self.terms[:, :4].max())
        p = deg + 1
        uw = (float(omega) - self.center[4]) / self.halfwidth[4]
        us = (float(noise_smooth) - self.center[5]) / self.halfwidth[5]
        pw = np.polynomial.legendre.legvander(np.array([uw]), int(self.terms[:, 4].max()))[0]
        ps = np.polynomial.legendre.legvander(np.array([us]), int(self.terms[:, 5].max()))[0]
        dense = np.zeros((p, p, p, p, self.coef.shape[1]))
        w = pw[self.terms[:, 4]] * ps[self.terms[:, 5]]
        np.add.at(dense, tuple(self.terms[:, :4].T), self.coef * w[:, None])
        levels = [np.asarray(v, dtype=float) for v in (slip_nodes, kS_levels, phiS_levels, dphi_levels)]
        bases = [np.polynomial.legendre.legvander((lv - self.center[j]) / self.halfwidth[j], deg)
                 for j, lv in enumerate(levels)]
        # one variable at a time, each a matrix product: (slip a, kS b, phiS c, dphi e, f) -> (kS, phiS, dphi, slip, f)
        x = np.tensordot(dense, bases[3], axes=([3], [1]))  # (a, b, c, f, dphi)
        x = np.tensordot(x, bases[2], axes=([2], [1]))  # (a, b, f, dphi, phiS)
        x = np.tensordot(x, bases[1], axes=([1], [1]))  # (a, f, dphi, phiS, kS)
        x = np.tensordot(x, bases[0], axes=([0], [1]))  # (f, dphi, phiS, kS, slip)
        return np.ascontiguousarray(x.transpose(3, 2, 1, 4, 0))

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, x, rows, schedule: dict, features=MODEL_FEATURES, ranges=None, phid_min: float = 0.0,
            covered: dict | None = None, meta: dict | None = None, progress=None) -> "FeatureSurrogate":
        """Least-squares fit on a training table (rows with non-finite values dropped).

        x: ``(n, 6)`` points (order of :data:`VARIABLES`, SI); rows: ``(n,
        len(FEATURE_NAMES))`` full feature rows; schedule: see
        :func:`schedule_terms`; ranges: ``(6, 2)`` normalisation box
        (default: the data's min/max). ``progress(k)``: called with the rows
        done after each block.
        """
        x = np.asarray(x, dtype=float)
        cols = [FEATURE_NAMES.index(f) for f in features]
        y = np.asarray(rows, dtype=float)[:, cols]
        ok = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(x), axis=1)
        terms = schedule_terms(schedule)
        if ok.sum() < 10 * len(terms):
            raise ValueError(f"too few training rows ({ok.sum()}) for {len(terms)} terms")
        x, y = x[ok], y[ok]
        rng_ = np.array(ranges, dtype=float) if ranges is not None else np.column_stack([x.min(0), x.max(0)])
        center = rng_.mean(axis=1)
        half = np.where(rng_[:, 1] > rng_[:, 0], 0.5 * (rng_[:, 1] - rng_[:, 0]), 1.0)
        u = (x - center) / half
        # normal equations accumulated in blocks (a 5000-term design of 4e5 rows would take 16 GB);
        # the Legendre basis keeps them well conditioned; a tiny ridge guards the rank
        a = np.zeros((len(terms), len(terms)))
        b = np.zeros((len(terms), y.shape[1]))
        for i in range(0, u.shape[0], _CHUNK):
            dm = _design(u[i : i + _CHUNK], terms)
            a += dm.T @ dm
            b += dm.T @ y[i : i + _CHUNK]
            if progress:
                progress(dm.shape[0])
        coef = np.linalg.solve(a + 1e-8 * np.trace(a) / len(terms) * np.eye(len(terms)), b)
        resid = np.empty_like(y)
        for i in range(0, u.shape[0], _CHUNK):
            resid[i : i + _CHUNK] = y[i : i + _CHUNK] - _design(u[i : i + _CHUNK], terms) @ coef
        basis = _cov_basis(u[:, 4], x[:, 5])  # (n, 5)
        gram = basis.T @ basis
        outer = np.einsum("nb,ni,nj->bij", basis, resid, resid)
        cov_coef = np.linalg.solve(gram, outer.reshape(len(COV_BASIS), -1)).reshape(outer.shape)
        return cls(tuple(features), center, half, rng_, float(phid_min), terms, coef, cov_coef, dict(covered or {}),
                   dict(meta or {}))

    # ------------------------------------------------------------------ file
    def to_dict(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "kind": "feature-surrogate",
            "variables": list(VARIABLES),
            "features": list(self.features),
            "center": self.center.tolist(),
            "halfwidth": self.halfwidth.tolist(),
            "ranges": self.ranges.tolist(),
            "phid_min": self.phid_min,
            "terms": self.terms.tolist(),
            "coef": self.coef.tolist(),
            "cov_basis": list(COV_BASIS),
            "cov_coef": self.cov_coef.tolist(),
            "covered": self.covered,
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "inverse model") -> "FeatureSurrogate":
        if not isinstance(d, dict):
            raise InverseModelError(f"{source}: expected a JSON object")
        if d.get("format_version") != FORMAT_VERSION:
            raise InverseModelError(
                f"{source}: format_version {d.get('format_version')!r} is not supported (this slipest reads "
                f"{FORMAT_VERSION}); regenerate it with tools/train_inverse.py"
            )
        keys = ("variables", "features", "center", "halfwidth", "ranges", "phid_min", "terms", "coef", "cov_basis",
                "cov_coef")
        missing = [k for k in keys if k not in d]
        if missing:
            raise InverseModelError(f"{source}: missing key(s) {missing}")
        if list(d["variables"]) != list(VARIABLES):
            raise InverseModelError(f"{source}: variables {d['variables']} are not {list(VARIABLES)}")
        if list(d["cov_basis"]) != list(COV_BASIS):
            raise InverseModelError(f"{source}: cov_basis {d['cov_basis']} is not {list(COV_BASIS)}")
        try:
            return cls(
                features=tuple(d["features"]),
                center=np.asarray(d["center"], dtype=float),
                halfwidth=np.asarray(d["halfwidth"], dtype=float),
                ranges=np.asarray(d["ranges"], dtype=float),
                phid_min=float(d["phid_min"]),
                terms=np.asarray(d["terms"], dtype=np.int64),
                coef=np.asarray(d["coef"], dtype=float),
                cov_coef=np.asarray(d["cov_coef"], dtype=float),
                covered=dict(d.get("covered", {})),
                meta=dict(d.get("meta", {})),
            )
        except InverseModelError as exc:
            raise InverseModelError(f"{source}: {exc}") from None
        except (ValueError, TypeError) as exc:  # ragged or non-numeric arrays
            raise InverseModelError(f"{source}: malformed inverse model ({exc})") from None


_CACHE: dict = {}


def load_inverse_model(path=None) -> FeatureSurrogate:
    """Load the inverse model (default: the shipped ``slipest/data/inverse_model.json``; cached).

    Raises :class:`InverseModelError` when missing, not JSON, of another version or malformed.
    """
    key = None if path is None else str(path)
    if key in _CACHE:
        return _CACHE[key]
    doc, source = read_json(path, "inverse_model.json", "inverse model", "tools/train_inverse.py", InverseModelError)
    model = FeatureSurrogate.from_dict(doc, source)
    _CACHE[key] = model
    return model


def save_inverse_model(model: FeatureSurrogate, path) -> Path:
    """Write the model as JSON (parent directories created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(model.to_dict(), allow_nan=False) + "\n", encoding="utf-8")
    return path


__all__ = ["FORMAT_VERSION", "VARIABLES", "MODEL_FEATURES", "COV_BASIS", "InverseModelError", "schedule_terms",
           "FeatureSurrogate", "load_inverse_model", "save_inverse_model"]
