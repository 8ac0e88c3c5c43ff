"""The calibration of testbed log files: read them, calibrate, write the rover file.

:func:`calibrate_logs` reads slipest log CSVs with the reference ``slip``
column (one soil per log, unknown), takes the known hardware from their
metadata (``nL``, ``MH``, ``mF``, ``lS``; options override them; logs that
disagree are refused, as ``slipest diagnose`` does) and runs
:func:`slipest.rover.calibrate.calibrate`. :func:`write_rover` writes its
result (:func:`slipest.rover.file.save_rover`).

Errors name the file: :class:`~slipest.io.log_csv.LogFormatError` (a
malformed log, no ``slip`` column), ``OSError`` (cannot read it),
``ValueError`` (too few usable cycles, logs that disagree on the hardware,
an unknown effect).
"""

from __future__ import annotations

from slipest.io.log_csv import LogFormatError, read_log
from slipest.offline.diagnose import DiagnoseOptions, geometry_of

__all__ = ["calibrate_logs", "write_rover"]


def calibrate_logs(paths, options=None, *, legs: int | None = None, MH: float | None = None, mF: float | None = None,
                   lS: float | None = None, model: str | None = None, progress=None):
    """The :class:`~slipest.rover.calibrate.Calibration` of testbed logs (``options``:
    :class:`~slipest.rover.calibrate.CalibrateOptions`; ``model``: an inverse-model file to correct instead
    of the shipped one); ``progress(done, total, label)`` per stage."""
    from slipest.rover.calibrate import CalibrateOptions, TestbedRun, calibrate

    options = options or CalibrateOptions()
    paths = [str(p) for p in paths]
    logs = []
    for p in paths:
        try:
            log = read_log(p)
        except OSError as exc:
            raise OSError(exc.errno, f"cannot read {p}: {exc.strerror or exc}") from None
        if log.slip is None:
            raise LogFormatError("no 'slip' column: calibration needs the slip of every leg cycle (a testbed's "
                                 "reference, visual odometry)", p)
        logs.append(log)
    diag = DiagnoseOptions(effects=options.effects, legs=legs, MH=MH, mF=mF, lS=lS)
    diag.checked_effects()
    geometry = geometry_of(diag, [log.metadata for log in logs])
    runs = [TestbedRun(p, log.t, log.az, log.theta, log.slip) for p, log in zip(paths, logs)]
    base = None
    if model:
        from slipest.inverse.surrogate import load_inverse_model

        base = load_inverse_model(model)
    return calibrate(runs, geometry, options, progress=progress, base=base)


def write_rover(calibration, path, created_by: str, model: str | None = None):
    """Write the calibration's rover file (``model``: the inverse-model file it corrects; None: shipped)."""
    from slipest.rover.file import save_rover

    return save_rover(calibration.model, calibration.report, path, created_by=created_by, base_path=model)
