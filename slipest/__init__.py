"""slipest: online slip estimation for wheel-legged rovers from hub vibration.

The names a rover program needs can be imported from here; each is loaded
on first use, so ``import slipest`` stays cheap (no numpy, numba or
python-can until then)::

    from slipest import SlipEstimator        # samples in, one Estimate per leg cycle out
    from slipest import LiveEstimation, StopConditions, run_live   # a live link's runtime

=====================  =========================================================
``SlipEstimator``      :class:`slipest.online.SlipEstimator`
``Estimate``           :class:`slipest.online.Estimate` (one leg cycle's estimate)
``ESTIMATE_FIELDS``    :data:`slipest.online.ESTIMATE_FIELDS` (its field names, in order)
``LiveEstimation``     :class:`slipest.live.LiveEstimation`
``StopConditions``     :class:`slipest.live.StopConditions`
``run_live``           :func:`slipest.live.run_live`
=====================  =========================================================

docs/api.md describes them.  Importing slipest also chooses where numba
caches the compiled kernels when the installed package is read-only
(:mod:`slipest.numba_cache`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from slipest import numba_cache as _numba_cache

__version__ = "0.1.0"

_numba_cache.configure()  # before any kernel is compiled or loaded

#: Public name -> the module it lives in.
_LAZY = {
    "SlipEstimator": "slipest.online",
    "Estimate": "slipest.online",
    "ESTIMATE_FIELDS": "slipest.online",
    "LiveEstimation": "slipest.live",
    "StopConditions": "slipest.live",
    "run_live": "slipest.live",
}

__all__ = ["__version__", *_LAZY]

if TYPE_CHECKING:  # what type checkers see; at run time, __getattr__ loads them on first use
    from slipest.live import LiveEstimation, StopConditions, run_live
    from slipest.online import ESTIMATE_FIELDS, Estimate, SlipEstimator


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'slipest' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
