"""A rover's calibration: the estimator's model corrected for what the testbed logs of that rover show.

* :mod:`slipest.rover.testbed`: testbed logs as feature rows with a known slip;
* :mod:`slipest.rover.discrepancy`: the feature discrepancy (a polynomial in slip and soil);
* :mod:`slipest.rover.physics`: the discrepancy a named catalog effect causes, from the simulator;
* :mod:`slipest.rover.fit`: each log's soil, the testbed correction, blind scores;
* :mod:`slipest.rover.eq515`: Eq. 5.15 refitted on the testbed logs;
* :mod:`slipest.rover.surrogate`: :class:`RoverSurrogate`, the calibrated model the estimator takes;
* :mod:`slipest.rover.calibrate`: :func:`calibrate`, the whole procedure;
* :mod:`slipest.rover.file`: the rover file (:func:`load_rover`, :func:`save_rover`).

A rover program::

    from slipest import SlipEstimator
    from slipest.rover import load_rover

    est = SlipEstimator(n_legs=4, model=load_rover("rover.json", n_legs=4))

Design and measurements: ``docs/calibration.md``.
"""

from slipest.rover.file import RoverFileError, load_rover, save_rover
from slipest.rover.surrogate import RoverSurrogate

__all__ = ["RoverFileError", "RoverSurrogate", "load_rover", "save_rover"]
