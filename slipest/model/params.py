"""Parameters of the wheel-leg stick-slip model, SI units throughout.

Defaults are those of ``docs/model.md`` section 3. The
nominal model is thesis Eqs. 5.10-5.14 with the leg's lateral stiffness
``kappa kS`` that makes it well-posed; the extension fields (damping,
Stribeck friction, drive ripple) are off at their defaults and exist for the
sim-to-real diagnosis (:mod:`slipest.model.effects`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from slipest.model import kernel as K
from slipest.units import G

#: Default leg angular speed [rad/s]: 10 cm/s traversal with no slip (thesis).
DEFAULT_OMEGA = 0.63
#: Default number of legs of the wheel-leg [-].
DEFAULT_LEGS = 4


@dataclass(frozen=True)
class StickSlipParams:
    """One stance's parameters (SI); every field a finite number (ValueError naming the field otherwise).

    slip: slip ratio ``i`` [-], 0 (none) to <1.
    kS: leg/soil spring stiffness [N/m].
    phiS, phiD: static and dynamic friction angles [rad]; ``muS = tan(phiS)``.
    kappa: lateral leg stiffness as a fraction of ``kS`` [-]; 0 is the
        literal (ill-posed) thesis model, 0.3 the project's default reading.
    MH: hub mass [kg]; mF: foot mass [kg]; nL: number of legs [-];
    lS: spring rest length (spoke length) [m]; omega: leg speed [rad/s];
    g: gravity [m/s^2].
    b_hc: Hunt-Crossley damping ``bHC`` [N s/m^(1+nHC)], >= 0 (0: off);
    n_hc: Hunt-Crossley exponent ``nHC`` [-], >= 0.
    stribeck_vs: Stribeck velocity [m/s], >= 0 (0: constant ``muD``);
    stribeck_exp: Stribeck exponent [-], > 0; viscous: viscous friction [N s/m], >= 0.
    ripple_amp: relative drive speed ripple ``A`` in
        ``omega (1 + A sin(h nL theta + ripple_phase))`` [-], in [0, 1);
        ripple_phase [rad], any finite angle;
        ripple_harmonic: ``h``, ripples per leg cycle (integer >= 1).
    """

    slip: float = 0.25
    kS: float = 1000.0
    phiS: float = 0.52
    phiD: float = 0.35
    kappa: float = 0.3
    MH: float = 1.0
    mF: float = 0.2
    nL: int = DEFAULT_LEGS
    lS: float = 0.1763
    omega: float = DEFAULT_OMEGA
    g: float = G
    b_hc: float = 0.0
    n_hc: float = 1.0
    stribeck_vs: float = 0.0
    stribeck_exp: float = 2.0
    viscous: float = 0.0
    ripple_amp: float = 0.0
    ripple_phase: float = 0.0
    ripple_harmonic: int = 1

    def __post_init__(self):
        problems = []
        # every field is a finite number first: NaN fails no comparison, so a range check alone lets it through
        for f in fields(self):
            value = getattr(self, f.name)
            try:
                finite = not isinstance(value, (bool, str)) and math.isfinite(value)
            except TypeError:
                finite = False
            if not finite:
                problems.append(f"{f.name}={value!r} must be a finite number")
        if problems:
            raise ValueError("invalid stick-slip parameters: " + "; ".join(problems))
        if not 0.0 <= self.slip < 1.0:
            problems.append(f"slip={self.slip} must be in [0, 1)")
        for name in ("kS", "MH", "mF", "lS", "omega", "g", "stribeck_exp"):
            value = getattr(self, name)
            if not value > 0.0:
                problems.append(f"{name}={value} must be a positive finite number")
        if not 0.0 < self.phiD <= self.phiS < math.pi / 2:
            problems.append(f"friction angles must satisfy 0 < phiD <= phiS < pi/2 (phiS={self.phiS}, phiD={self.phiD})")
        for name in ("kappa", "b_hc", "n_hc", "stribeck_vs", "viscous"):
            value = getattr(self, name)
            if value < 0.0:
                problems.append(f"{name}={value} must be >= 0")
        if int(self.nL) != self.nL or self.nL < 2:
            problems.append(f"nL={self.nL} must be an integer >= 2")
        if not 0.0 <= self.ripple_amp < 1.0:
            problems.append(f"ripple_amp={self.ripple_amp} must be in [0, 1)")
        if int(self.ripple_harmonic) != self.ripple_harmonic or self.ripple_harmonic < 1:
            problems.append(f"ripple_harmonic={self.ripple_harmonic} must be an integer >= 1")
        if not problems and self.MH * self.g / self.kS >= self.lS:
            problems.append(
                f"the hub's static sinkage MH g / kS = {self.MH * self.g / self.kS:.4f} m is not below lS = {self.lS} m"
            )
        if problems:
            raise ValueError("invalid stick-slip parameters: " + "; ".join(problems))

    @property
    def dphi(self) -> float:
        """Friction angle drop ``phiS - phiD`` [rad]."""
        return self.phiS - self.phiD

    @property
    def muS(self) -> float:
        """Static friction coefficient [-]."""
        return math.tan(self.phiS)

    @property
    def muD(self) -> float:
        """Dynamic friction coefficient [-]."""
        return math.tan(self.phiD)

    @property
    def stance_angle(self) -> float:
        """Leg angle at the end of the propulsive half-stance, ``pi/nL`` [rad]."""
        return math.pi / self.nL

    def with_(self, **changes) -> "StickSlipParams":
        """A copy with some fields changed (validated)."""
        return replace(self, **changes)

    def as_dict(self) -> dict:
        """Field name to value."""
        return asdict(self)

    def to_row(self) -> np.ndarray:
        """This parameter set as one row of the kernel's parameter matrix."""
        row = np.zeros(K.N_PARAMS)
        row[K.P_SLIP] = self.slip
        row[K.P_KS] = self.kS
        row[K.P_MUS] = self.muS
        row[K.P_MUD] = self.muD
        row[K.P_KAPPA] = self.kappa
        row[K.P_MH] = self.MH
        row[K.P_MF] = self.mF
        row[K.P_LS] = self.lS
        row[K.P_OMEGA] = self.omega
        row[K.P_NL] = self.nL
        row[K.P_G] = self.g
        row[K.P_BHC] = self.b_hc
        row[K.P_NHC] = self.n_hc
        row[K.P_VS] = self.stribeck_vs
        row[K.P_SEXP] = self.stribeck_exp
        row[K.P_VISC] = self.viscous
        row[K.P_RIPPLE_A] = self.ripple_amp
        row[K.P_RIPPLE_PH] = self.ripple_phase
        row[K.P_RIPPLE_H] = self.ripple_harmonic
        return row


PARAM_NAMES = tuple(f.name for f in fields(StickSlipParams))


def param_matrix(params) -> np.ndarray:
    """Kernel parameter matrix ``(B, N_PARAMS)`` from a sequence of :class:`StickSlipParams`."""
    params = list(params)
    if not params:
        raise ValueError("no parameter sets given")
    return np.stack([p.to_row() for p in params])


def param_grid(base: StickSlipParams | None = None, **arrays) -> list[StickSlipParams]:
    """Parameter sets with fields taken from broadcast arrays, e.g. a sweep.

    ``param_grid(slip=np.linspace(0, .5, 11), kS=[[500], [1000]])`` gives
    the 22 combinations (numpy broadcasting), flattened in C order. Every
    set is validated.
    """
    base = base or StickSlipParams()
    unknown = set(arrays) - set(PARAM_NAMES)
    if unknown:
        raise ValueError(f"unknown parameter(s): {sorted(unknown)}")
    names = list(arrays)
    bcast = np.broadcast_arrays(*[np.asarray(arrays[n], dtype=float) for n in names])
    flat = [b.ravel() for b in bcast]
    out = []
    for j in range(flat[0].size if flat else 0):
        change = {n: (int(v[j]) if n == "nL" else float(v[j])) for n, v in zip(names, flat)}
        out.append(replace(base, **change))
    return out
