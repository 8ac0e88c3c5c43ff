"""A log's reference slip column is a fraction in ``[0, 1)``, as the model's slip is (pure check).

Testbed and visual-odometry logs carry the slip they measured. Written in
percent, negative (a sign convention), 1 and above or infinite, it would make a
calibration, a diagnosis or a replay that learns from it (``--use-reference``)
fit the wrong numbers without a word; those commands refuse it, naming the file
(a CAN log's SlipReference frames too: their signed field carries a negative one).
"""

from __future__ import annotations

import numpy as np

from slipest.io.log_csv import LogFormatError, slip_out_of_range

__all__ = ["check_reference_slip"]


def check_reference_slip(slip, t, path: str, *, what: str = "sample") -> None:
    """:class:`~slipest.io.log_csv.LogFormatError` naming ``path`` unless every value of ``slip`` [-] but NaN
    lies in ``[0, 1)`` (:func:`~slipest.io.log_csv.slip_out_of_range`: ``inf`` and ``-inf`` are outside);
    ``t`` [s]: the values' times, to say where the first bad one is; ``what``: what a value is, for the
    message (a CSV's or a bag's ``"sample"``, a CAN log's ``"SlipReference frame"``). NaN (no reference) is
    allowed. The message suggests percent when the values span more than 1.5 and up to 100."""
    slip = np.asarray(slip, dtype=float)
    bad = slip_out_of_range(slip)  # False for NaN, True for +-inf
    if not bad.any():
        return
    i = int(np.argmax(bad))
    known = slip[~np.isnan(slip)]
    lo, hi = float(known.min()), float(known.max())
    hint = " (in percent? slipest wants a fraction, 0.25 for 25 %)" if lo >= 0.0 and 1.5 < hi <= 100.0 else ""
    raise LogFormatError(f"slip {slip[i]:g} at t = {float(np.asarray(t, dtype=float)[i]):.3f} s is outside [0, 1)"
                         f"{hint}; {int(bad.sum())} {what}(s) so, the values span {lo:g} to {hi:g}", path)
