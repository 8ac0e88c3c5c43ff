"""The estimator options that `slipest replay` and the live commands (`serial`, `can`) share.

``--method``, ``--model`` and the known soil (``--kS``, ``--phiS``,
``--phiD``, ``--dphi``): added to a parser by :func:`add_estimator_arguments`
and read back by :func:`soil_from_args` and :func:`model_from_args`.
"""

from __future__ import annotations

import argparse

#: The soil options, in SI: kS [N/m], phiS, phiD, dphi [rad].
SOIL_OPTIONS = ("kS", "phiS", "phiD", "dphi")


def add_estimator_arguments(p) -> None:
    """Add ``--method``, ``--model`` and the soil options to a parser or an argument group."""
    from slipest.online import METHODS

    p.add_argument("--method", choices=METHODS, default="default",
                   help="default: multi-feature inverse with the soil learnt as it goes; eq515: thesis Eq. 5.15 "
                   "(always needs --kS; and --dphi, or --phiS with --phiD, or --use-reference to learn dphi from "
                   "the reference slip)")
    p.add_argument("--model", metavar="FILE", default=None,
                   help="inverse model JSON of the default method (default: the shipped one, made for 4 legs at "
                   "0.63 rad/s; tools/train_inverse.py --legs N makes one for another wheel-leg)")
    p.add_argument("--kS", type=float, default=None, help="known soil stiffness [N/m]")
    p.add_argument("--phiS", type=float, default=None, help="known static friction angle [rad]")
    p.add_argument("--phiD", type=float, default=None, help="known dynamic friction angle [rad]")
    p.add_argument("--dphi", type=float, default=None, help="known phiS - phiD [rad]")


def soil_from_args(args: argparse.Namespace) -> dict:
    """The soil options given, ``{name: value}`` (empty when none)."""
    return {k: getattr(args, k) for k in SOIL_OPTIONS if getattr(args, k, None) is not None}


def model_from_args(args: argparse.Namespace):
    """The inverse model ``--model`` names, or None for the shipped one.

    Raises :class:`~slipest.inverse.surrogate.InverseModelError` (a
    ValueError naming the file) when it cannot be used.
    """
    path = getattr(args, "model", None)
    if not path:
        return None
    from slipest.inverse.surrogate import load_inverse_model

    return load_inverse_model(path)
