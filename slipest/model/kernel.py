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
One step of the loop is ``_step`` (state tuple in, state tuple out); it and
its pieces (leg force, friction law, sliding step, recording, results) are
``inline="always"`` helpers, compiled into the loops that drive it: one stance
(``integrate_stance``) or, in the batch, two stances side by side in one loop
so that the processor overlaps their dependency chains (``integrate_batch``).
Both perform the same floating-point operations in the same order, so their
results agree to the last bit.

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
_RUNNING = 18  # index of the ``running`` flag in a stance state (see ``_initial_state``)


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
def _record(rec, row):
    """Row ``n`` of the waveform buffer (as many ``CH_*`` channels as it has); ``n < 0``: none."""
    n, th, az, stick, contact, fn, fe, fs, zh, xh, xc, vc = row
    n_ch = rec.shape[1]
    if 0 <= n < rec.shape[0] and n_ch > 0:
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


@numba.njit(**_INLINE)
def _constants(p, dt):
    """The per-stance constants of the step, from a parameter row (see ``_step``)."""
    n_legs = p[P_NL]
    omega0 = p[P_OMEGA]
    return (
        p[P_SLIP], p[P_KS], p[P_MUS], p[P_MUD], p[P_KAPPA], p[P_LS], omega0, p[P_G],
        p[P_RIPPLE_A], p[P_RIPPLE_PH], n_legs * p[P_RIPPLE_H],  # ripple_k: ripples per radian of leg angle
        math.pi / n_legs,  # th_end
        1.0 / p[P_MH], 1.0 / p[P_MF],
        # With a constant leg speed the angle grows by a fixed step: rotate
        # (sin, cos) by it instead of calling sin and cos every step (the
        # recurrence drifts by ~1e-12 over a stance; Da agrees to 1e-11).
        math.sin(omega0 * dt), math.cos(omega0 * dt),
        p[P_BHC], p[P_NHC], p[P_VS], p[P_SEXP], p[P_VISC],
    )


@numba.njit(**_INLINE)
def _initial_state(p, max_steps):
    """The state at midstance: static equilibrium, the spring carries the hub's weight.

    ``(th, xh, xc, vc, zh, vz, s, c, stick, contact, az_max, az_min, breakaway,
    n_break, n_loss, status, status_th, n, running)``.
    """
    zh = p[P_LS] - p[P_MH] * p[P_G] / p[P_KS]
    running = 0.0 < math.pi / p[P_NL]
    status = STATUS_OK
    status_th = math.nan
    if running and max_steps <= 0:
        status = STATUS_MAX_STEPS
        status_th = 0.0
        running = False
    return (0.0, 0.0, 0.0, 0.0, zh, 0.0, 0.0, 1.0, True, True, -1e300, 1e300, math.nan,
            0, 0, status, status_th, 0, running)


@numba.njit(**_INLINE)
def _step(k, state, dt, max_steps):
    """One integration step of a running stance: ``(new state, row)`` (state: see ``_initial_state``).

    ``row``: the ``_record`` arguments of the step (the state at its start,
    after the contact and friction updates), with ``n = -1`` if nothing is to be
    recorded (a step that failed before its acceleration).

    ``k``: the stance's constants (``_constants``). ``running`` turns False
    when the stance reaches ``th_end`` or fails (``status`` tells why).
    """
    (slip, ks, mus, mud, kappa, ls, omega0, g, ripple_a, ripple_ph, ripple_k, th_end, inv_mh, inv_mf,
     s_step, c_step, bhc, nhc, vs, sexp, visc) = k
    (th, xh, xc, vc, zh, vz, s, c, stick, contact, az_max, az_min, breakaway,
     n_break, n_loss, status, status_th, n, running) = state
    constant_speed = ripple_a == 0.0
    if constant_speed:
        omega = omega0
    else:
        omega = _omega_at(omega0, ripple_a, ripple_ph, ripple_k, th)
        s = math.sin(th)
        c = math.cos(th)
    vxh = (1.0 - slip) * ls * omega * c

    if contact:
        fs, fhx, fhz = _leg_force(xh, zh, xc, vxh, vc, vz, s, c, ls, ks, kappa, bhc, nhc)
    else:
        # contact loss: re-plant the unloaded foot on the leg line, in stick
        xc = xh - zh * s / c
        vc = 0.0
        stick = True
        fs, fhx, fhz = _leg_force(xh, zh, xc, vxh, vc, vz, s, c, ls, ks, kappa, bhc, nhc)
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
        contact = False
    elif not contact and fn > 0.0:
        contact = True

    row = (-1, th, 0.0, stick, contact, fn, fe, fs, zh, xh, xc, vc)
    if status == STATUS_OK:
        if contact:
            if stick and abs(fe) > mus * fn:
                stick = False
                n_break += 1
                if n_break == 1:
                    breakaway = th
            if not stick:
                mu = _friction_coefficient(vc, mus, mud, vs, sexp)
                stick, vc, xc = _slide(vc, xc, fe, fn, mu, visc, inv_mf, dt)
            az = fhz * inv_mh - g
        else:
            az = -g

        row = (n, th, az, stick, contact, fn, fe, fs, zh, xh, xc, vc)

        if az > az_max:
            az_max = az
        if az < az_min:
            az_min = az
        if abs(az) > RUNAWAY_LIMIT:
            status = STATUS_RUNAWAY
        else:
            vz += az * dt
            zh += vz * dt
            xh += vxh * dt
            th += omega * dt
            if constant_speed:
                s, c = s * c_step + c * s_step, c * c_step - s * s_step
        n += 1
        if status == STATUS_OK:
            if zh < 0.0:
                status = STATUS_BELOW_GROUND
            elif th < th_end and n >= max_steps:
                status = STATUS_MAX_STEPS
    if status != STATUS_OK:
        status_th = th
        running = False
    else:
        running = th < th_end
    return (th, xh, xc, vc, zh, vz, s, c, stick, contact, az_max, az_min, breakaway,
            n_break, n_loss, status, status_th, n, running), row


@numba.njit(**_INLINE)
def _finish(k, state, res):
    """Write the results row of a stance that stopped running (see ``R_*``)."""
    kappa = k[4]
    (th, xh, xc, vc, zh, vz, s, c, stick, contact, az_max, az_min, breakaway,
     n_break, n_loss, status, status_th, n, running) = state
    if kappa == 0.0 and status == STATUS_OK and n_break > 0 and not stick:
        # literal model: broke away at th = phiS and was never held again
        status = STATUS_ILL_POSED
        status_th = th
    _write_results(res, az_max, az_min, breakaway, n_break, n_loss, status, status_th, n)


@numba.njit(cache=True, error_model="numpy")
def integrate_stance(p, dt, max_steps, res, rec):
    """Integrate one propulsive half-stance, midstance (th = 0) to th = pi/nL.

    ``p``: one parameter row (see ``P_*``). ``dt``: step [s]. ``res``: output
    row (see ``R_*``), written in place. ``rec``: waveform buffer of shape
    ``(n, channels)``; the first ``min(n, steps)`` steps are recorded when
    ``channels > 0`` (see ``CH_*``). The state is recorded at the start of
    each step, so row 0 is the static equilibrium at midstance.
    """
    k = _constants(p, dt)
    st = _initial_state(p, max_steps)
    while st[_RUNNING]:
        st, row = _step(k, st, dt, max_steps)
        _record(rec, row)
    _finish(k, st, res)


@numba.njit(cache=True, parallel=True, error_model="numpy")
def integrate_batch(params, dt, max_steps, res, rec):
    """Integrate every row of ``params`` (shape ``(B, N_PARAMS)``) in parallel.

    ``res``: ``(B, N_RESULTS)`` output. ``rec``: ``(B, n, channels)`` waveform
    buffer (``n = 0`` or ``channels = 0`` records nothing).

    Two stances advance side by side in one loop (``_step`` each), so that the
    processor overlaps their dependency chains; each stance's arithmetic is
    exactly that of ``integrate_stance`` (same results to the last bit).
    Partners are neighbours in the order of nominal stance duration
    ``pi / (nL omega)`` (little left to run alone), and the pairs are dealt to
    the threads longest and shortest alternately (equal shares of the work).
    """
    n_b = params.shape[0]
    order = np.argsort(params[:, P_NL] * params[:, P_OMEGA])  # longest stance first
    n_pairs = (n_b + 1) // 2
    for p in numba.prange(n_pairs):
        q = p // 2 if p % 2 == 0 else n_pairs - 1 - p // 2  # 0, last, 1, last - 1, ...
        a = order[2 * q]
        b = order[min(2 * q + 1, n_b - 1)]
        ka = _constants(params[a], dt)
        kb = _constants(params[b], dt)
        sa = _initial_state(params[a], max_steps)
        sb = _initial_state(params[b], max_steps)
        rec_a = rec[a]
        rec_b = rec[b]
        if b != a:
            while sa[_RUNNING] and sb[_RUNNING]:
                sa, row = _step(ka, sa, dt, max_steps)
                _record(rec_a, row)
                sb, row = _step(kb, sb, dt, max_steps)
                _record(rec_b, row)
            while sb[_RUNNING]:
                sb, row = _step(kb, sb, dt, max_steps)
                _record(rec_b, row)
        while sa[_RUNNING]:
            sa, row = _step(ka, sa, dt, max_steps)
            _record(rec_a, row)
        _finish(ka, sa, res[a])
        if b != a:
            _finish(kb, sb, res[b])


def empty_results(batch: int) -> np.ndarray:
    """A result matrix for ``batch`` elements, NaN-filled."""
    return np.full((batch, N_RESULTS), np.nan)
