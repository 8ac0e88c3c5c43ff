"""The calibration of testbed log files: read them, calibrate, write the rover file.

:func:`calibrate_logs` reads slipest log CSVs with the reference ``slip``
column (one soil per log, unknown), takes the known hardware from their
metadata (``nL``, ``MH``, ``mF``, ``lS``; options override them; logs that
disagree are refused, as ``slipest diagnose`` does) and runs
:func:`slipest.rover.calibrate.calibrate`. :func:`write_rover` writes its
result (:func:`slipest.rover.file.save_rover`).

Errors name the file: :class:`~slipest.io.log_csv.LogFormatError` (a
malformed log, no ``slip`` column, a slip outside ``[0, 1)``: in percent,
say; a time that goes back or repeats: runs appended in one file, which a
calibration would take for one run on one soil), ``OSError`` (cannot read
it), ``ValueError`` (too few usable cycles, one slip level in a log, the
same log given twice: the same samples, whatever the file's bytes; logs of
different IMU rates or that disagree on the hardware, an unknown effect).
"""

from __future__ import annotations

import hashlib

import numpy as np

from slipest.io.log_csv import LogFormatError, read_log
from slipest.offline.diagnose import DiagnoseOptions, geometry_of
from slipest.offline.reference_slip import check_reference_slip

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
        check_reference_slip(log.slip, log.t, p)
        _check_time_increases(log.t, p)
        logs.append(log)
    _check_distinct(logs, paths)
    _check_rates(logs, paths)
    diag = DiagnoseOptions(effects=options.effects, legs=legs, MH=MH, mF=mF, lS=lS)
    diag.checked_effects()
    geometry = geometry_of(diag, [log.metadata for log in logs])
    runs = [TestbedRun(p, log.t, log.az, log.theta, log.slip) for p, log in zip(paths, logs)]
    base = None
    if model:
        from slipest.inverse.surrogate import load_inverse_model

        base = load_inverse_model(model)
    return calibrate(runs, geometry, options, progress=progress, base=base)


#: Logs whose IMU rates differ by more than this fraction are not one rover's IMU setting.
RATE_TOLERANCE = 0.02


def _check_time_increases(t, path: str) -> None:
    """:class:`~slipest.io.log_csv.LogFormatError` naming ``path``, the data row and the times where the log's
    time ``t`` [s] first goes back or repeats (NaN times are passed over, compared with the times around them).
    A calibration takes each log for one run on one soil: two runs appended in one file (the time restarts)
    would be fitted as one."""
    t = np.asarray(t, dtype=float)
    rows = np.flatnonzero(~np.isnan(t))
    steps = np.diff(t[rows])
    back = np.flatnonzero(~(steps > 0.0))
    if not back.size:
        return
    k = int(back[0])
    before, after = float(t[rows[k]]), float(t[rows[k + 1]])
    n_back = int(np.count_nonzero(steps < 0.0))
    how = "goes back" if after < before else "does not increase"
    raise LogFormatError(f"the time {how} at data row {rows[k + 1] + 1}: t = {after:.12g} s after {before:.12g} s "
                         f"({n_back} place(s) where it goes back); a testbed log is one run on one soil: runs "
                         "appended in one file? give each run as its own log", path)


def _samples_digest(log) -> str:
    """sha256 of a log's samples as read (``t``, ``az``, ``theta``, ``slip``): equal for the same run whatever its
    comments, metadata or number formatting (``-0`` is 0, every NaN the same)."""
    h = hashlib.sha256()
    for column in (log.t, log.az, log.theta, log.slip):
        values = np.asarray(column, dtype=np.float64) + 0.0
        values = np.ascontiguousarray(np.where(np.isnan(values), np.nan, values))
        h.update(len(values).to_bytes(8, "little"))
        h.update(values.tobytes())
    return h.hexdigest()


def _check_distinct(logs, paths) -> None:
    """ValueError naming both files when two of the logs hold the same samples (the same file under two names, or
    a copy with other comments: its held-out check would test a log on itself)."""
    seen: dict = {}
    for log, p in zip(logs, paths):
        digest = _samples_digest(log)
        if digest in seen:
            raise ValueError(f"{p} is the same log as {seen[digest]} (the same t, az, theta and slip samples): give "
                             "each testbed run once (a run given twice would be held out against itself)")
        seen[digest] = p


def _check_rates(logs, paths) -> None:
    """ValueError when the logs' IMU rates (median time step) differ by more than :data:`RATE_TOLERANCE`."""
    from slipest.rover.testbed import sample_rate

    rates = [sample_rate(log.t) for log in logs]
    finite = [r for r in rates if np.isfinite(r)]
    if finite and max(finite) > (1.0 + RATE_TOLERANCE) * min(finite):
        listed = ", ".join(f"{p}: {r:.4g} Hz" for p, r in zip(paths, rates))
        raise ValueError(f"the logs were sampled at different IMU rates ({listed}): a rover file is for one IMU "
                         "setting; calibrate the logs of each rate on their own")


def write_rover(calibration, path, created_by: str, model: str | None = None):
    """Write the calibration's rover file (``model``: the inverse-model file it corrects; None: shipped)."""
    from slipest.rover.file import save_rover

    return save_rover(calibration.model, calibration.report, path, created_by=created_by, base_path=model)
