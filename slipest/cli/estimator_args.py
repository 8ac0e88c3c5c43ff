"""The estimator options that `slipest replay` and the live commands (`serial`, `can`) share.

``--method``, ``--model``, ``--rover`` and the known soil (``--kS``,
``--phiS``, ``--phiD``, ``--dphi``): added to a parser by
:func:`add_estimator_arguments` and read back by :func:`soil_from_args`
(which also checks that ``--method eq515`` has what it needs, and says so in
the options' own spelling) and :func:`model_from_args` (the inverse model or
the rover's calibrated one).
"""

from __future__ import annotations

import argparse

#: The soil options, in SI: kS [N/m], phiS, phiD, dphi [rad].
SOIL_OPTIONS = ("kS", "phiS", "phiD", "dphi")

#: What ``--method eq515`` needs (slipest.inverse.eq515.Eq515Tracker): kS always (Eq. 5.15 cannot learn
#: it); dphi known, or learnt from the reference slip.
EQ515_NEEDS = "needs --kS, and --dphi (or --phiS with --phiD) or --use-reference to learn dphi from the reference slip"


def add_estimator_arguments(p) -> None:
    """Add ``--method``, ``--model``, ``--rover`` and the soil options to a parser or an argument group."""
    from slipest.online import METHODS

    p.add_argument("--method", choices=METHODS, default="default",
                   help="default: multi-feature inverse with the soil learnt as it goes; eq515: thesis Eq. 5.15, "
                   f"the baseline: {EQ515_NEEDS}; its calibration knows one leg speed (the shipped one: 4 legs at "
                   "0.63 rad/s), a cycle driven more than 10%% faster or slower is flagged 'speed', not estimated")
    p.add_argument("--model", metavar="FILE", default=None,
                   help="inverse model file (.npz) of the default method (default: the shipped one, made for 4 legs "
                   "and leg speeds 0.3-1.2 rad/s; tools/train_inverse.py makes one for another wheel-leg or range)")
    p.add_argument("--rover", metavar="ROVER.json", default=None,
                   help="the rover file slipest calibrate wrote from this rover's testbed logs: the model corrected "
                   "for this rover (default method) and its refitted Eq. 5.15 (--method eq515)")
    p.add_argument("--kS", type=float, default=None, help="known soil stiffness [N/m]")
    p.add_argument("--phiS", type=float, default=None, help="known static friction angle [rad]")
    p.add_argument("--phiD", type=float, default=None, help="known dynamic friction angle [rad]")
    p.add_argument("--dphi", type=float, default=None, help="known phiS - phiD [rad]")


def soil_from_args(args: argparse.Namespace) -> dict:
    """The soil options given, ``{name: value}`` (empty when none).

    ValueError, naming the options, when ``--method eq515`` lacks what it
    needs (:data:`EQ515_NEEDS`; ``args.use_reference`` is read where the
    command has it).
    """
    soil = {k: getattr(args, k) for k in SOIL_OPTIONS if getattr(args, k, None) is not None}
    if getattr(args, "method", None) == "eq515":
        dphi_known = "dphi" in soil or {"phiS", "phiD"} <= set(soil)
        if "kS" not in soil or not (dphi_known or getattr(args, "use_reference", False)):
            given = ", ".join(f"--{k}" for k in soil) or "no soil option"
            raise ValueError(f"--method eq515 {EQ515_NEEDS} (given: {given})")
    return soil


def model_from_args(args: argparse.Namespace, n_legs: int | None = None):
    """The model ``--rover`` or ``--model`` names, or None for the shipped one; ``n_legs``: the legs it will
    estimate (a rover file made for others is refused).

    Raises :class:`~slipest.inverse.surrogate.InverseModelError` or
    :class:`~slipest.rover.file.RoverFileError` (ValueErrors naming the file)
    when it cannot be used, and ValueError when both are given.
    """
    from slipest.rover.file import model_from_files

    return model_from_files(getattr(args, "model", None), getattr(args, "rover", None), n_legs)
