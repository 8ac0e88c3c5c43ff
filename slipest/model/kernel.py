"""The compiled integrator of the wheel-leg stick-slip model (one propulsive half-stance).

This module holds the one time loop of the project's physics, written once
and compiled with numba; :mod:`slipest.model.stance` wraps it in the public
single-cycle and batch APIs. The model is slipest's reading of thesis
Eqs. 5.10-5.14 (``docs/model.md`` section 3), made well-posed by a leg that
resists being pushed off its commanded line:

Coordinates x forward, z up; foot at ``(xC, 0)``, hub at ``(xH, zH)``;
``ea = (sin th, cos th)`` (foot to hub, along the leg), ``ep = (cos th, -sin th)``::

    L  = sqrt(zH^2 + (xH - xC)^2)        FS = kS (lS - L)  [+ damping]      (5.13)
    p  = (xH - xC) cos th - zH sin th     hub offset from the leg line [m]
    FH = FS ea - kappa kS p ep            force of the leg on the hub [N]
    FN = FH_z,  FE = -FH_x                normal / tangential force on the foot
    stick while |FE| <= muS FN; slip: mF aC = FE - mu(vC) FN sgn(vC)       (5.11, 5.12)
    back to stick when vC changes sign within a step
    MH zH'' = FH_z - MH g                                                  (5.14, z up)
    contact lost (FH_z <= 0): hub in free fall, foot re-planted on the leg line
        (kappa > 0 only; with kappa = 0, the literal thesis model, a lost
        contact, or a foot still sliding at the end after breaking away, is
        the model's ill-posedness and is returned as a failure status)
    vXH = (1 - i) lS omega cos(th)        imposed hub horizontal speed [m/s]

Integration is fixed-step semi-implicit Euler (velocity first, then position).
The loop's pieces (leg force, friction law, sliding step, recording, results)
are ``inline="always"`` helpers, compiled into the one loop.

Besides the nominal model the kernel carries the physical extensions that the
sim-to-real diagnosis can switch on (all off at their neutral values):

* Hunt-Crossley damping of the leg/soil spring (thesis Eq. 5.10 before its
  simplification): ``FS = kS d + bHC d^nHC d'`` with ``d = lS - L`` [m],
  clamped at zero while in compression (no adhesion);
* Stribeck friction: ``mu(v) = muD + (muS - muD) exp(-(|v|/vs)^delta)`` plus a
  viscous force ``sigma_v v`` [N s/m] (``vs = 0`` means constant ``muD``);
* drive speed ripple: ``omega(th) = omega0 (1 + A sin(h nL th + phase))``, ``h`` its harmonic of
  the leg-cycle frequency (an integer >= 1, so that the ripple repeats every cycle).

Parameters come as one row per batch element of a float64 matrix whose
columns are named by the ``P_*`` indices below (kept in one place so that
:mod:`slipest.model.stance` builds the matrix from the dataclass).
"""

from __future__ import annotations

import math

import numba
import numpy as np

# --- parameter matrix columns (SI units) -------------------------------------
P_SLIP = 0  # slip i [-]
P_KS = 1  # spring stiffness kS [N/m]
P_MUS = 2  # static friction coefficient muS = tan(phiS) [-]
P_MUD = 3  # dynamic friction coefficient muD = tan(phiD) [-]
P_KAPPA = 4  # leg lateral stiffness ratio kappa [-]
P_MH = 5  # hub mass MH [kg]
P_MF = 6  # foot mass mF [kg]
P_LS = 7  # spring rest length lS [m]
P_OMEGA = 8  # nominal leg angular speed omega [rad/s]
P_NL = 9  # number of legs nL [-]
P_G = 10  # gravity [m/s^2]
P_BHC = 11  # Hunt-Crossley damping bHC [N s / m^(1 + nHC)]
P_NHC = 12  # Hunt-Crossley exponent nHC [-]
P_VS = 13  # Stribeck velocity vs [m/s] (0: off)
P_SEXP = 14  # Stribeck exponent delta [-]
P_VISC = 15  # viscous friction sigma_v [N s/m]
P_RIPPLE_A = 16  # relative amplitude of the drive speed ripple [-]
P_RIPPLE_PH = 17  # phase of the drive speed ripple [rad]
P_RIPPLE_H = 18  # harmonic of the drive speed ripple: ripples per leg cycle [-] (integer >= 1)
N_PARAMS = 19

# --- recorded channels of a waveform ----------------------------------------
CH_THETA = 0  # leg angle [rad]
CH_AZ = 1  # hub vertical acceleration zH'' (z up, gravity-free) [m/s^2]
CH_STICK = 2  # 1 while the foot sticks, 0 while it slides
CH_CONTACT = 3  # 1 while the foot is loaded, 0 in free fall
CH_FN = 4  # normal force on the soil [N]
CH_FE = 5  # tangential force on the foot [N]
CH_FS = 6  # spring force, positive in compression [N]
CH_ZH = 7  # hub height [m]
CH_XH = 8  # hub horizontal position [m]
CH_XC = 9  # foot horizontal position [m]
CH_VC = 10  # foot horizontal speed [m/s]
N_CHANNELS = 11

# --- per-element results ----------------------------------------------------
R_AZ_MAX = 0  # max of zH'' over the stance [m/s^2]
R_AZ_MIN = 1  # min of zH'' over the stance [m/s^2]
R_BREAKAWAY = 2  # leg angle of the first break-away [rad] (NaN: never)
R_N_BREAKAWAY = 3  # number of stick-to-slip transitions
R_N_CONTACT_LOSS = 4  # number of contact losses
R_STATUS = 5  # STATUS_* code
R_STATUS_THETA = 6  # leg angle at which a failure was detected [rad]
R_N_STEPS = 7  # integration steps taken
N_RESULTS = 8

STATUS_OK = 0
STATUS_BELOW_GROUND = 1  # hub height went negative: the hub fell through the soil
STATUS_RUNAWAY = 2  # |zH''| exceeded the runaway limit: the integration blew up
STATUS_MAX_STEPS = 3  # the stance did not finish within the step budget
STATUS_ILL_POSED = 4  # literal model (kappa = 0): the foot slid out of the friction cone (ladder problem)

#: |zH''| above this is a blown-up integration, not physics [m/s^2] (50 g).
RUNAWAY_LIMIT = 50.0 * 9.81


_INLINE = dict(cache=True, inline="always", error_model="numpy")


@numba.njit(**_INLINE)
def _omega_at(omega0, ripple_a, ripple_ph, ripple_k, th):
    return omega0 * (1.0 + ripple_a * math.sin(ripple_k * th + ripple_ph))


@numba.njit(**_INLINE)
def _sign(x):
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@numba.njit(**_INLINE)
def _leg_force(xh, zh, xc, vxh, vc, vz, s, c, ls, ks, kappa, bhc, nhc):
    """Spring force ``FS`` [N] (Eq. 5.13 + Hunt-Crossley damping, clamped >= 0) and the leg's force on the
    hub ``(FH_x, FH_z)`` [N] (spring along the leg, lateral stiffness ``kappa kS`` across it)."""
    dx = xh - xc
    length = math.sqrt(zh * zh + dx * dx)
    comp = ls - length
    fs = ks * comp
    if bhc > 0.0 and comp > 0.0:
        comp_rate = -(dx * (vxh - vc) + zh * vz) / length
        fs += bhc * comp**nhc * comp_rate
        if fs < 0.0:
            fs = 0.0
    off = dx * c - zh * s
    fhx = fs * s - kappa * ks * off * c
    fhz = fs * c + kappa * ks * off * s
    return fs, fhx, fhz


@numba.njit(**_INLINE)
def _friction_coefficient(vc, mus, mud, vs, sexp):
    """Sliding friction coefficient: Stribeck ``muD + (muS - muD) exp(-(|v|/vs)^delta)``, or ``muD`` if ``vs = 0``."""
    if vs > 0.0:
        return mud + (mus - mud) * math.exp(-((abs(vc) / vs) ** sexp))
    return mud


@numba.njit(**_INLINE)
def _slide(vc, xc, fe, fn, mu, visc, inv_mf, dt):
    """One step of the sliding foot (Eq. 5.12 + viscous term): ``(stuck, vC, xC)``; it sticks when vC changes sign."""
    sgn = _sign(vc) if vc != 0.0 else _sign(fe)
    ac = (fe - mu * fn * sgn - visc * vc) * inv_mf
    vc_new = vc + ac * dt
    if vc != 0.0 and vc_new * vc < 0.0:
        return True, 0.0, xc
    return False, vc_new, xc + vc_new * dt


@numba.njit(**_INLINE)
def _record(rec, n, th, az, stick, contact, fn, fe, fs, zh, xh, xc, vc):
    """Row ``n`` of the waveform buffer (as many ``CH_*`` channels as it has)."""
    n_ch = rec.shape[1]
    if n < rec.shape[0] and n_ch > 0:
        r = rec[n]
        r[CH_THETA] = th
        r[CH_AZ] = az
        if n_ch > CH_STICK:
            r[CH_STICK] = 1.0 if stick else 0.0
            r[CH_CONTACT] = 1.0 if contact else 0.0
        if n_ch > CH_FN:
            state = (fn, fe, fs, zh, xh, xc, vc)  # channels CH_FN .. CH_VC, in this order
            for j in range(len(state)):
                r[CH_FN + j] = state[j]


@numba.njit(**_INLINE)
def _write_results(res, az_max, az_min, breakaway, n_break, n_loss, status, status_th, n):
    """The per-element results row (see ``R_*``)."""
    row = (az_max, az_min, breakaway, float(n_break), float(n_loss), float(status), status_th, float(n))  # R_* order
    for j in range(N_RESULTS):
        res[j] = row[j]


@numba.njit(cache=True, error_model="numpy")
def integrate_stance(p, dt, max_steps, res, rec):
    """Integrate one propulsive half-stance, midstance (th = 0) to th = pi/nL.

    ``p``: one parameter row (see ``P_*``). ``dt``: step [s]. ``res``: output
    row (see ``R_*``), written in place. ``rec``: waveform buffer of shape
    ``(n, channels)``; the first ``min(n, steps)`` steps are recorded when
    ``channels > 0`` (see ``CH_*``). The state is recorded at the start of
    each step, so row 0 is the static equilibrium at midstance.
    """
    slip = p[P_SLIP]
    ks = p[P_KS]
    mus = p[P_MUS]
    mud = p[P_MUD]
    kappa = p[P_KAPPA]
    mh = p[P_MH]
    ls = p[P_LS]
    omega0 = p[P_OMEGA]
    n_legs = p[P_NL]
    g = p[P_G]
    ripple_a = p[P_RIPPLE_A]
    ripple_ph = p[P_RIPPLE_PH]
    ripple_k = n_legs * p[P_RIPPLE_H]  # ripples per radian of leg angle
    th_end = math.pi / n_legs

    # static equilibrium at midstance: the spring carries the hub's weight
    th = 0.0
    xh = 0.0
    xc = 0.0
    vc = 0.0
    zh = ls - mh * g / ks
    vz = 0.0
    vxh = 0.0
    stick = True
    contact = True

    az_max = -1e300
    az_min = 1e300
    breakaway = math.nan
    n_break = 0
    n_loss = 0
    status = STATUS_OK
    status_th = math.nan
    n = 0
    inv_mh = 1.0 / mh
    inv_mf = 1.0 / p[P_MF]
    # With a constant leg speed the angle grows by a fixed step: rotate
    # (sin, cos) by it instead of calling sin and cos every step (the
    # recurrence drifts by ~1e-12 over a stance; Da agrees to 1e-11).
    constant_speed = ripple_a == 0.0
    s = 0.0
    c = 1.0
    s_step = math.sin(omega0 * dt)
    c_step = math.cos(omega0 * dt)
    while th < th_end:
        if n >= max_steps:
            status = STATUS_MAX_STEPS
            status_th = th
            break
        if constant_speed:
            omega = omega0
        else:
            omega = _omega_at(omega0, ripple_a, ripple_ph, ripple_k, th)
            s = math.sin(th)
            c = math.cos(th)
        vxh = (1.0 - slip) * ls * omega * c

        # contact loss: re-plant the unloaded foot on the leg line, in stick
        if not contact:
            xc = xh - zh * s / c
            vc = 0.0
            stick = True

        fs, fhx, fhz = _leg_force(xh, zh, xc, vxh, vc, vz, s, c, ls, ks, kappa, p[P_BHC], p[P_NHC])
        fn = fhz
        fe = -fhx

        if contact and fn <= 0.0:
            n_loss += 1
            if kappa == 0.0:
                # The thesis model as written has no rule for a lost contact:
                # the leg force lies along the leg, FE/FN = tan(th) has left the
                # friction cone, and the foot can never be held again (ladder
                # problem). Re-planting belongs to the well-posed reading only.
                status = STATUS_ILL_POSED
                status_th = th
                break
            contact = False
        elif not contact and fn > 0.0:
            contact = True

        if contact:
            if stick and abs(fe) > mus * fn:
                stick = False
                n_break += 1
                if n_break == 1:
                    breakaway = th
            if not stick:
                mu = _friction_coefficient(vc, mus, mud, p[P_VS], p[P_SEXP])
                stick, vc, xc = _slide(vc, xc, fe, fn, mu, p[P_VISC], inv_mf, dt)
            az = fhz * inv_mh - g
        else:
            az = -g

        _record(rec, n, th, az, stick, contact, fn, fe, fs, zh, xh, xc, vc)

        if az > az_max:
            az_max = az
        if az < az_min:
            az_min = az
        if abs(az) > RUNAWAY_LIMIT:
            status = STATUS_RUNAWAY
            status_th = th
            n += 1
            break

        vz += az * dt
        zh += vz * dt
        xh += vxh * dt
        th += omega * dt
        if constant_speed:
            s, c = s * c_step + c * s_step, c * c_step - s * s_step
        n += 1
        if zh < 0.0:
            status = STATUS_BELOW_GROUND
            status_th = th
            break

    if kappa == 0.0 and status == STATUS_OK and n_break > 0 and not stick:
        # literal model: broke away at th = phiS and was never held again
        status = STATUS_ILL_POSED
        status_th = th
    _write_results(res, az_max, az_min, breakaway, n_break, n_loss, status, status_th, n)


@numba.njit(cache=True, parallel=True, error_model="numpy")
def integrate_batch(params, dt, max_steps, res, rec):
    """Integrate every row of ``params`` (shape ``(B, N_PARAMS)``) in parallel.

    ``res``: ``(B, N_RESULTS)`` output. ``rec``: ``(B, n, channels)`` waveform
    buffer (``n = 0`` or ``channels = 0`` records nothing).
    """
    for b in numba.prange(params.shape[0]):
        integrate_stance(params[b], dt, max_steps, res[b], rec[b])


def empty_results(batch: int) -> np.ndarray:
    """A result matrix for ``batch`` elements, NaN-filled."""
    return np.full((batch, N_RESULTS), np.nan)
