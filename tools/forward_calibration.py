"""The forward calibration study: ``Da`` [g] as a function of slip and soil, fitted and inverted.

Offline research code used by ``tools/calibrate.py`` (and its tests), not
by the estimator: docs/model.md (section 5) recommends calibrating forward,
``Da = alpha + beta * i`` per soil with ``alpha``, ``beta`` surfaces in the
soil, then inverting, and this module fits and compares such candidates on a
sweep table (the arrays of :mod:`slipest.calibration`): in-sample,
leave-one-soil-out and on an independent validation table, and selects one
by a stated rule (:func:`select_forward`). :func:`forward_da` evaluates and
:func:`invert_slip` inverts the chosen model (slip from ``Da`` with the soil
known). :func:`build_calibration` assembles the whole calibration file
(Eq. 5.15 and the forward section), :func:`check_forward_section` validates
the forward section a file carries. Units: slip [-], kS [N/m], phiS, phiD,
dphi [rad], Da [g].
"""

from __future__ import annotations

import copy
import datetime as _dt
import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from slipest.calibration import (
    FORMAT_VERSION,
    CalibrationError,
    Eq515Fit,
    _sweep_arrays,
    linear_fit,
    linear_model_fit,
    r2_score,
    rmse,
    soil_index,
    validate_calibration,
)
from slipest.json_files import json_number

#: Variables of the forward model, in the order of a term's exponent tuple.
FORWARD_VARIABLES = ("slip", "dphi", "kS", "phiS")

#: Default slip clipping range of :func:`invert_slip` when the calibration gives none [-].
DEFAULT_SLIP_CLIP = (0.0, 0.55)


@dataclass(frozen=True)
class ForwardModel:
    """``Da`` [g] as a polynomial in the normalised ``(slip, dphi, kS, phiS)``.

    ``u_k = (x_k - center[k]) / scale[k]`` for the variables of
    :data:`FORWARD_VARIABLES` (slip [-], dphi [rad], kS [N/m], phiS [rad]);
    ``Da = sum_t coef[t] * prod_k u_k ** terms[t][k]``. ``kind`` is
    ``"linear-in-slip"`` when no term has a slip exponent above 1 (then
    :func:`invert_slip` is closed-form), else ``"polynomial"``.
    ``slip_clip``: range [-] the inversion clips to (and searches in).
    """

    name: str
    terms: tuple
    coef: np.ndarray
    center: np.ndarray
    scale: np.ndarray
    slip_clip: tuple = DEFAULT_SLIP_CLIP

    @property
    def kind(self) -> str:
        """``"linear-in-slip"`` or ``"polynomial"``."""
        return "linear-in-slip" if max(t[0] for t in self.terms) <= 1 else "polynomial"

    @property
    def slip_degree(self) -> int:
        """Highest power of slip in the model."""
        return max(t[0] for t in self.terms)

    def _soil_u(self, kS, phiS, phiD):
        kS, phiS, phiD = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (kS, phiS, phiD)))
        raw = (phiS - phiD, kS, phiS)
        return [(raw[k] - self.center[k + 1]) / self.scale[k + 1] for k in range(3)]

    def slip_coefficients(self, kS, phiS, phiD) -> np.ndarray:
        """Coefficients ``c_p`` of ``Da = sum_p c_p u_slip^p`` for given soils: shape ``(..., P + 1)``."""
        u = self._soil_u(kS, phiS, phiD)
        out = np.zeros(u[0].shape + (self.slip_degree + 1,))
        for t, c in zip(self.terms, self.coef):
            out[..., t[0]] += c * u[0] ** t[1] * u[1] ** t[2] * u[2] ** t[3]
        return out

    def da(self, slip, kS, phiS, phiD) -> np.ndarray:
        """``Da`` [g] at slip [-] on soil (kS [N/m], phiS, phiD [rad]); broadcasts."""
        slip, kS, phiS, phiD = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (slip, kS, phiS, phiD)))
        c = self.slip_coefficients(kS, phiS, phiD)
        u = (slip - self.center[0]) / self.scale[0]
        return np.sum(c * u[..., None] ** np.arange(c.shape[-1]), axis=-1)

    def invert(self, da_g, kS, phiS, phiD, clip: bool = True) -> np.ndarray:
        """Slip [-] whose modelled ``Da`` equals ``da_g`` [g] on the given soil; broadcasts.

        Linear in slip: ``(Da - alpha) / beta``, clipped to ``slip_clip``
        when ``clip`` (``beta = 0``: NaN). Higher degree: searched on a
        0.0005-step grid over ``slip_clip`` and refined linearly; with
        several solutions the smallest slip is returned, with none the slip
        of the closest modelled ``Da``. NaN ``Da`` gives NaN.
        """
        da_g, kS, phiS, phiD = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (da_g, kS, phiS, phiD)))
        c = self.slip_coefficients(kS, phiS, phiD)
        lo, hi = self.slip_clip
        if self.slip_degree <= 1:
            with np.errstate(divide="ignore", invalid="ignore"):
                beta = c[..., 1] if c.shape[-1] > 1 else np.zeros(da_g.shape)
                u = np.where(beta != 0.0, (da_g - c[..., 0]) / beta, np.nan)
            slip = self.center[0] + self.scale[0] * u
            return np.clip(slip, lo, hi) if clip else slip
        grid = np.linspace(lo, hi, int(round((hi - lo) / 0.0005)) + 1)
        ug = (grid - self.center[0]) / self.scale[0]
        flat_c = c.reshape(-1, c.shape[-1])
        flat_da = da_g.reshape(-1)
        out = np.full(flat_da.shape, np.nan)
        powers = ug[None, :] ** np.arange(c.shape[-1])[:, None]  # (P+1, G)
        for start in range(0, flat_da.size, 2048):  # bounded memory
            sl = slice(start, start + 2048)
            r = flat_c[sl] @ powers - flat_da[sl, None]  # (n, G)
            crossing = (r[:, :-1] == 0.0) | (np.sign(r[:, :-1]) != np.sign(r[:, 1:]))
            has = crossing.any(axis=1)
            first = np.argmax(crossing, axis=1)
            rows = np.arange(r.shape[0])
            r0, r1 = r[rows, first], r[rows, first + 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                frac = np.where(r1 != r0, r0 / (r0 - r1), 0.0)
            root = grid[first] + np.clip(frac, 0.0, 1.0) * (grid[1] - grid[0])
            nearest = grid[np.argmin(np.abs(r), axis=1)]
            out[sl] = np.where(has, root, nearest)
        out[~np.isfinite(flat_da)] = np.nan
        return out.reshape(da_g.shape)

    def to_dict(self) -> dict:
        """The model part of the ``forward`` section of a calibration file."""
        return {
            "name": self.name,
            "kind": self.kind,
            "variables": list(FORWARD_VARIABLES),
            "center": [float(v) for v in self.center],
            "scale": [float(v) for v in self.scale],
            "terms": [list(map(int, t)) for t in self.terms],
            "coef": [float(v) for v in self.coef],
            "slip_clip": [float(v) for v in self.slip_clip],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "ForwardModel":
        """Build from a ``forward`` section (extra keys ignored)."""
        if list(d["variables"]) != list(FORWARD_VARIABLES):
            raise CalibrationError(f"forward model variables {d['variables']} are not {list(FORWARD_VARIABLES)}")
        terms = tuple(tuple(int(e) for e in t) for t in d["terms"])
        if any(len(t) != len(FORWARD_VARIABLES) for t in terms) or len(terms) != len(d["coef"]):
            raise CalibrationError("forward model: every term needs 4 exponents and one coefficient")
        return cls(
            name=str(d["name"]),
            terms=terms,
            coef=np.asarray(d["coef"], dtype=float),
            center=np.asarray(d["center"], dtype=float),
            scale=np.asarray(d["scale"], dtype=float),
            slip_clip=tuple(float(v) for v in d.get("slip_clip", DEFAULT_SLIP_CLIP)),
        )


def _normalisation(slip, kS, phiS, phiD):
    """Centre and half-range of each forward variable (slip kept raw: centre 0, scale 1)."""
    center = [0.0]
    scale = [1.0]
    for x in (phiS - phiD, kS, phiS):
        lo, hi = float(np.min(x)), float(np.max(x))
        center.append(0.5 * (lo + hi))
        scale.append(0.5 * (hi - lo) if hi > lo else 1.0)
    return np.array(center), np.array(scale)


def soil_terms(degree: int, use_phiS: bool = True) -> list[tuple[int, int, int]]:
    """Exponent triples over (dphi, kS, phiS) of total degree <= ``degree``, low orders first."""
    out = [e for e in itertools.product(range(degree + 1), repeat=3) if sum(e) <= degree]
    if not use_phiS:
        out = [e for e in out if e[2] == 0]
    return sorted(out, key=lambda e: (sum(e), tuple(-v for v in e)))


def _design(u_vars, terms) -> np.ndarray:
    """Design matrix: one column per exponent tuple over the given normalised variables."""
    cols = []
    for t in terms:
        col = np.ones_like(u_vars[0])
        for u, e in zip(u_vars, t):
            if e:
                col = col * u**e
        cols.append(col)
    return np.column_stack(cols)


def forward_lines(slip, kS, phiS, phiD, da_g, min_points: int = 3):
    """Per soil ``Da = alpha + beta * i`` by least squares.

    Returns ``(soils, alpha [g], beta [g], r2, n)`` (arrays over soils;
    NaN for soils with fewer than ``min_points`` rows or a single slip).
    """
    slip, kS, phiS, phiD, da_g = _sweep_arrays(slip, kS, phiS, phiD, da_g)
    index, soils = soil_index(kS, phiS, phiD)
    s_count = soils.shape[0]
    alpha, beta, r2 = (np.full(s_count, np.nan) for _ in range(3))
    counts = np.bincount(index, minlength=s_count)
    for s in range(s_count):
        m = index == s
        if counts[s] >= min_points and np.ptp(slip[m]) > 0.0:
            alpha[s], beta[s], r2[s] = linear_fit(slip[m], da_g[m])
    return soils, alpha, beta, r2, counts


def fit_forward_surfaces(
    slip, kS, phiS, phiD, da_g, degree: int = 1, use_phiS: bool = False, name: str | None = None, _norm=None
) -> tuple[ForwardModel, dict]:
    """Two-stage forward fit: per-soil lines ``Da = alpha + beta i``, then ``alpha`` and
    ``beta`` as polynomial surfaces of total ``degree`` in (dphi, kS[, phiS]).

    ``degree = 1`` gives the planes of docs/model.md section 5. Returns the model and a dict
    with ``r2_alpha``, ``r2_beta`` (surface fits over soils), the per-soil
    line R^2 figures and ``identifiable`` (False when the sweep's levels
    cannot determine every coefficient: rank-deficient design, e.g. a cubic
    in a variable swept at 3 levels); for planes also ``alpha_plane`` and
    ``beta_plane``, coefficients ``{const, dphi, kS[, phiS]}`` in SI (``Da``
    in g, ``dphi``/``phiS`` in rad, ``kS`` in N/m).
    """
    slip, kS, phiS, phiD, da_g = _sweep_arrays(slip, kS, phiS, phiD, da_g)
    center, scale = _norm if _norm is not None else _normalisation(slip, kS, phiS, phiD)
    soils, alpha, beta, r2, _ = forward_lines(slip, kS, phiS, phiD, da_g)
    ok = np.isfinite(alpha)
    s_raw = (soils[ok, 1] - soils[ok, 2], soils[ok, 0], soils[ok, 1])
    u = [(s_raw[k] - center[k + 1]) / scale[k + 1] for k in range(3)]
    sterms = soil_terms(degree, use_phiS)
    a = _design(u, sterms)
    ca = np.linalg.lstsq(a, alpha[ok], rcond=None)[0]
    cb = np.linalg.lstsq(a, beta[ok], rcond=None)[0]
    terms = tuple((0,) + t for t in sterms) + tuple((1,) + t for t in sterms)
    vars_ = "dphi, kS, phiS" if use_phiS else "dphi, kS"
    label = name or (f"alpha, beta planes in ({vars_})" if degree == 1 else f"alpha, beta degree-{degree} in ({vars_})")
    model = ForwardModel(label, terms, np.concatenate([ca, cb]), center, scale)
    r2v = r2[ok]
    info = {
        "r2_alpha": r2_score(alpha[ok], a @ ca),
        "r2_beta": r2_score(beta[ok], a @ cb),
        "lines_r2_mean": float(np.mean(r2v)),
        "lines_r2_median": float(np.median(r2v)),
        "lines_r2_min": float(np.min(r2v)),
        "identifiable": bool(np.linalg.matrix_rank(a) == a.shape[1]),
    }
    if degree == 1:
        names = ["dphi", "kS", "phiS"]
        first = [t.index(1) for t in sterms[1:]]  # variable of each first-degree term
        for key, c in (("alpha_plane", ca), ("beta_plane", cb)):
            # undo the normalisation: c0 + sum_j c_j (x_k - center_k) / scale_k
            phys = {"const": float(c[0] - sum(c[j + 1] * center[k + 1] / scale[k + 1] for j, k in enumerate(first)))}
            for j, k in enumerate(first):
                phys[names[k]] = float(c[j + 1] / scale[k + 1])
            info[key] = phys
    return model, info


def fit_forward_polynomial(
    slip, kS, phiS, phiD, da_g, degree: int = 2, name: str | None = None, _norm=None
) -> tuple[ForwardModel, dict]:
    """``Da`` fitted directly by least squares as a polynomial of total ``degree`` in (slip, dphi, kS, phiS).

    Returns the model and ``{"identifiable": bool}`` (see :func:`fit_forward_surfaces`).
    """
    slip, kS, phiS, phiD, da_g = _sweep_arrays(slip, kS, phiS, phiD, da_g)
    center, scale = _norm if _norm is not None else _normalisation(slip, kS, phiS, phiD)
    terms = sorted(
        (e for e in itertools.product(range(degree + 1), repeat=4) if sum(e) <= degree),
        key=lambda e: (sum(e), tuple(-v for v in e)),
    )
    raw = (slip, phiS - phiD, kS, phiS)
    u = [(raw[k] - center[k]) / scale[k] for k in range(4)]
    a = _design(u, terms)
    coef = np.linalg.lstsq(a, da_g, rcond=None)[0]
    model = ForwardModel(name or f"polynomial degree {degree} in (slip, dphi, kS, phiS)", tuple(terms), coef, center, scale)
    return model, {"identifiable": bool(np.linalg.matrix_rank(a) == a.shape[1])}


@dataclass
class ForwardCandidate:
    """One forward model with its figures of merit.

    r2_da, rmse_da [g]: ``Da`` predicted over the sweep (in-sample);
    rmse_slip [-]: slip recovered by inverting the model, soil known;
    ``*_cv``: the same, leave-one-soil-out (each soil predicted by a model
    fitted without it); ``*_val``: the same on an independent validation
    table (NaN when none was given). ``identifiable``: the sweep determines
    every coefficient. ``monotone_fraction``: share of the soils of a dense
    check grid over the sweep's soil ranges on which the modelled ``Da`` is
    strictly increasing in slip over ``slip_clip`` (1.0: the inverse is
    unique everywhere in the calibrated box; see :func:`monotone_fraction`).
    ``info``: fit-specific figures (surface R^2...).
    """

    model: ForwardModel
    n_coef: int
    identifiable: bool
    monotone_fraction: float
    r2_da: float
    rmse_da: float
    r2_da_cv: float
    rmse_da_cv: float
    rmse_slip: float
    rmse_slip_cv: float
    r2_da_val: float = math.nan
    rmse_da_val: float = math.nan
    rmse_slip_val: float = math.nan
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """JSON-ready figures (no coefficients except the SI planes)."""
        out = {"name": self.model.name, "kind": self.model.kind, "n_coef": int(self.n_coef)}
        out["identifiable"] = bool(self.identifiable)
        out["monotone_fraction"] = json_number(self.monotone_fraction)
        for key in (
            "r2_da",
            "rmse_da",
            "r2_da_cv",
            "rmse_da_cv",
            "rmse_slip",
            "rmse_slip_cv",
            "r2_da_val",
            "rmse_da_val",
            "rmse_slip_val",
        ):
            out[key] = json_number(getattr(self, key))
        for key, value in self.info.items():
            if key == "identifiable":
                continue
            out[key] = {k: json_number(v) for k, v in value.items()} if isinstance(value, dict) else json_number(value)
        return out


#: Candidate forward models compared by :func:`compare_forward`: (kind, options), simplest first.
DEFAULT_CANDIDATES = (
    ("surfaces", dict(degree=1, use_phiS=False)),
    ("surfaces", dict(degree=1, use_phiS=True)),
    ("polynomial", dict(degree=2)),
    ("surfaces", dict(degree=2, use_phiS=True)),
    ("polynomial", dict(degree=3)),
    ("surfaces", dict(degree=3, use_phiS=True)),
)


def monotone_fraction(model: ForwardModel, kS_range, phiD_range, dphi_range, n_soil: int = 16, n_slip: int = 111) -> float:
    """Share of soils on which ``Da`` is strictly increasing in slip over ``model.slip_clip``.

    Soils: an ``n_soil``^3 grid over ``kS_range`` [N/m], ``phiD_range`` and
    ``dphi_range`` [rad] (``phiS = phiD + dphi``); slips: ``n_slip`` points.
    1.0 means :func:`invert_slip` has a unique answer for every soil of
    the box (for a model linear in slip: ``beta > 0`` everywhere).
    """
    ks, pd, dp = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(*kS_range, n_soil), np.linspace(*phiD_range, n_soil), np.linspace(*dphi_range, n_soil), indexing="ij"
        )
    )
    slips = np.linspace(model.slip_clip[0], model.slip_clip[1], n_slip)
    da = model.da(slips[None, :], ks[:, None], (pd + dp)[:, None], pd[:, None])
    return float(np.mean(np.all(np.diff(da, axis=1) > 0.0, axis=1)))


def _fit_candidate(kind, opts, arrays, norm, clip):
    if kind == "surfaces":
        model, info = fit_forward_surfaces(*arrays, _norm=norm, **opts)
    elif kind == "polynomial":
        model, info = fit_forward_polynomial(*arrays, _norm=norm, **opts)
    else:
        raise ValueError(f"unknown candidate kind {kind!r}")
    return ForwardModel(model.name, model.terms, model.coef, model.center, model.scale, clip), info


def compare_forward(
    slip, kS, phiS, phiD, da_g, candidates=DEFAULT_CANDIDATES, validation=None, slip_clip=None, progress=None
) -> list[ForwardCandidate]:
    """Fit every candidate forward model and score it: in-sample, leave-one-soil-out, and on
    an optional independent ``validation`` table ``(slip, kS, phiS, phiD, Da_g)`` (e.g.
    random off-grid soils, which a leave-one-soil-out split of a grid cannot test).

    ``slip_clip``: inversion range (default ``[0, 1.1 * max slip]``).
    ``progress``: optional callable ``progress(n)`` called after each
    candidate (e.g. a tqdm bar's ``update``). Returns a list of
    :class:`ForwardCandidate` in the order of ``candidates``.
    """
    arrays = _sweep_arrays(slip, kS, phiS, phiD, da_g)
    slip, kS, phiS, phiD, da_g = arrays
    val = _sweep_arrays(*validation) if validation is not None else None
    norm = _normalisation(slip, kS, phiS, phiD)
    clip = tuple(slip_clip) if slip_clip is not None else (0.0, 1.1 * float(slip.max()))
    index, soils = soil_index(kS, phiS, phiD)
    dphi = phiS - phiD
    box = ((kS.min(), kS.max()), (phiD.min(), phiD.max()), (dphi.min(), dphi.max()))
    out = []
    for kind, opts in candidates:
        model, info = _fit_candidate(kind, opts, arrays, norm, clip)
        pred = model.da(slip, kS, phiS, phiD)
        inv = model.invert(da_g, kS, phiS, phiD)
        pred_cv = np.empty_like(da_g)
        inv_cv = np.empty_like(da_g)
        for s in range(soils.shape[0]):
            m = index == s
            m_cv, _ = _fit_candidate(kind, opts, [a[~m] for a in arrays], norm, clip)
            pred_cv[m] = m_cv.da(slip[m], kS[m], phiS[m], phiD[m])
            inv_cv[m] = m_cv.invert(da_g[m], kS[m], phiS[m], phiD[m])
        cand = ForwardCandidate(
            model=model,
            n_coef=len(model.terms),
            identifiable=bool(info.get("identifiable", True)),
            monotone_fraction=monotone_fraction(model, *box),
            r2_da=r2_score(da_g, pred),
            rmse_da=rmse(da_g, pred),
            r2_da_cv=r2_score(da_g, pred_cv),
            rmse_da_cv=rmse(da_g, pred_cv),
            rmse_slip=rmse(slip, inv),
            rmse_slip_cv=rmse(slip, inv_cv),
            info=info,
        )
        if val is not None:
            v_slip, v_ks, v_phis, v_phid, v_da = val
            v_pred = model.da(v_slip, v_ks, v_phis, v_phid)
            cand.r2_da_val = r2_score(v_da, v_pred)
            cand.rmse_da_val = rmse(v_da, v_pred)
            cand.rmse_slip_val = rmse(v_slip, model.invert(v_da, v_ks, v_phis, v_phid))
        out.append(cand)
        if progress is not None:
            progress(1)
    return out


SELECTION_RULE = (
    "admissible candidates: the sweep determines every coefficient (full-rank design) and Da is strictly "
    "increasing in slip for every soil of the calibrated box (unique inverse); among them, the one with the "
    "fewest coefficients whose slip RMSE after inversion (soil known) is within {tol:.0%} of the best "
    "admissible one's, RMSE measured on {metric}"
)


def _selection_metric(candidates) -> str:
    return "val" if all(math.isfinite(c.rmse_slip_val) for c in candidates) else "cv"


def selection_rule(candidates, tolerance: float = 0.05) -> str:
    """The text of the rule :func:`select_forward` applies to these candidates."""
    metric = _selection_metric(candidates)
    what = "the independent validation table" if metric == "val" else "a leave-one-soil-out split"
    return SELECTION_RULE.format(tol=tolerance, metric=what)


def select_forward(candidates, tolerance: float = 0.05) -> ForwardCandidate:
    """Pick the forward model to ship: see :data:`SELECTION_RULE` (``tolerance`` relative).

    Uses the validation slip RMSE when every candidate has one, else the
    leave-one-soil-out slip RMSE. Raises ``ValueError`` if no candidate is
    admissible.
    """
    key = "rmse_slip_val" if _selection_metric(candidates) == "val" else "rmse_slip_cv"
    usable = [
        c for c in candidates if c.identifiable and c.monotone_fraction >= 1.0 and math.isfinite(getattr(c, key))
    ]
    if not usable:
        raise ValueError("no admissible forward candidate (identifiable, monotone in slip, finite slip RMSE)")
    best = min(getattr(c, key) for c in usable)
    good = [c for c in usable if getattr(c, key) <= (1.0 + tolerance) * best]
    return min(good, key=lambda c: (c.n_coef, getattr(c, key)))


def _forward_model(cal) -> ForwardModel:
    if isinstance(cal, ForwardModel):
        return cal
    if isinstance(cal, ForwardCandidate):
        return cal.model
    if isinstance(cal, dict):
        return ForwardModel.from_dict(cal["forward"] if "forward" in cal else cal)
    raise TypeError(f"expected a calibration dict or a ForwardModel, not {type(cal).__name__}")


def forward_da(cal, slip, kS, phiS, phiD) -> np.ndarray:
    """``Da`` [g] the calibration's forward model predicts at slip [-] on soil (kS [N/m], phiS, phiD [rad]).

    ``cal``: a calibration dict (e.g. :func:`load_calibration`), its
    ``forward`` section, or a :class:`ForwardModel`. Broadcasts.
    """
    return _forward_model(cal).da(slip, kS, phiS, phiD)


def invert_slip(cal, da_g, kS, phiS, phiD, clip: bool = True) -> np.ndarray:
    """Slip [-] from ``Da`` [g] with the soil known (kS [N/m], phiS, phiD [rad]), by inverting
    the forward model; clipped to the calibration's ``slip_clip`` (about [0, 0.55]). Broadcasts.
    """
    return _forward_model(cal).invert(da_g, kS, phiS, phiD, clip=clip)


def soil_in_range(cal: dict, kS, phiS, phiD, rel_margin: float = 1e-9) -> np.ndarray:
    """True where the soil (kS [N/m], phiS, phiD [rad]) lies inside the calibration sweep's box.

    The box is the ranges of ``grid.kS``, ``grid.phiD`` and ``grid.dphi`` of
    the calibration dict; outside it :func:`invert_slip` extrapolates.
    Broadcasts.
    """
    g = cal["grid"]
    kS, phiS, phiD = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (kS, phiS, phiD)))
    out = np.ones(kS.shape, dtype=bool)
    for x, levels in ((kS, g["kS"]), (phiD, g["phiD"]), (phiS - phiD, g["dphi"])):
        lo, hi = float(min(levels)), float(max(levels))
        tol = rel_margin * max(abs(lo), abs(hi), 1.0)
        out &= (x >= lo - tol) & (x <= hi + tol)
    return out



# --------------------------------------------------------------------------- calibration file


def build_calibration(
    eq515: Eq515Fit,
    candidates,
    chosen: ForwardCandidate,
    model: dict,
    grid: dict,
    created_by: str,
    tolerance: float = 0.05,
) -> dict:
    """Assemble a calibration dict (schema: :data:`SCHEMA_DOC`)."""
    from slipest import __version__

    forward = chosen.model.to_dict()
    forward.update(
        {
            "r2_da": json_number(chosen.r2_da),
            "rmse_da": json_number(chosen.rmse_da),
            "r2_da_cv": json_number(chosen.r2_da_cv),
            "rmse_da_cv": json_number(chosen.rmse_da_cv),
            "rmse_slip": json_number(chosen.rmse_slip),
            "rmse_slip_cv": json_number(chosen.rmse_slip_cv),
            "r2_da_val": json_number(chosen.r2_da_val),
            "rmse_da_val": json_number(chosen.rmse_da_val),
            "rmse_slip_val": json_number(chosen.rmse_slip_val),
            "selection_rule": selection_rule(candidates, tolerance),
            "candidates": [c.summary() for c in candidates],
        }
    )
    lines = next((c.info for c in candidates if "lines_r2_mean" in c.info), None)
    if lines:
        forward["per_soil_lines"] = {
            "r2_mean": json_number(lines["lines_r2_mean"]),
            "r2_median": json_number(lines["lines_r2_median"]),
            "r2_min": json_number(lines["lines_r2_min"]),
        }
    cal = {
        "format_version": FORMAT_VERSION,
        "created_by": created_by,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "slipest_version": __version__,
        "units": {"slip": "-", "kS": "N/m", "phiS": "rad", "phiD": "rad", "dphi": "rad", "Da": "g", "dt": "s"},
        "model": copy.deepcopy(model),
        "grid": copy.deepcopy(grid),
        "eq515": eq515.to_dict(),
        "forward": forward,
    }
    validate_calibration(cal)
    check_forward_section(cal)
    return cal


def check_forward_section(cal: dict) -> dict:
    """Raise :class:`~slipest.calibration.CalibrationError` unless the file's forward model is consistent
    (variables, one coefficient and four exponents per term)."""
    ForwardModel.from_dict(cal["forward"])
    return cal


