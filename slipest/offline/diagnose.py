"""The sim-to-real diagnosis of log files: read them, cut their cycles, diagnose; or one log at a time.

:func:`diagnose_logs` reads slipest log CSVs (with the ``slip`` column: the
slip imposed and logged) and ROS 2 bags (with a reference slip topic: read
as ``slipest replay`` reads them, :class:`~slipest.io.rosbag.RosBag`; they
carry no metadata), takes the known hardware from the CSVs' metadata
(``nL``, ``MH``, ``mF``, ``lS``; :class:`DiagnoseOptions` overrides them;
logs that disagree are refused), cuts and bins their cycles and runs
:func:`slipest.diagnosis.run.diagnose` on all of them together.
:func:`diagnose_rows` is the many-logs worker: one log diagnosed on its own,
its row of the table (:data:`DIAGNOSE_COLUMNS`) out, any error in the row.
Beside the fits, each log's leg swaps are read for the IMU's timing against
the encoder (:func:`slipest.swap_timing.swap_summary`), model-free.

Errors name the file: :class:`~slipest.io.log_csv.LogFormatError` (a
malformed log or bag, or a reference slip outside ``[0, 1)``, e.g. in percent:
:func:`slipest.offline.reference_slip.check_reference_slip`, checked for
every log before any cycle is cut), ``OSError`` (cannot read it), ``ValueError`` (no slip
column or topic, logs that disagree on the hardware, an unknown effect, too few
cycles), :class:`~slipest.extras.MissingExtra` (a bag without ``rosbags``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from slipest.io.log_csv import LogData, LogFormatError, LogMetadata, read_log
from slipest.io.rosbag import BagTopics
from slipest.offline.logs import detect_kind
from slipest.offline.reference_slip import check_reference_slip

__all__ = ["DIAGNOSE_COLUMNS", "DiagnoseOptions", "diagnose_logs", "diagnose_rows", "geometry_of"]

#: The many-logs table of the diagnosis, one row per log: cycles (cut, fitted, held out), what was left out of
#: the log (the leg cycles replay's segmenter flags, and the glitch samples left out of the cycles kept: the
#: report's ``data:`` line), the mean logged slip [-], the nominal model's fitted soil (kS [N/m], phiS, dphi
#: [rad], kappa [-]), the held-out gap before and after the best effect [mg], the verdict (an effect, ``none``,
#: ``unexplained``, or ``error``), the IMU's timing against the encoder at the leg swaps (median offset [ms],
#: steps found, settling ratio [-], NaN when that timing is off: :class:`slipest.swap_timing.SwapSummary`), the
#: error, the seconds it took.
DIAGNOSE_COLUMNS = ("log", "cycles", "fitted", "held_out", "cycles_left_out", "samples_repaired", "mean_slip", "kS",
                    "phiS", "dphi", "kappa", "gap_nominal_mg", "gap_after_mg", "verdict", "swap_offset_ms",
                    "swap_steps", "settling", "error", "seconds")


@dataclass(frozen=True)
class DiagnoseOptions:
    """``effects``: catalog effects to try (None: all).  ``rank_all``: fit every effect even when the
    nominal model explains the data.  ``quick``: half the optimiser budget.  ``seed``: the optimiser's.
    ``legs``, ``MH`` [kg], ``mF`` [kg], ``lS`` [m]: the hardware (None: the logs' metadata, else the
    defaults of :class:`~slipest.diagnosis.fit.Geometry`).  ``bag``: where a ROS 2 bag's samples and
    reference slip are (as replay's)."""

    effects: tuple | None = None
    rank_all: bool = False
    quick: bool = False
    seed: int = 0
    legs: int | None = None
    MH: float | None = None
    mF: float | None = None
    lS: float | None = None
    bag: BagTopics = BagTopics()

    def checked_effects(self):
        """The effects as a list (None: all); ValueError naming unknown ones."""
        from slipest.model.effects import ORDER

        if self.effects is None:
            return None
        bad = [e for e in self.effects if e not in ORDER]
        if bad:
            raise ValueError(f"unknown effect(s) {', '.join(bad)}; known: {', '.join(ORDER)}")
        return list(self.effects)


def geometry_of(options: DiagnoseOptions, metas):
    """The :class:`~slipest.diagnosis.fit.Geometry`: an option, else the logs' metadata (ValueError when
    they disagree), else the default."""
    from slipest.diagnosis.fit import Geometry

    default = Geometry()

    def pick(opt, key, conv, fallback):
        if getattr(options, opt) is not None:
            return conv(getattr(options, opt))
        values = {conv(m[key]) for m in metas if key in m}
        if len(values) > 1:
            raise ValueError(f"the logs disagree on {key} ({sorted(values)}); give --{opt}")
        return values.pop() if values else fallback

    return Geometry(MH=pick("MH", "MH", float, default.MH), mF=pick("mF", "mF", float, default.mF),
                    lS=pick("lS", "lS", float, default.lS), nL=pick("legs", "nL", int, default.nL), g=default.g)


def _read(path, bag: BagTopics = BagTopics()) -> LogData:
    """A log's samples whole: a slipest CSV (:func:`~slipest.io.log_csv.read_log`), or a ROS 2 bag's (its
    chunks as replay streams them, without metadata: ``slip`` None without ``bag.slip``)."""
    try:
        if detect_kind(path) != "ros2":
            return read_log(path)
        from slipest.io.rosbag import RosBag

        with RosBag(path, bag) as reader:
            chunks = list(reader.iter_chunks())
            has_slip = reader.has_slip
    except OSError as exc:
        raise OSError(exc.errno, f"cannot read {path}: {exc.strerror or exc}") from None
    cols = ("t", "az", "theta") + (("slip",) if has_slip else ())
    data = {c: np.concatenate([getattr(ch, c) for ch in chunks]) if chunks else np.zeros(0) for c in cols}
    return LogData(LogMetadata(source=path), cols, data["t"], data["az"], data["theta"], data.get("slip"), {})


def _check_units(path, az) -> None:
    """ValueError naming the likely mistake when the log's median ``az`` is not gravity (``az`` in g, gravity
    removed, the axis reversed: :func:`slipest.online.units_hint`); over whole cycles the hub's own
    acceleration averages out."""
    from slipest.online import GRAVITY_RANGE, units_hint
    from slipest.units import G

    finite = az[np.isfinite(az)]
    if finite.size:
        level = float(np.median(finite)) / G
        if not GRAVITY_RANGE[0] <= level <= GRAVITY_RANGE[1]:
            raise ValueError(f"{path}: {units_hint(level, 'median')}")


def diagnose_logs(paths, options: DiagnoseOptions = DiagnoseOptions(), progress=None):
    """Diagnose the logs together; returns the :class:`~slipest.diagnosis.run.Diagnosis`.
    ``progress(done, total, label)`` as :func:`~slipest.diagnosis.run.diagnose` calls it."""
    from slipest.diagnosis.cycles import concat, cut_cycles, segmenter_flags
    from slipest.diagnosis.fit import FitBudget
    from slipest.diagnosis.predict import Grid
    from slipest.diagnosis.run import diagnose
    from slipest.swap_timing import swap_summary

    effects = options.checked_effects()
    paths = [str(p) for p in paths]
    logs = [_read(p, options.bag) for p in paths]
    geometry = geometry_of(options, [log.metadata for log in logs])
    grid = Grid(geometry.nL)
    for path, log in zip(paths, logs):  # every log checked before any work
        if log.slip is None:
            what = "no reference slip topic (--slip-topic)" if detect_kind(path) == "ros2" else "no 'slip' column"
            raise LogFormatError(f"{what} (the diagnosis needs the imposed slip)", path)
        check_reference_slip(log.slip, log.t, path)  # a slip in percent or negative: refused, not fitted
    sets = []
    for k, (path, log) in enumerate(zip(paths, logs)):
        _check_units(path, log.az)
        try:
            flags = segmenter_flags(log.t, log.az, log.theta, geometry.nL)  # replay's flagged cycles: left out
            sets.append(cut_cycles(log.t, log.az, log.theta, log.slip, geometry.nL, grid=grid, log_index=k,
                                   flags=flags))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    budget = FitBudget().scaled(0.5) if options.quick else FitBudget()
    d = diagnose(concat(sets), geometry, effects, seed=options.seed, budget=budget, rank_all=options.rank_all,
                 progress=progress)
    swaps = tuple((path, swap_summary(log.t, log.az, log.theta, geometry.nL)) for path, log in zip(paths, logs))
    return dataclasses.replace(d, swaps=swaps)


def diagnose_rows(log, options: DiagnoseOptions = DiagnoseOptions()) -> list[dict]:
    """The many-logs worker: ``log`` diagnosed on its own, its table row (:data:`DIAGNOSE_COLUMNS`);
    an error becomes the row's ``error`` (verdict ``error``).  Picklable, for processes and Dask."""
    t0 = time.monotonic()
    row = dict.fromkeys(DIAGNOSE_COLUMNS, "")
    row["log"] = str(log)
    try:
        d = diagnose_logs([log], options)
    except Exception as exc:  # reported in the log's row, not swallowed
        row.update(verdict="error", error=str(exc) if isinstance(exc, (LogFormatError, OSError))
                   else f"{type(exc).__name__}: {exc}", seconds=time.monotonic() - t0)
        return [row]
    soil = d.nominal.soil()
    row.update(cycles=len(d.cycles), fitted=len(d.split.train), held_out=len(d.split.test),
               cycles_left_out=sum(d.cycles.left_out.values()), samples_repaired=d.cycles.repaired,
               mean_slip=float(np.mean(d.cycles.slip)) if len(d.cycles) else math.nan,
               kS=soil["kS"], phiS=soil["phiS"], dphi=soil["dphi"], kappa=soil["kappa"],
               gap_nominal_mg=d.gap_nominal * 1000, gap_after_mg=d.gap_after * 1000, verdict=d.verdict,
               seconds=time.monotonic() - t0)
    if d.swaps:
        sw = d.swaps[0][1]
        row.update(swap_offset_ms=sw.offset_s * 1000, swap_steps=sw.measured, settling=sw.settling_read)
    return [row]
