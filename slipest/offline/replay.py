"""Replay one recorded log through the estimator: its estimates, counters, summary and table rows.

:class:`Replay` opens a log of any kind (:mod:`slipest.offline.logs`),
checks the options (an estimator is built once, so a wrong number of legs
or a bad model file fails before any output), and :meth:`Replay.run` streams
it through the estimator in bounded memory, calling ``on_estimate(wheel,
estimate)`` for every leg cycle in order:

* a slipest log CSV or a ROS 2 bag is one wheel's sample stream (``wheel``
  None), pushed in chunks into one :class:`~slipest.online.SlipEstimator`;
* a CAN log carries frames of every wheel: they go through
  :class:`slipest.live.LiveEstimation`, the live runtime's own frames ->
  samples -> estimator path (losses, restarts, wrapped counters and times,
  stuck sensors), so a replay gives what ``slipest can`` gave on the same
  frames.

The reference slip (the CSV's ``slip`` column, a bag's slip topic, the CAN
SlipReference messages) reaches the estimates' ``slip_ref`` only when
``carry_reference`` (or ``truth`` / ``use_reference``) is set, as in the
live commands, and the estimator learns from it only with
``use_reference``.  With ``use_reference`` or ``truth`` a reference outside
[0, 1) (slip in percent, a negative sign convention) in a CSV, a bag or a
CAN log is refused, naming the log and the time, at the chunk that brings it
(:func:`~slipest.offline.reference_slip.check_reference_slip`); without them
a CAN log's are counted and skipped, as ``slipest can`` skips them.

:class:`ReplayResult` holds per-wheel tallies and counters;
:meth:`ReplayResult.summary_lines` is the one place the replay's summary is
worded, and :meth:`ReplayResult.rows` gives its rows of the many-logs table
(:data:`TABLE_COLUMNS`).  :func:`replay_rows` is the worker of that table:
one log in, its rows out, any error in its row.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from slipest.stuck import STUCK_TIME
from slipest.io.log_csv import LogFormatError, LogReader
from slipest.io.rosbag import BagTopics
from slipest.online import MODEL_HINTS, SlipEstimator, fit_advice
from slipest.offline.logs import KINDS, detect_kind

__all__ = ["TABLE_COLUMNS", "Replay", "ReplayOptions", "ReplayResult", "TruthSummary", "WheelTally", "error_row",
           "replay_rows"]

#: Columns of the many-logs table, one row per log and wheel: counts, the mean estimated slip [-], the soil
#: the estimator held at the end of the log (dphi, dphi_std [rad], kS [N/m], phiS [rad]), the slip RMSE
#: against the log's reference (``truth``), a verdict (``ok``, ``no cycle estimated``, ``no cycle``,
#: ``error``), the error, and the seconds it took.
TABLE_COLUMNS = ("log", "kind", "wheel", "samples", "cycles", "estimated", "flagged", "mean_slip", "dphi", "dphi_std",
                 "kS", "phiS", "slip_rmse", "verdict", "error", "seconds")


@dataclass(frozen=True)
class ReplayOptions:
    """How to replay.  ``legs``: legs of the wheel-leg (None: the log's ``nL``, else 4).  ``method``,
    ``soil`` (``{name: value}`` SI), ``model`` (an inverse-model file; None: the shipped one), ``rover``
    (a rover file of ``slipest calibrate``, instead of ``model``) and ``use_reference``: as
    :class:`~slipest.online.SlipEstimator`.  ``truth``: compare the slip with the
    log's reference (needs one).  ``carry_reference``: put the reference on the estimates
    (``slip_ref``) without comparing.  ``skip_bad``: count and skip malformed CSV rows.  ``log_format``:
    ``"auto"`` or one of :data:`~slipest.offline.logs.KINDS`.  ``wheels``: CAN wheels to estimate (None:
    all).  ``stuck_time`` [s] (default 20 ms, as live) or ``stuck_samples`` (a fixed run length; 0:
    never): a stuck sensor (:mod:`slipest.stuck`; a CAN log's frames as
    :class:`~slipest.io.device_stream.WheelStream` takes them, a sample log's cycles as
    :class:`~slipest.online.SlipEstimator` does).  ``bag``: where the
    samples are in a ROS 2 bag.  ``chunk_rows``: samples per push (memory)."""

    legs: int | None = None
    method: str = "default"
    soil: dict | None = None
    model: str | None = None
    rover: str | None = None
    use_reference: bool = False
    truth: bool = False
    carry_reference: bool = False
    skip_bad: bool = False
    log_format: str = "auto"
    wheels: tuple | None = None
    stuck_time: float = STUCK_TIME
    stuck_samples: int | None = None
    bag: BagTopics = BagTopics()
    chunk_rows: int = 65536

    @property
    def pass_reference(self) -> bool:
        return self.truth or self.use_reference or self.carry_reference


class TruthSummary:
    """Errors of the slip estimates against the reference slip carried on each estimate (and of
    dphi against a known ``dphi_true`` [rad])."""

    def __init__(self, dphi_true: float | None = None):
        self.err = []
        self.std = []
        self.derr = []
        self.dstd = []
        self.no_truth = 0
        self.dphi_true = dphi_true

    def add(self, e) -> None:
        if not e.ok:
            return
        if math.isfinite(e.slip_ref):
            self.err.append(e.slip - e.slip_ref)
            self.std.append(e.slip_std)
        else:
            self.no_truth += 1
        if self.dphi_true is not None and math.isfinite(e.dphi):
            self.derr.append(e.dphi - self.dphi_true)
            self.dstd.append(e.dphi_std)

    @property
    def slip_rmse(self) -> float:
        return float(np.sqrt(np.mean(np.square(self.err)))) if self.err else math.nan

    @staticmethod
    def _figs(err, std) -> str:
        e = np.asarray(err)
        s = np.asarray(std)
        rmse = float(np.sqrt(np.mean(e**2)))
        cov = float(np.mean(np.abs(e) <= 1.96 * s))
        return f"RMSE {rmse:.4f}, bias {float(np.mean(e)):+.4f}, 95% interval coverage {cov:.3f} ({e.size} cycles)"

    def lines(self) -> list:
        out = []
        if self.err:
            out.append("truth: slip " + self._figs(self.err, self.std))
        else:
            out.append("truth: no cycle had both an estimate and a reference slip")
        if self.no_truth:
            out.append(f"truth: {self.no_truth} estimated cycle(s) had no reference slip")
        if self.derr and not np.any(self.dstd):  # a dphi given (a known soil): nothing was estimated to score
            given = sorted({round(self.dphi_true + e, 9) for e in self.derr})
            out.append(f"truth: dphi was given ({', '.join(f'{g:g}' for g in given)} rad), not estimated; the log's "
                       f"metadata says {self.dphi_true:g} rad")
        elif self.derr:
            out.append(f"truth: dphi (log metadata {self.dphi_true:g} rad) " + self._figs(self.derr, self.dstd))
        return out


@dataclass
class WheelTally:
    """One wheel's estimates, tallied as they come: cycles, estimated, the sum of the estimated slips,
    the last estimate (the soil the estimator holds), the truth comparison."""

    truth: TruthSummary | None = None
    cycles: int = 0
    estimated: int = 0
    slip_sum: float = 0.0
    last_ok: object = None
    estimator_counters: dict = field(default_factory=dict)
    stream_counters: dict = field(default_factory=dict)
    hints: dict = field(default_factory=dict)

    def add(self, e) -> None:
        self.cycles += 1
        if e.ok and e.slip == e.slip:
            self.estimated += 1
            self.slip_sum += e.slip
            self.last_ok = e
        if self.truth is not None:
            self.truth.add(e)

    @property
    def mean_slip(self) -> float:
        return self.slip_sum / self.estimated if self.estimated else math.nan

    @property
    def verdict(self) -> str:
        if self.estimated:
            return "ok"
        return "no cycle estimated" if self.cycles else "no cycle"


def _metadata_dphi(meta):
    try:
        phiS, phiD = meta.get_float("phiS"), meta.get_float("phiD")
    except LogFormatError:
        return None  # e.g. "varies"
    return None if phiS is None or phiD is None else phiS - phiD


@dataclass
class ReplayResult:
    """What a replay found (see the module docstring).  ``wheels``: wheel (None for a one-stream log)
    -> :class:`WheelTally`.  ``source``: the reader's counters (CAN decoder, bag)."""

    log: str
    kind: str
    legs: int
    options: ReplayOptions
    wheels: dict
    source: dict
    n_skipped: int = 0
    bad_rows: list = field(default_factory=list)
    seconds: float = 0.0
    joint: str | None = None
    estimator_errors: int = 0
    last_error: str | None = None

    @property
    def estimated(self) -> int:
        return sum(w.estimated for w in self.wheels.values())

    def _cycles_line(self, c: dict) -> str:
        o = self.options
        return (f"{c.get('cycles', 0)} leg cycles: {c.get('cycles_ok', 0)} estimated, "
                f"{c.get('cycles_flagged', 0)} flagged"
                + (" (" + ", ".join(f"{k[len('flagged_'):]} {v}" for k, v in c.items() if k.startswith("flagged_"))
                   + ")" if c.get("cycles_flagged") else "")
                + f"; method {o.method}, {self.legs} legs"
                + (f", reference slip used on {c.get('reference_used', 0)} cycles" if o.use_reference else "")
                + (f"; IMU noise {c['noise_g']:.4f} g" if c.get("noise_g", math.nan) == c.get("noise_g") else "")
                + (f"; {off} estimated cycle(s) off the model (intervals widened)"
                   if (off := c.get("cycles_off_model", 0) - c.get("flagged_misfit", 0)) > 0 else ""))

    @staticmethod
    def _hint_texts(w: "WheelTally") -> list[str]:
        """The estimator's hints on a wheel's data (what looks wrong with the input, a model that does not
        fit it), worded for people: the one wording of the summary's lines and the table's ``error``."""
        return [text if kind in MODEL_HINTS else f"the input looks wrong: {text}"
                for kind, text in w.hints.items() if kind != "fit"]

    @staticmethod
    def _advice_lines(prefix: str, w: "WheelTally") -> list[str]:
        """What looks wrong with a wheel's data, and a model that does not fit it, for people."""
        c = w.estimator_counters
        lines = [f"replay: {prefix}{text}" for text in ReplayResult._hint_texts(w)]
        advice = fit_advice(c.get("cycles_ok", 0) + c.get("flagged_misfit", 0), c.get("cycles_off_model", 0))
        if advice:
            lines.append(f"replay: {prefix}{advice}")
        if w.cycles and not w.estimated:
            lines.append(f"replay: {prefix}no leg cycle was estimated (the flagged reasons above say why)")
        elif not w.cycles:
            n = c.get("samples", 0)
            lines.append(f"replay: {prefix}no leg cycle: " + ("the log holds no samples" if not n else
                         f"its {n} samples never completed a leg cycle (check that theta advances, in rad)"))
        return lines

    def summary_lines(self) -> list[str]:
        """The replay's summary, for people (stderr): what was read, cycles estimated and flagged (and
        why) per wheel, skipped rows, and with ``truth`` the errors against the reference."""
        o = self.options
        lines = []
        if self.kind == "can":
            s = self.source
            lines.append(f"replay: {s['frames']} CAN frames read from {self.log}: {s['ok']} ours, "
                         f"{s['unknown_id']} other IDs, {s['bad_frame']} bad, {s['not_data']} error/remote frames"
                         + (f", {s['references_invalid']} invalid references" if s["references_invalid"] else "")
                         + (f", {s['references_out_of_range']} references outside [0, 1) skipped"
                            if s.get("references_out_of_range") else ""))
            if s.get("bytes_missing"):
                lines.append(f"replay: {self.log} is cut short: its header says {s['bytes_missing']} bytes more than "
                             "the file has (a copy or a recording that stopped early); the frames in them are lost")
            if not self.wheels:
                lines.append("replay: no ImuSample frame of a wheel to estimate")
            for wheel, w in sorted(self.wheels.items()):
                sc = w.stream_counters
                lines.append(f"replay: wheel {wheel}: {sc.get('samples_out', 0)} samples ({sc.get('frames_lost', 0)} "
                             f"lost frames filled, {sc.get('out_of_order', 0)} out of order, "
                             + (f"{sc['reordered']} put back in order, " if sc.get("reordered") else "")
                             + (f"{sc['frames_invalid']} invalid (no angle or time), " if sc.get("frames_invalid")
                                else "")
                             + f"{sc.get('restarts', 0)} restarts, {sc.get('stuck_samples', 0)} stuck); "
                             + self._cycles_line(w.estimator_counters))
        else:
            (w,) = self.wheels.values()
            c = w.estimator_counters
            lines.append(f"replay: {c.get('samples', 0)} samples read from {self.log}"
                         + (f", {self.n_skipped} malformed row(s) skipped" if o.skip_bad else ""))
            if self.kind == "ros2":
                s = self.source
                lines.append(f"replay: ROS 2 bag: {s['imu_messages']} Imu messages, {s['joint_states']} joint states "
                             f"of {self.joint!r}; {s['outside_joint_states']} samples outside the joint states left "
                             f"out, {s['in_joint_gap']} in joint-state gaps (not estimated)"
                             + (f"; {s['slip_messages']} reference slips" if o.bag.slip else ""))
            lines.append("replay: " + self._cycles_line(c))
        for wheel, w in sorted(self.wheels.items(), key=lambda kv: -1 if kv[0] is None else kv[0]):
            lines += self._advice_lines("" if wheel is None else f"wheel {wheel}: ", w)
        if self.estimator_errors:
            lines.append(f"replay: the estimator failed on {self.estimator_errors} push(es) (their cycles are "
                         f"missing); last: {self.last_error}")
        if o.skip_bad and self.bad_rows:
            first = self.bad_rows[0]
            lines.append(f"replay: first malformed row: line {first.line}: {first.reason}")
        for wheel, w in sorted(self.wheels.items(), key=lambda kv: -1 if kv[0] is None else kv[0]):
            if w.truth is not None:
                prefix = "" if wheel is None else f"wheel {wheel}: "
                lines += [line.replace("truth: ", f"truth: {prefix}", 1) for line in w.truth.lines()]
        return lines

    def rows(self) -> list[dict]:
        """This log's rows of the many-logs table (:data:`TABLE_COLUMNS`), one per wheel.  ``error``: the
        estimator's last error, else, for a wheel with no cycle estimated, the hints on its data that the
        summary gives (e.g. az in g), joined by ``"; "``."""
        out = []
        for wheel, w in sorted(self.wheels.items(), key=lambda kv: -1 if kv[0] is None else kv[0]):
            last = w.last_ok
            soil = {k: getattr(last, k, math.nan) for k in ("dphi", "dphi_std", "kS", "phiS")}
            out.append({"log": self.log, "kind": self.kind, "wheel": "" if wheel is None else wheel,
                        "samples": w.estimator_counters.get("samples", 0), "cycles": w.cycles,
                        "estimated": w.estimated, "flagged": w.cycles - w.estimated, "mean_slip": w.mean_slip, **soil,
                        "slip_rmse": w.truth.slip_rmse if w.truth is not None else math.nan,
                        "verdict": w.verdict,
                        "error": self.last_error or ("" if w.estimated else "; ".join(self._hint_texts(w))),
                        "seconds": self.seconds})
        if not out:
            out.append(error_row(self.log, "no ImuSample frame of a wheel to estimate", self.kind, self.seconds,
                                 verdict="no cycle"))
        return out


def error_row(log: str, error: str, kind: str = "", seconds: float = math.nan, verdict: str = "error") -> dict:
    """A table row for a log that could not be replayed (``error``: what went wrong)."""
    row = dict.fromkeys(TABLE_COLUMNS, "")
    row.update(log=log, kind=kind, verdict=verdict, error=error, seconds=seconds)
    return row


class Replay:
    """One log opened for replay (see the module docstring); a context manager.  ``log``: a path, a
    bag directory, or a binary stream of a slipest CSV; ``name``: how the summary names it (default:
    the path, or the stream's name).

    Raises on opening: ``FileNotFoundError``/``OSError``,
    :class:`~slipest.io.log_csv.LogFormatError` (not a log of its kind, a
    reference needed but absent), ``ValueError`` (options the estimator
    refuses, an inverse-model file that cannot be used: the message names
    it), :class:`~slipest.extras.MissingExtra` (a bag without ``rosbags``, a
    ``.mf4`` without ``asammdf``).
    """

    def __init__(self, log, options: ReplayOptions = ReplayOptions(), *, name: str | None = None):
        self.options = o = options
        if name is None:
            name = os.fsdecode(log) if isinstance(log, (str, bytes, os.PathLike)) else str(getattr(log, "name", "-"))
        self.source_name = name
        kind = detect_kind(log) if o.log_format == "auto" else o.log_format
        if kind not in KINDS:
            raise ValueError(f"unknown log format {kind!r} (known: auto, {', '.join(KINDS)})")
        self.kind = kind
        self._reader = None
        self.dphi_true = None
        self.estimator_errors, self.last_error = 0, None
        try:
            if kind == "slipest":
                self._reader = LogReader(log, skip_bad=o.skip_bad)
                self.legs = o.legs if o.legs is not None else (self._reader.metadata.n_legs or 4)
                has_ref = self._reader.has_slip
                self.dphi_true = _metadata_dphi(self._reader.metadata)
            elif kind == "ros2":
                from slipest.io.rosbag import RosBag

                self._reader = RosBag(log, o.bag)
                self.legs = o.legs if o.legs is not None else 4
                has_ref = self._reader.has_slip
            else:
                from slipest.io.can_log import CanLogFile

                check = self._check_references if o.truth or o.use_reference else None  # as _sample_chunks checks
                self._reader = CanLogFile(log, check_references=check)
                self.legs = o.legs if o.legs is not None else 4
                has_ref = True  # SlipReference frames may come; which wheels have them shows in the summary
            if (o.truth or o.use_reference) and not has_ref:
                what = {"slipest": "a 'slip' column", "ros2": "a reference slip topic (--slip-topic)"}[kind]
                raise LogFormatError(f"--truth and --use-reference need {what}, the log has none", self.source_name)
            from slipest.rover.file import model_from_files

            self.model = model_from_files(o.model, o.rover, self.legs)
            self._estimator(0)  # the options are checked before anything is read
        except BaseException:
            self.close()
            raise

    def _estimator(self, wheel) -> SlipEstimator:
        o = self.options
        return SlipEstimator(n_legs=self.legs, method=o.method, soil=o.soil or None, use_reference=o.use_reference,
                             model=self.model, stuck_time=o.stuck_time, stuck_samples=o.stuck_samples)

    def _tally(self) -> WheelTally:
        o = self.options
        return WheelTally(TruthSummary(self.dphi_true if self.kind == "slipest" else None) if o.truth else None)

    def run(self, on_estimate: Callable | None = None) -> ReplayResult:
        """Stream the log through the estimator (once); ``on_estimate(wheel, estimate)`` for every
        leg cycle in order.  Errors in the log raise :class:`~slipest.io.log_csv.LogFormatError`."""
        t0 = time.monotonic()
        try:
            wheels, source = (self._run_frames if self.kind == "can" else self._run_samples)(on_estimate)
        finally:
            self.close()
        r = self._reader
        return ReplayResult(self.source_name, self.kind, self.legs, self.options, wheels, source,
                            n_skipped=getattr(r, "n_skipped", 0), bad_rows=list(getattr(r, "bad_rows", [])),
                            seconds=time.monotonic() - t0, joint=getattr(r, "joint_name", None),
                            estimator_errors=self.estimator_errors, last_error=self.last_error)

    def _run_samples(self, on_estimate):
        est = self._estimator(None)
        tally = self._tally()
        for e in est.iter_estimates(self._sample_chunks()):
            tally.add(e)
            if on_estimate is not None:
                on_estimate(None, e)
        tally.estimator_counters = est.counters
        tally.hints = est.hints
        source = self._reader.counters() if self.kind == "ros2" else {}
        return {None: tally}, source

    def _check_references(self, slip, t) -> None:
        """A CAN log's references as a CSV's slip column is checked (``LogFormatError`` naming the log)."""
        from slipest.offline.reference_slip import check_reference_slip

        check_reference_slip(slip, t, self.source_name, what="SlipReference frame")

    def _sample_chunks(self):
        """The log's chunks as the estimator takes them, ``(t, az, theta, slip or None)``.  With
        ``use_reference`` or ``truth`` each chunk's reference slip is checked as it reaches the estimator
        (:func:`~slipest.offline.reference_slip.check_reference_slip`): the first chunk with a value
        outside [0, 1) (percent, a negative sign convention) raises ``LogFormatError`` naming the log."""
        from slipest.offline.reference_slip import check_reference_slip

        o = self.options
        check = o.use_reference or o.truth
        for ch in self._reader.iter_chunks(o.chunk_rows):
            if check and ch.slip is not None:
                check_reference_slip(ch.slip, ch.t, self.source_name)
            yield ch.t, ch.az, ch.theta, ch.slip if o.pass_reference else None

    def _run_frames(self, on_estimate):
        from slipest.live.estimation import LiveEstimation

        o = self.options
        tallies: dict[int, WheelTally] = {}

        def collect(wheel, e, info):
            tally = tallies.get(wheel)
            if tally is None:
                tally = tallies[wheel] = self._tally()
            tally.add(e)
            if on_estimate is not None:
                on_estimate(wheel, e)

        # the estimator learns from references only with use_reference (the factory's); they are handed on
        # (slip_ref) when pass_reference, as the live runtime hands them on with its use_reference
        live = LiveEstimation(self._reader, n_legs=self.legs, use_reference=o.pass_reference,
                              wheels=list(o.wheels) if o.wheels else None, stuck_samples=o.stuck_samples,
                              stuck_time=o.stuck_time, on_estimate=collect, estimator_factory=self._estimator)
        try:
            for batches in self._reader.batches():
                live.feed(batches)
        finally:
            live.close()
        counters = live.counters()
        for wheel, st in live.wheels.items():
            tally = tallies.setdefault(wheel, self._tally())
            tally.estimator_counters = st.estimator.counters
            tally.hints = getattr(st.estimator, "hints", {})
            tally.stream_counters = counters[f"wheel{wheel}"]
        self.estimator_errors, self.last_error = counters["estimator_errors"], live.last_error
        return tallies, self._reader.counters()

    def close(self) -> None:
        close = getattr(self._reader, "close", None)
        if close is not None:
            close()

    def __enter__(self) -> "Replay":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def replay_rows(log: str, options: ReplayOptions = ReplayOptions()) -> list[dict]:
    """The many-logs worker: replay ``log`` and return its table rows; an error (a file that cannot
    be read, an estimator failure) becomes the log's row with ``verdict`` ``error`` and what went wrong,
    so the other logs go on.  Picklable (a module-level function), for worker processes and Dask."""
    t0 = time.monotonic()
    try:
        with Replay(log, options) as replay:
            return replay.run().rows()
    except Exception as exc:  # reported in the log's row, not swallowed
        what = str(exc) if isinstance(exc, (LogFormatError, OSError)) else f"{type(exc).__name__}: {exc}"
        kind = options.log_format if options.log_format != "auto" else detect_kind(log)
        return [error_row(str(log), what, kind, time.monotonic() - t0)]
