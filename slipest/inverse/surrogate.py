"""The multi-feature inverse: a surrogate of the feature vector used as a measurement model.

Instead of inverting ``Da`` alone with the soil given (Eq. 5.15), the
project fits, offline, the **forward** map from slip and soil to the mean
feature vector of a cycle (the spec's "calibrate forward, then invert",
carried to the whole waveform), with the spread around it:

    f = mu(slip, kS, phiD, dphi) + e,    e ~ N(0, R)

* ``f``: the features :data:`MODEL_FEATURES` of one cycle
  (:mod:`slipest.features`), amplitudes in g, angles in rad, frequencies in Hz;
* ``mu``: one polynomial of total degree :attr:`FeatureSurrogate.degree` in
  the normalised ``(slip, kS, phiD, dphi)`` per feature, in the tensor
  Legendre basis (well conditioned at high degree; least squares);
* ``R``: the covariance of the residuals over the training set. It holds
  the IMU noise (training used 0.01 g at 1 kHz) **and** what a smooth
  surrogate cannot follow: in this model the waveform's end (the phase of
  the oscillation when the stance ends) jumps about with small parameter
  changes, so ``Da`` and the RMS features scatter by about 30 % around any
  smooth law, while the break-away angle is followed to a few percent.

Slip is then inverted by Bayes on a slip grid (likelihood of ``f``), with
the soil known (:meth:`SurrogateInverse.slip`, a 1-D grid) or unknown (a
uniform prior over a soil grid, marginalised). :mod:`slipest.estimator`
does the same recursively, learning the soil over cycles.

The model is package data, ``slipest/data/inverse_model.json`` (versioned,
:data:`FORMAT_VERSION`), written by ``tools/train_inverse.py``;
:func:`load_inverse_model` reads it. Units: slip [-], kS [N/m], phiS,
phiD, dphi [rad].
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slipest.features import FEATURE_NAMES
from slipest.inverse.base import SlipInverse, Soil
from slipest.inverse.grid_kernels import grid_loglik, marginal_from_rows, node_moments, select_cells
from slipest.json_files import read_json

#: Version of the inverse model file format.
#: 2: Legendre basis (1 was monomials; such a file is refused with a clear message).
FORMAT_VERSION = 2
#: Variables of the surrogate, in order.
VARIABLES = ("slip", "kS", "phiD", "dphi")
#: Features the shipped model uses (``noise`` and ``n_crossings`` are left out:
#: the first says nothing of slip or soil, the second repeats ``zc_rate``;
#: ``stick_mean`` was tried and left out: too noisy at 0.01 g to change the
#: results on the development draws).
MODEL_FEATURES = tuple(n for n in FEATURE_NAMES if n not in ("noise", "n_crossings", "stick_mean"))
#: Default slip grid of the inversions [-]: 0 to 0.55 by 0.01.
SLIP_NODES = np.round(np.arange(0.0, 0.5501, 0.01), 6)


class InverseModelError(ValueError):
    """The inverse model file is missing, of another format version, or malformed."""


#: Rows per block when building design matrices [-].
_CHUNK = 20000


def _basis(u, degree: int) -> np.ndarray:
    """Legendre polynomials ``P_0..P_degree`` at ``u`` (any shape): shape ``u.shape + (degree + 1,)``."""
    return np.polynomial.legendre.legvander(np.asarray(u, dtype=float), degree)


def _design(u, terms) -> np.ndarray:
    """Design matrix ``(n, T)`` of the tensor terms at normalised points ``u`` ``(n, 4)``."""
    b = _basis(u, int(terms.max()))
    return b[:, 0, terms[:, 0]] * b[:, 1, terms[:, 1]] * b[:, 2, terms[:, 2]] * b[:, 3, terms[:, 3]]


def _evaluate(u, terms, coef) -> np.ndarray:
    """The polynomials at normalised points ``u`` ``(n, 4)``: ``(n, d)``, a block of rows at a time
    (bounded memory at high degree)."""
    out = np.empty((u.shape[0], coef.shape[1]))
    for i in range(0, u.shape[0], _CHUNK):
        out[i : i + _CHUNK] = _design(u[i : i + _CHUNK], terms) @ coef
    return out


def _terms(degree: int) -> np.ndarray:
    t = [e for e in itertools.product(range(degree + 1), repeat=4) if sum(e) <= degree]
    t.sort(key=lambda e: (sum(e), tuple(-v for v in e)))
    return np.array(t, dtype=np.int64)


@dataclass(frozen=True)
class FeatureSurrogate:
    """Mean feature vector as Legendre-basis polynomials in ``u = (x - center) / halfwidth``, ``x = (slip, kS, phiD, dphi)``.

    features: names of the modelled features (subset of ``FEATURE_NAMES``).
    center, halfwidth: ``(4,)`` normalisation (SI). ranges: ``(4, 2)``
    [lo, hi] of the training draw (SI). degree: total degree.
    terms: ``(T, 4)`` Legendre degrees per variable. coef: ``(T, d)``. R: ``(d, d)`` residual
    covariance (feature units). meta: provenance (free-form dict).
    """

    features: tuple
    center: np.ndarray
    halfwidth: np.ndarray
    ranges: np.ndarray
    degree: int
    terms: np.ndarray
    coef: np.ndarray
    R: np.ndarray
    meta: dict
    log_offset: np.ndarray | None = None

    def __post_init__(self):
        d = len(self.features)
        if self.log_offset is None:
            object.__setattr__(self, "log_offset", np.full(d, np.nan))
        if np.shape(self.log_offset) != (d,):
            raise InverseModelError(f"inverse model log_offset must have {d} entries")
        unknown = [f for f in self.features if f not in FEATURE_NAMES]
        if unknown:
            raise InverseModelError(f"inverse model uses unknown feature(s) {unknown}")
        t = self.terms
        if t.ndim != 2 or t.shape[1] != 4 or (t < 0).any() or (t.sum(axis=1) > self.degree).any():
            raise InverseModelError(f"inverse model terms must be (T, 4) degrees >= 0 of total at most {self.degree}")
        if self.center.shape != (4,) or self.halfwidth.shape != (4,) or not np.all(np.isfinite(self.center)) \
                or not np.all(np.isfinite(self.halfwidth) & (self.halfwidth > 0)):
            raise InverseModelError("inverse model center and halfwidth must be 4 finite values (halfwidth > 0)")
        if self.coef.shape != (self.terms.shape[0], d) or self.R.shape != (d, d):
            raise InverseModelError(
                f"inverse model shapes do not agree: {self.terms.shape[0]} terms, coef {self.coef.shape}, "
                f"R {self.R.shape}, {d} features"
            )
        if not (np.all(np.isfinite(self.coef)) and np.all(np.isfinite(self.R))):
            raise InverseModelError("inverse model has non-finite coefficients")
        try:
            np.linalg.cholesky(self.R)
        except np.linalg.LinAlgError:
            raise InverseModelError("inverse model residual covariance R is not positive definite") from None

    # ------------------------------------------------------------------ evaluation
    @property
    def n_legs(self) -> int:
        """Legs of the wheel-leg the model was trained for [-] (4 when the file does not say)."""
        return int(self.meta.get("training", {}).get("n_legs", 4))

    @property
    def omega(self) -> float:
        """Leg speed the model was trained at [rad/s] (0.63 when the file does not say)."""
        return float(self.meta.get("training", {}).get("omega", 0.63))

    @property
    def columns(self) -> np.ndarray:
        """Column of each modelled feature in a full feature row."""
        return np.array([FEATURE_NAMES.index(f) for f in self.features])

    def observe(self, rows) -> np.ndarray:
        """The modelled quantities ``(..., d)`` from full feature rows ``(..., len(FEATURE_NAMES))``:
        the model's features, log-transformed where :attr:`log_offset` says so."""
        y = np.asarray(rows, dtype=float)[..., self.columns]
        lg = np.isfinite(self.log_offset)
        if lg.any():
            y = y.copy()
            with np.errstate(invalid="ignore", divide="ignore"):
                y[..., lg] = np.log(np.maximum(y[..., lg] + self.log_offset[lg], 1e-12))
        return y

    def normalise(self, slip, kS, phiS, phiD) -> np.ndarray:
        """``u`` of shape ``(..., 4)`` from SI arrays (broadcast)."""
        slip, kS, phiS, phiD = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (slip, kS, phiS, phiD)))
        x = np.stack([slip, kS, phiD, phiS - phiD], axis=-1)
        return (x - self.center) / self.halfwidth

    def mean(self, slip, kS, phiS, phiD) -> np.ndarray:
        """Modelled mean features ``(..., d)`` at slip [-] on soil kS [N/m], phiS, phiD [rad]."""
        u = self.normalise(slip, kS, phiS, phiD)
        shape = u.shape[:-1]
        return _evaluate(u.reshape(-1, 4), self.terms, self.coef).reshape(shape + (len(self.features),))

    def whitener(self) -> np.ndarray:
        """``W`` with ``W W^T = R^-1``: ``(f - mu) @ W`` has identity covariance."""
        return np.linalg.cholesky(np.linalg.inv(self.R))

    def table(self, slip_nodes, kS_levels, phiD_levels, dphi_levels, pad_to: int = 16) -> np.ndarray:
        """Whitened mean features on a grid: ``(S, K, D)`` float32.

        Cells ``S`` in C order over (kS, phiD, dphi) levels, slip nodes ``K``;
        ``D`` = number of features padded with zeros to a multiple of ``pad_to``.
        Evaluated by contracting one variable at a time (fast for large grids).
        """
        p = self.degree + 1
        dense = np.zeros((p, p, p, p, len(self.features)))
        for t, c in zip(self.terms, self.coef):
            dense[tuple(t)] += c
        levels = [np.asarray(v, dtype=float) for v in (slip_nodes, kS_levels, phiD_levels, dphi_levels)]
        pows = [_basis((lv - self.center[j]) / self.halfwidth[j], self.degree) for j, lv in enumerate(levels)]
        x = np.einsum("ze,abcef->abczf", pows[3], dense)
        x = np.einsum("yc,abczf->abyzf", pows[2], x)
        x = np.einsum("xb,abyzf->axyzf", pows[1], x)
        x = np.einsum("sa,axyzf->xyzsf", pows[0], x)  # (kS, phiD, dphi, slip, f)
        x = x.reshape(-1, levels[0].size, len(self.features)) @ self.whitener()
        d = len(self.features)
        dpad = int(math.ceil(d / pad_to) * pad_to)
        out = np.zeros(x.shape[:2] + (dpad,), dtype=np.float32)
        out[:, :, :d] = x
        return out

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, features_2d, slip, kS, phiS, phiD, features=MODEL_FEATURES, degree: int = 14, ranges=None, meta=None,
            log_offset=None):
        """Least-squares fit on a training table (rows with non-finite features dropped).

        features_2d: ``(n, len(FEATURE_NAMES))`` full feature rows; slip, kS,
        phiS, phiD: ``(n,)`` SI. ranges: ``(4, 2)`` of (slip, kS, phiD, dphi);
        default: the data's min/max.
        """
        features_2d = np.asarray(features_2d, dtype=float)
        cols = [FEATURE_NAMES.index(f) for f in features]
        lo = np.full(len(cols), np.nan) if log_offset is None else np.asarray(log_offset, dtype=float)
        y = cls(tuple(features), np.zeros(4), np.ones(4), np.zeros((4, 2)), 0, np.zeros((1, 4), dtype=np.int64),
                np.zeros((1, len(cols))), np.eye(len(cols)), {}, lo).observe(features_2d)
        x = np.column_stack([np.asarray(v, dtype=float) for v in (slip, kS, phiD, np.asarray(phiS) - np.asarray(phiD))])
        ok = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(x), axis=1)
        if ok.sum() < 10 * len(_terms(degree)):
            raise ValueError(f"too few training rows ({ok.sum()}) for a degree-{degree} surrogate")
        x, y = x[ok], y[ok]
        rng_ = np.array(ranges, dtype=float) if ranges is not None else np.column_stack([x.min(0), x.max(0)])
        center = rng_.mean(axis=1)
        half = np.where(rng_[:, 1] > rng_[:, 0], 0.5 * (rng_[:, 1] - rng_[:, 0]), 1.0)
        terms = _terms(degree)
        u = (x - center) / half
        # normal equations accumulated in chunks (a degree-14 design of 4e5 rows would take 10 GB);
        # the Legendre basis keeps them well conditioned; a tiny ridge guards the rank
        A = np.zeros((len(terms), len(terms)))
        B = np.zeros((len(terms), y.shape[1]))
        for i in range(0, u.shape[0], _CHUNK):
            dm = _design(u[i : i + _CHUNK], terms)
            A += dm.T @ dm
            B += dm.T @ y[i : i + _CHUNK]
        coef = np.linalg.solve(A + 1e-8 * np.trace(A) / len(terms) * np.eye(len(terms)), B)
        R = np.cov((y - _evaluate(u, terms, coef)).T)
        return cls(tuple(features), center, half, rng_, degree, terms, coef, R, dict(meta or {}), lo)

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
            "degree": int(self.degree),
            "terms": self.terms.tolist(),
            "coef": self.coef.tolist(),
            "R": self.R.tolist(),
            "log_offset": [None if not np.isfinite(v) else float(v) for v in self.log_offset],
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
        missing = [k for k in ("variables", "features", "center", "halfwidth", "ranges", "degree", "terms", "coef", "R") if k not in d]
        if missing:
            raise InverseModelError(f"{source}: missing key(s) {missing}")
        if list(d["variables"]) != list(VARIABLES):
            raise InverseModelError(f"{source}: variables {d['variables']} are not {list(VARIABLES)}")
        try:
            return cls._from_fields(d)
        except InverseModelError as exc:
            raise InverseModelError(f"{source}: {exc}") from None
        except (ValueError, TypeError) as exc:  # ragged or non-numeric arrays
            raise InverseModelError(f"{source}: malformed inverse model ({exc})") from None

    @classmethod
    def _from_fields(cls, d: dict) -> "FeatureSurrogate":
        return cls(
            features=tuple(d["features"]),
            center=np.asarray(d["center"], dtype=float),
            halfwidth=np.asarray(d["halfwidth"], dtype=float),
            ranges=np.asarray(d["ranges"], dtype=float),
            degree=int(d["degree"]),
            terms=np.asarray(d["terms"], dtype=np.int64),
            coef=np.asarray(d["coef"], dtype=float),
            R=np.asarray(d["R"], dtype=float),
            meta=dict(d.get("meta", {})),
            log_offset=np.array([np.nan if v is None else float(v) for v in d.get("log_offset", [None] * len(d["features"]))]),
        )


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


# ---------------------------------------------------------------------- soil grid


@dataclass(frozen=True)
class SoilGrid:
    """The soil cells of the grid inversions: levels of kS [N/m], phiD [rad], dphi [rad] (C order)."""

    kS: np.ndarray
    phiD: np.ndarray
    dphi: np.ndarray

    @classmethod
    def default(cls, ranges=None) -> "SoilGrid":
        """11 x 10 x 31 levels over the spec's ranges (steps 100 N/m, 0.033 rad, 0.0117 rad): 3410 cells.

        The steps follow how sharply a cycle's features pin each axis down:
        ``dphi`` (the oscillation amplitude) most, ``kS`` and ``phiD`` much
        less. Measured in development (slip RMSE from the 10th cycle, seeds
        11 / 7 / 3 of ``tools/bench_accuracy.py``'s draw): 15 x 13 x 11
        levels gave 0.028 / 0.027 / 0.025; 15 x 13 x 21, 0.026 / 0.025; 11 x
        10 x 31, 0.025 / 0.023 / 0.025; more ``dphi`` levels (41) or more
        ``kS`` and ``phiD`` levels (29 x 25 x 21) gained nothing more."""
        r = np.asarray(ranges, dtype=float) if ranges is not None else np.array([[0, .5], [500, 1500], [.1, .4], [0, .35]])
        return cls(np.linspace(r[1, 0], r[1, 1], 11), np.linspace(r[2, 0], r[2, 1], 10), np.linspace(r[3, 0], r[3, 1], 31))

    @property
    def shape(self) -> tuple:
        return (self.kS.size, self.phiD.size, self.dphi.size)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def cells(self) -> np.ndarray:
        """``(S, 3)``: kS [N/m], phiS, phiD [rad] of every cell."""
        k, p, d = np.meshgrid(self.kS, self.phiD, self.dphi, indexing="ij")
        return np.column_stack([k.ravel(), (p + d).ravel(), p.ravel()])

    def steps(self) -> np.ndarray:
        """Level spacing of (kS, phiD, dphi)."""
        return np.array([np.ptp(v) / max(v.size - 1, 1) for v in (self.kS, self.phiD, self.dphi)])


# ---------------------------------------------------------------------- slip nodes


def slip_prior(nodes, hi: float = 0.5, tail: float = 4.0) -> np.ndarray:
    """Log prior over slip nodes: flat on ``[0, hi]``, ``-tail`` above (the models' range is 0-0.5)."""
    nodes = np.asarray(nodes, dtype=float)
    return np.where(nodes <= hi + 1e-9, 0.0, -float(tail))


# ---------------------------------------------------------------------- the inverse


#: Built grid tables, shared by the inverses of one model (key: model identity, grid, n_dims).
_TABLE_CACHE: dict = {}


class SurrogateInverse(SlipInverse):
    """Slip from one cycle's features by Bayes on the feature surrogate, soil known or not.

    With the soil complete (kS, phiS, phiD): the likelihood
    ``N(f; mu(slip, soil), R)`` on a fine slip grid (0-0.55 by 0.0025),
    prior flat on 0-0.5. Otherwise: marginalised over the soil grid
    (uniform over the cells, restricted to the known parts when some are
    given). Returns the posterior mean and standard deviation.
    """

    name = "surrogate"
    needs_soil = ()

    def __init__(self, model: FeatureSurrogate | None = None, grid: SoilGrid | None = None, n_dims: int | None = None):
        self.model = model or load_inverse_model()
        self.features = self.model.features
        self.grid = grid or SoilGrid.default(self.model.ranges)
        if n_dims is None:  # every modelled feature (fewer directions lose information: measured in development)
            n_dims = len(self.features)
        if not 1 <= n_dims <= len(self.features):
            raise ValueError(f"n_dims={n_dims} must be in [1, {len(self.features)}]")
        self.n_dims = int(n_dims)
        self._cols = self.model.columns
        self._W = self.model.whitener()
        self._fine = np.round(np.arange(0.0, 0.5501, 0.0025), 6)
        self._lp_fine = slip_prior(self._fine)
        self._table = None
        self._proj = None

    def _build(self) -> None:
        key = (id(self.model), self.grid.kS.tobytes(), self.grid.phiD.tobytes(), self.grid.dphi.tobytes(), self.n_dims)
        hit = _TABLE_CACHE.get(key)
        if hit is not None and hit[0] is self.model:  # same model object: reuse (one table for many wheels)
            _, self._table, self._proj, self.retained_signal = hit
            return
        full = self.model.table(SLIP_NODES, self.grid.kS, self.grid.phiD, self.grid.dphi, pad_to=1).astype(np.float64)
        d = full.shape[2]
        # keep the n_dims whitened directions along which the modelled mean varies most
        # (noise is 1 in every whitened direction, so these carry the most information)
        ev, vec = np.linalg.eigh(np.cov(full.reshape(-1, d).T))
        proj = vec[:, ::-1][:, : self.n_dims]
        dpad = int(math.ceil(self.n_dims / 8) * 8)
        table = np.zeros(full.shape[:2] + (dpad,), dtype=np.float32)
        table[:, :, : self.n_dims] = full @ proj
        self._proj = self._W @ proj  # feature row -> projected whitened coordinates
        self._table = table
        self.retained_signal = float(ev[::-1][: self.n_dims].sum() / ev.sum())
        table.flags.writeable = False
        if len(_TABLE_CACHE) >= 8:
            _TABLE_CACHE.clear()
        _TABLE_CACHE[key] = (self.model, table, self._proj, self.retained_signal)

    @property
    def table(self) -> np.ndarray:
        """The grid table ``(S, K, D)`` float32: mean features whitened and projected on the
        ``n_dims`` most informative directions (zero-padded to a multiple of 8); built on first use."""
        if self._table is None:
            self._build()
        return self._table

    @property
    def table_t(self) -> np.ndarray:
        """:attr:`table` as ``(S, D, K)`` (contiguous)."""
        if getattr(self, "_table_t", None) is None:
            self._table_t = np.ascontiguousarray(self.table.transpose(0, 2, 1))
        return self._table_t

    @property
    def table_c(self) -> np.ndarray:
        """:attr:`table` as ``(D, K, S)`` (contiguous), the columnar layout of :mod:`slipest.inverse.grid_kernels`."""
        if getattr(self, "_table_c", None) is None:
            self._table_c = np.ascontiguousarray(self.table.transpose(2, 1, 0))
        return self._table_c

    @property
    def projection(self) -> np.ndarray:
        """``(d, n_dims)``: the modelled features (:meth:`FeatureSurrogate.observe`) times this are the
        coordinates of :attr:`table` (whitened, projected on the ``n_dims`` most informative directions)."""
        self.table  # built with the table
        return self._proj

    def whiten(self, features) -> np.ndarray:
        """A full feature row in the coordinates of :attr:`table` (float32, padded)."""
        table = self.table
        f = self.model.observe(features) @ self._proj
        out = np.zeros(table.shape[2], dtype=np.float32)
        out[: f.size] = f
        return out

    def slip_known_soil(self, features, kS, phiS, phiD) -> tuple[float, float]:
        """Posterior mean and std of slip [-] on a known soil (fine slip grid)."""
        f = self.model.observe(features)
        if not np.all(np.isfinite(f)):
            return math.nan, math.nan
        mu = self.model.mean(self._fine, kS, phiS, phiD)
        r = (f - mu) @ self._W
        ll = -0.5 * np.sum(r * r, axis=1) + self._lp_fine
        p = np.exp(ll - ll.max())
        return node_moments(p, self._fine, 0.0025**2 / 12)

    def soil_logprior(self, soil: Soil | None) -> np.ndarray:
        """Log prior over the grid cells: uniform, restricted (Gaussian, one grid step wide) to known soil parts."""
        cells = self.grid.cells()
        lp = np.zeros(cells.shape[0])
        if soil is None:
            return lp
        step = self.grid.steps()
        if soil.kS is not None:
            lp += -0.5 * ((cells[:, 0] - soil.kS) / step[0]) ** 2
        if soil.phiD is not None:
            lp += -0.5 * ((cells[:, 2] - soil.phiD) / step[1]) ** 2
        if soil.dphi is not None:
            lp += -0.5 * ((cells[:, 1] - cells[:, 2] - soil.dphi) / step[2]) ** 2
        elif soil.phiS is not None:
            lp += -0.5 * ((cells[:, 1] - soil.phiS) / step[2]) ** 2
        return lp - lp.max()

    def slip(self, features, soil: Soil | None = None) -> tuple[float, float]:
        f = np.asarray(features, dtype=float)
        if not np.all(np.isfinite(self.model.observe(f))):
            return math.nan, math.nan
        if soil is not None and soil.complete:
            return self.slip_known_soil(f, soil.kS, soil.phiS, soil.phiD)
        table_c = self.table_c
        _, K, S = table_c.shape
        dmat = np.empty((K, S), dtype=np.float32)
        lc = np.empty(S)
        lp = slip_prior(SLIP_NODES).astype(np.float32)
        grid_loglik(table_c, self.whiten(f), lp, 1.0, dmat, lc, np.empty((2, S), dtype=np.float32))
        sel = np.empty(S, dtype=np.int64)
        base = np.empty(S, dtype=np.float32)
        n = select_cells(self.soil_logprior(soil), lc, 20.0, sel, base)
        ps = np.zeros(K)
        marginal_from_rows(dmat, sel, base, n, ps)
        return node_moments(ps, SLIP_NODES, 0.01**2 / 12)
