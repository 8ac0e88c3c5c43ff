"""The small interface every slip inverse implements (pure computation).

An *inverse* turns one leg cycle's feature row (:data:`slipest.features.FEATURE_NAMES`,
from :func:`slipest.features.cycle_features`) into a slip estimate with a
standard deviation, with the soil known or, if the inverse can, unknown.
Recursive use over many cycles (learning the soil) is the job of
:mod:`slipest.estimator`; an inverse is one cycle at a time.

Units: slip [-]; soil ``kS`` [N/m], ``phiS``, ``phiD`` [rad]; ``Da`` [g].
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Soil:
    """A soil (leg/soil spring and friction): ``kS`` [N/m], ``phiS``, ``phiD`` [rad].

    ``phiS`` may be None when only ``dphi = phiS - phiD`` is known (give
    ``dphi`` then); :meth:`from_args` builds one from whatever is known.
    """

    kS: float | None = None
    phiS: float | None = None
    phiD: float | None = None
    dphi_: float | None = None

    def __post_init__(self):
        for name in ("kS", "phiS", "phiD", "dphi_"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"soil {name.rstrip('_')}={v} must be finite")
        if self.kS is not None and not self.kS > 0:
            raise ValueError(f"soil kS={self.kS} N/m must be > 0")
        if self.phiS is not None and self.phiD is not None:
            if not 0 < self.phiD <= self.phiS < math.pi / 2:
                raise ValueError(f"soil friction angles must satisfy 0 < phiD <= phiS < pi/2 (phiS={self.phiS}, phiD={self.phiD})")
            if self.dphi_ is not None and abs(self.dphi_ - (self.phiS - self.phiD)) > 1e-9:
                raise ValueError("dphi given does not equal phiS - phiD")
        if self.dphi_ is not None and self.dphi_ < 0:
            raise ValueError(f"soil dphi={self.dphi_} rad must be >= 0")

    @classmethod
    def from_args(cls, kS=None, phiS=None, phiD=None, dphi=None) -> "Soil | None":
        """A soil from any of its known parts (``phiD = phiS - dphi`` and the like); None if nothing is known."""
        if all(v is None for v in (kS, phiS, phiD, dphi)):
            return None
        if phiS is None and phiD is not None and dphi is not None:
            phiS = phiD + dphi
        if phiD is None and phiS is not None and dphi is not None:
            phiD = phiS - dphi
        return cls(kS=kS, phiS=phiS, phiD=phiD, dphi_=dphi)

    @property
    def dphi(self) -> float | None:
        """``phiS - phiD`` [rad] when known."""
        if self.phiS is not None and self.phiD is not None:
            return self.phiS - self.phiD
        return self.dphi_

    @property
    def complete(self) -> bool:
        """True when kS, phiS and phiD are all known."""
        return None not in (self.kS, self.phiS, self.phiD)


class SlipInverse(ABC):
    """One-cycle slip inverse.

    ``name``: short name (``"eq515"``, ``"surrogate"``). ``needs_soil``:
    which soil parts :meth:`slip` requires (empty: none, it can estimate
    with the soil unknown). ``features``: the feature names it reads.
    """

    name: str = ""
    needs_soil: tuple = ()
    features: tuple = ()

    def check_soil(self, soil: Soil | None) -> None:
        """Raise ``ValueError`` naming what is missing when ``soil`` lacks a part this inverse needs."""
        missing = [p for p in self.needs_soil if soil is None or getattr(soil, p) is None]
        if missing:
            raise ValueError(f"the {self.name} inverse needs the soil's {', '.join(missing)}")

    @abstractmethod
    def slip(self, features: np.ndarray, soil: Soil | None = None) -> tuple[float, float]:
        """Slip [-] and its standard deviation [-] from one feature row (order of ``FEATURE_NAMES``).

        NaN features give ``(nan, nan)``.
        """

    def slip_batch(self, features_2d: np.ndarray, soil: Soil | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`slip` over the rows of ``features_2d``: arrays ``(slip, std)``."""
        features_2d = np.atleast_2d(np.asarray(features_2d, dtype=float))
        out = np.array([self.slip(row, soil) for row in features_2d], dtype=float).reshape(-1, 2)
        return out[:, 0], out[:, 1]
