"""Simulate the propulsive half-stance: one cycle with every signal, or many at once.

``simulate_stance(params)`` integrates one stance (midstance to ``pi/nL``)
and returns time, leg angle, hub vertical acceleration, stick/contact flags
and forces. ``simulate_batch(list_of_params)`` integrates many parameter
sets in one compiled, parallel loop and returns ``Da``, the first break-away
angle and, on request, the waveforms. Both run the same kernel
(:mod:`slipest.model.kernel`), so they agree to the last bit.

A stance that fails (hub below the ground, runaway acceleration, the literal
``kappa = 0`` model losing support) raises :class:`ModelFailure` naming the
cause; ``simulate_batch(..., on_error="flag")`` instead marks those elements
(``status != 0``, ``delta_a = NaN``) for sweeps that must go on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slipest.model import kernel as K
from slipest.model.params import StickSlipParams, param_matrix

#: Default integration step [s]; halving it changes Da by < 0.1% on the reference cases (docs/model.md, section 3).
DEFAULT_DT = 1e-4

_STATUS_TEXT = {
    K.STATUS_BELOW_GROUND: "the hub fell below the ground (zH < 0): the soil is too soft for the hub's weight "
    "or the model diverged",
    K.STATUS_RUNAWAY: f"runaway acceleration (|zH''| > {K.RUNAWAY_LIMIT / 9.81:.0f} g): the integration blew up",
    K.STATUS_MAX_STEPS: "the stance did not reach pi/nL within the step budget",
    K.STATUS_ILL_POSED: "the literal thesis model (kappa = 0) is ill-posed here: the leg force lies along the "
    "leg, FE/FN = tan(theta) leaves the friction cone past theta = phiS, friction can never hold the foot again "
    "and it slides out until the hub loses support (ladder problem); use kappa > 0 (default 0.3)",
}


class ModelFailure(RuntimeError):
    """The stick-slip model failed for a parameter set; the message names the cause."""

    def __init__(self, status: int, theta: float, params: StickSlipParams | None = None, index: int | None = None):
        self.status = int(status)
        self.theta = float(theta)
        self.params = params
        self.index = index
        where = f"parameter set #{index}: " if index is not None else ""
        what = _STATUS_TEXT.get(self.status, f"unknown status {self.status}")
        soil = ""
        if params is not None:
            soil = (
                f" (slip={params.slip:g}, kS={params.kS:g} N/m, phiS={params.phiS:g} rad, "
                f"phiD={params.phiD:g} rad, kappa={params.kappa:g})"
            )
        super().__init__(f"{where}stick-slip model failed at theta = {theta:.3f} rad: {what}{soil}")


def status_text(status: int) -> str:
    """Human-readable meaning of a kernel status code (``""`` for OK)."""
    return _STATUS_TEXT.get(int(status), "")


def _max_steps(params: StickSlipParams | np.ndarray, dt: float) -> int:
    """Step budget of a stance: its duration at the slowest drive speed, plus margin."""
    if isinstance(params, StickSlipParams):
        angle, omega, ripple = params.stance_angle, params.omega, params.ripple_amp
    else:
        angle = float(np.max(np.pi / params[:, K.P_NL]))
        omega = float(np.min(params[:, K.P_OMEGA]))
        ripple = float(np.max(params[:, K.P_RIPPLE_A]))
    return int(math.ceil(angle / (omega * (1.0 - ripple) * dt))) + 2


@dataclass(frozen=True)
class StanceResult:
    """One simulated stance. Arrays are per integration step, state at the step's start.

    t [s] from midstance; theta [rad]; az: hub vertical acceleration zH''
    (z up, gravity-free) [m/s^2]; stick, contact: bool flags; FN, FE, FS [N];
    zH, xH, xC [m]; vC [m/s]. ``delta_a`` [m/s^2] is ``max(az) - min(az)``;
    ``breakaway_theta`` [rad] the first stick-to-slip transition (NaN: none).
    """

    params: StickSlipParams
    dt: float
    t: np.ndarray
    theta: np.ndarray
    az: np.ndarray
    stick: np.ndarray
    contact: np.ndarray
    FN: np.ndarray
    FE: np.ndarray
    FS: np.ndarray
    zH: np.ndarray
    xH: np.ndarray
    xC: np.ndarray
    vC: np.ndarray
    delta_a: float
    breakaway_theta: float
    n_breakaways: int
    n_contact_losses: int

    @property
    def delta_a_g(self) -> float:
        """``Da`` in g."""
        return self.delta_a / self.params.g


def simulate_stance(params: StickSlipParams | None = None, dt: float = DEFAULT_DT) -> StanceResult:
    """Simulate one propulsive half-stance with every signal recorded.

    Raises :class:`ModelFailure` if the model fails (see module docstring).
    """
    params = params or StickSlipParams()
    if not dt > 0:
        raise ValueError(f"dt={dt} must be > 0")
    row = params.to_row()
    max_steps = _max_steps(params, dt)
    res = K.empty_results(1)[0]
    rec = np.zeros((max_steps, K.N_CHANNELS))
    K.integrate_stance(row, dt, max_steps, res, rec)
    if res[K.R_STATUS] != K.STATUS_OK:
        raise ModelFailure(res[K.R_STATUS], res[K.R_STATUS_THETA], params)
    n = int(res[K.R_N_STEPS])
    w = rec[:n]
    return StanceResult(
        params=params,
        dt=dt,
        t=np.arange(n) * dt,
        theta=w[:, K.CH_THETA].copy(),
        az=w[:, K.CH_AZ].copy(),
        stick=w[:, K.CH_STICK] > 0.5,
        contact=w[:, K.CH_CONTACT] > 0.5,
        FN=w[:, K.CH_FN].copy(),
        FE=w[:, K.CH_FE].copy(),
        FS=w[:, K.CH_FS].copy(),
        zH=w[:, K.CH_ZH].copy(),
        xH=w[:, K.CH_XH].copy(),
        xC=w[:, K.CH_XC].copy(),
        vC=w[:, K.CH_VC].copy(),
        delta_a=float(res[K.R_AZ_MAX] - res[K.R_AZ_MIN]),
        breakaway_theta=float(res[K.R_BREAKAWAY]),
        n_breakaways=int(res[K.R_N_BREAKAWAY]),
        n_contact_losses=int(res[K.R_N_CONTACT_LOSS]),
    )


@dataclass(frozen=True)
class BatchResult:
    """Many simulated stances (one entry per parameter set).

    delta_a [m/s^2] and delta_a_g [g]: ``Da`` (NaN where the model failed);
    breakaway_theta [rad] (NaN: no break-away); n_contact_losses;
    status: kernel status codes (0 OK); n_steps.
    theta, az: waveforms ``(B, n)`` [rad], [m/s^2] when requested, else None;
    entries past an element's ``n_steps`` are NaN.
    """

    delta_a: np.ndarray
    delta_a_g: np.ndarray
    breakaway_theta: np.ndarray
    n_contact_losses: np.ndarray
    status: np.ndarray
    n_steps: np.ndarray
    theta: np.ndarray | None
    az: np.ndarray | None
    dt: float

    @property
    def ok(self) -> np.ndarray:
        """Boolean mask of the elements that simulated without failure."""
        return self.status == K.STATUS_OK


def simulate_batch(
    params,
    dt: float = DEFAULT_DT,
    waveforms: bool = False,
    on_error: str = "raise",
) -> BatchResult:
    """Simulate many stances at once (compiled loop, parallel over the batch).

    ``params``: a sequence of :class:`StickSlipParams`, or a kernel parameter
    matrix ``(B, N_PARAMS)`` (see :func:`slipest.model.params.param_matrix`).
    ``waveforms``: also return ``theta`` and ``az`` per step.
    ``on_error``: ``"raise"`` raises :class:`ModelFailure` for the first
    failed element; ``"flag"`` returns NaN ``Da`` and the status instead.
    """
    if on_error not in ("raise", "flag"):
        raise ValueError(f"on_error must be 'raise' or 'flag', not {on_error!r}")
    if not dt > 0:
        raise ValueError(f"dt={dt} must be > 0")
    if isinstance(params, np.ndarray):
        if params.ndim != 2 or params.shape[1] != K.N_PARAMS:
            raise ValueError(f"parameter matrix must have shape (B, {K.N_PARAMS}), not {params.shape}")
        param_list = None
        mat = np.ascontiguousarray(params, dtype=np.float64)
    else:
        param_list = list(params)
        mat = param_matrix(param_list)
    batch = mat.shape[0]
    max_steps = _max_steps(mat, dt)
    res = K.empty_results(batch)
    rec = np.full((batch, max_steps, 2), np.nan) if waveforms else np.zeros((batch, 0, 0))
    K.integrate_batch(mat, dt, max_steps, res, rec)
    status = res[:, K.R_STATUS].astype(np.int64)
    bad = np.flatnonzero(status != K.STATUS_OK)
    if bad.size and on_error == "raise":
        j = int(bad[0])
        raise ModelFailure(status[j], res[j, K.R_STATUS_THETA], param_list[j] if param_list else None, index=j)
    delta_a = res[:, K.R_AZ_MAX] - res[:, K.R_AZ_MIN]
    delta_a[bad] = np.nan
    return BatchResult(
        delta_a=delta_a,
        delta_a_g=delta_a / mat[:, K.P_G],
        breakaway_theta=res[:, K.R_BREAKAWAY],
        n_contact_losses=res[:, K.R_N_CONTACT_LOSS].astype(np.int64),
        status=status,
        n_steps=res[:, K.R_N_STEPS].astype(np.int64),
        theta=rec[:, :, K.CH_THETA] if waveforms else None,
        az=rec[:, :, K.CH_AZ] if waveforms else None,
        dt=dt,
    )
