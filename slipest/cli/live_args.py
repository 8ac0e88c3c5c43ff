"""What ``slipest serial`` and ``slipest can`` share: options, printing, the run.

The runtime is the library's (:mod:`slipest.live`); this module turns the
command line into it and prints: the live options (:func:`add_live_arguments`),
the :class:`~slipest.live.LiveEstimation` they describe
(:func:`live_from_args`), the estimate rows (:func:`make_printer`), the
counters for people (:func:`format_counters`), the live view
(:func:`add_view_arguments`, :func:`view_from_args`: ``--view [HOST:]PORT``,
a Foxglove WebSocket server, :mod:`slipest.live.view`), and the run of a
command around a source (:func:`run_command`: counters at exit and on
SIGUSR1, the ``--report`` JSON, exit code 0 on a normal stop; it says
``stopping (REASON)`` as soon as it stops, and a second Ctrl-C or SIGTERM
while it stops is ignored, so the recording and the report are complete).

``--record FILE`` (repeatable) records by the file's name: a ``.csv`` (or
any name that is not a python-can log) gets the samples each wheel's
estimator was given; a python-can log name (``.asc``, ``.blf``, ``.log``,
``.trc``, ``.db``, ``.mf4``, gzipped text ones) gets the raw CAN frames
(``slipest can`` only); ``--record-frames FILE`` records the frames
whatever the suffix (python-can's ``.csv``).

Estimates go to stdout (``--format csv``, ``jsonl`` or ``none``); every
other message goes through :mod:`logging` to stderr, with time and level
(``-v``/``-q``/``--log-level``): INFO for the start, the stop and the
counters (at exit and on SIGUSR1), WARNING for the link's trouble
(disconnections, reconnections, bus errors), ERROR for what stops the
command.  ``--config FILE`` reads options from a TOML file
(:mod:`slipest.cli.config_file`).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

from slipest.cli.command import add_logging_arguments, leg_count
from slipest.cli.estimator_args import add_estimator_arguments, model_from_args, soil_from_args
from slipest.cli.output_paths import output_problem
from slipest.live import LiveEstimation, StopConditions, run_live
from slipest.live.loop import RunResult, StopSignals
from slipest.live.recording import record_path
from slipest.stuck import STUCK_TIME

#: What ``--format`` offers: CSV rows, JSON lines, or no estimates printed.
FORMATS = ("csv", "jsonl", "none")


def add_live_arguments(p: argparse.ArgumentParser, link: str, *, frames: bool = False) -> None:
    """Options shared by the live commands; ``link``: what ``--wait-open`` opens (for its help);
    ``frames``: the link delivers CAN frames (``--record-frames``)."""
    p.add_argument("--config", metavar="FILE.toml",
                   help="read options from a TOML file: its keys are this command's long options (e.g. legs = 4, "
                   "wheel = [0, 1], model = \"rover_model.npz\"); options on the command line override it")
    p.add_argument("--wait-open", type=float, default=5.0, metavar="S",
                   help=f"keep trying to open {link} for S seconds at start (default 5)")
    e = p.add_argument_group("estimation")
    e.add_argument("--legs", type=leg_count, default=4, help="legs of each wheel-leg (default 4)")
    add_estimator_arguments(e)
    e.add_argument("--use-reference", action="store_true",
                   help="learn the soil from the reference slip frames the device sends (testbeds)")
    e.add_argument("--wheel", type=int, action="append", default=None, metavar="W",
                   help="estimate only this wheel (repeatable; default: every wheel seen)")
    stuck = e.add_mutually_exclusive_group()
    stuck.add_argument("--stuck-time", type=float, default=STUCK_TIME, metavar="S",
                       help="az bit-identical for S seconds is a stuck sensor: not estimated from (default "
                       f"{STUCK_TIME:g}: {STUCK_TIME * 1000:g} samples at 1 kHz, at least 12 samples at lower rates; "
                       "0: off; noise-free simulated data over CAN needs 0)")
    stuck.add_argument("--stuck-samples", type=int, default=None, metavar="N",
                       help="a stuck sensor is N bit-identical samples instead (0: off)")
    o = p.add_argument_group("output")
    o.add_argument("--record", metavar="FILE", action="append", default=None,
                   help="record the input, by the file's name (repeatable): FILE.csv: the samples each estimator "
                   "got, as a log CSV (wheel 0: FILE; wheel k: STEM.wheelK.EXT, or FILE with {wheel} replaced); a "
                   "python-can log (.asc, .blf, .log, .trc, .db, .mf4, .asc.gz...): every raw CAN frame received "
                   "(slipest can), which slipest replay turns into the same estimates; flushed continuously, "
                   "complete after Ctrl-C or SIGTERM")
    if frames:
        o.add_argument("--record-frames", metavar="FILE", action="append", default=None,
                       help="record every raw CAN frame received to a python-can log, the format by the suffix "
                       "whatever it is (for python-can's own .csv; repeatable)")
    o.add_argument("--overwrite", action="store_true", help="overwrite existing --record files")
    o.add_argument("--report", metavar="FILE", help="write the counters and latency figures as JSON at exit")
    o.add_argument("--format", choices=FORMATS, default="csv",
                   help="estimates on stdout: csv (default; a header, then one row per leg cycle, wheel first), "
                   "jsonl (one JSON object per line, wheel first), none (not printed)")
    add_view_arguments(o)
    add_logging_arguments(p)
    s = p.add_argument_group("stopping")
    s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    s.add_argument("--cycles", type=int, default=None, metavar="N",
                   help="stop once every wheel seen has N leg cycles estimated or flagged")
    s.add_argument("--idle-timeout", type=float, default=None, metavar="S",
                   help="stop when no frame arrived for S seconds (after the first one); without a stop option "
                   "the run goes on until Ctrl-C or SIGTERM, saying when no data came for 5 s (--quiet-notice)")
    s.add_argument("--quiet-notice", type=float, default=5.0, metavar="S",
                   help="say so when no frame arrived for S seconds, and when data comes back (default 5; again "
                   "after each minute of silence)")
    t = p.add_argument_group("timing")
    t.add_argument("--sim-speed", type=float, default=None, metavar="S",
                   help="the device is firmware-sim on this host with --speed S: its timestamps are this host's "
                   "monotonic clock x S, so the latency from each sample's instant to its intake is measured, and "
                   "wrapped CAN timestamps are unwrapped across outages knowing that device time runs S times "
                   "faster than this host's")


def parse_view_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, port); the host is 127.0.0.1 (this machine only) when omitted; an IPv6
    host in brackets (``[::1]:8765``).  ``argparse.ArgumentTypeError`` on anything else."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep:
        host = "127.0.0.1"
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not host or not 0 <= number <= 65535:
        raise argparse.ArgumentTypeError(f"expected [HOST:]PORT (e.g. 8765, 0.0.0.0:8765), got {text!r}")
    return host, number


def add_view_arguments(group) -> None:
    """``--view [HOST:]PORT`` and ``--view-rate HZ`` (an argument group or parser)."""
    from slipest.live.view import DEFAULT_PORT, DEFAULT_RATE

    group.add_argument("--view", type=parse_view_address, default=None, metavar="[HOST:]PORT",
                       help="publish estimates, az and the leg angle to Foxglove over a WebSocket on PORT "
                       f"(e.g. {DEFAULT_PORT}; 0: any free port; HOST 127.0.0.1 unless given, 0.0.0.0 for every "
                       "interface); open ws://HOST:PORT in Foxglove; needs pip install 'slipest[view]' "
                       "(docs/live-view.md)")
    group.add_argument("--view-rate", type=float, default=DEFAULT_RATE, metavar="HZ",
                       help=f"az and leg-angle samples per second of device time on the view (default {DEFAULT_RATE:g})")


def view_from_args(prog: str, args, live):
    """The :class:`~slipest.live.view.LiveView` ``--view`` asks for, attached to ``live`` (None without
    ``--view``); SystemExit naming the extra to install, or why it cannot listen."""
    if getattr(args, "view", None) is None:
        return None
    from slipest.extras import MissingExtra
    from slipest.live.view import LiveView

    host, port = args.view
    try:
        view = LiveView(host, port, rate=args.view_rate)
    except (MissingExtra, OSError, ValueError) as exc:
        raise SystemExit(f"{prog}: {exc}") from None
    logging.getLogger(prog.replace(" ", ".")).info(
        "live view on %s (Foxglove: Open connection, Foxglove WebSocket, %s)", view.url, view.url)
    return view.attach(live)


def live_from_args(args, source, on_estimate) -> LiveEstimation:
    """The warmed-up :class:`~slipest.live.LiveEstimation` the live options describe for ``source``
    (SystemExit on a bad combination, an existing recording, or one that cannot be written where it is named)."""
    for path in list(args.record or ()) + list(getattr(args, "record_frames", None) or ()):
        problem = output_problem(record_path(path, 0), what="--record")
        if problem:
            raise SystemExit(f"slipest: {problem}")
    try:
        live = LiveEstimation(source, n_legs=args.legs, method=args.method, soil=soil_from_args(args),
                              use_reference=args.use_reference, model=model_from_args(args, args.legs), wheels=args.wheel,
                              stuck_samples=args.stuck_samples, stuck_time=args.stuck_time,
                              sim_speed=args.sim_speed, record=args.record,
                              record_frames=getattr(args, "record_frames", None) or (),
                              overwrite=args.overwrite, on_estimate=on_estimate)
        live.warmup()  # also checks the estimator options (e.g. eq515 without a soil)
    except FileExistsError as exc:
        raise SystemExit(f"slipest: {exc}; use --overwrite") from None
    except (ValueError, TypeError) as exc:
        raise SystemExit(f"slipest: {exc}") from None
    return live


def make_printer(args, out=None):
    """The ``on_estimate`` callback that prints each estimate in ``args.format`` (csv: header first;
    jsonl: one object per line; none: nothing), wheel first, flushed."""
    from slipest.cli import estimate_output

    out = out or sys.stdout
    fmt = getattr(args, "format", "csv")
    state = {"header": False}

    def on_estimate(wheel, est, info):
        if fmt == "jsonl":
            print(estimate_output.json_row(est, {"wheel": wheel}), file=out, flush=True)
        elif fmt == "csv":
            if not state["header"]:
                print(estimate_output.header(("wheel",)), file=out)
                state["header"] = True
            print(estimate_output.row(est, (wheel,)), file=out, flush=True)

    return on_estimate


def format_counters(source: dict, estimation: dict, latency: dict) -> str:
    """Counters of what was dropped and why, and the latencies, for people."""
    lines = ["counters:"]
    lines.append("  source: " + ", ".join(f"{k}={v}" for k, v in source.items() if not isinstance(v, dict)))
    lines.append("  estimation: " + ", ".join(f"{k}={v}" for k, v in estimation.items() if not isinstance(v, dict)))
    for path, fc in estimation.get("frame_logs", {}).items():
        lines.append(f"  CAN log {path}: " + ", ".join(f"{k}={v}" for k, v in fc.items()))
    for key, wc in estimation.items():
        if isinstance(wc, dict) and key != "frame_logs":
            flat = {k: v for k, v in wc.items() if not isinstance(v, dict)}
            lines.append(f"  {key}: " + ", ".join(f"{k}={v}" for k, v in flat.items())
                         + (f", qualities={wc['qualities']}" if wc.get("qualities") else ""))
    for name, figures in latency.items():
        if figures.get("n"):
            lines.append(f"  latency {name.replace('_', ' ')}: median {figures['median_ms']:.3f} ms, "
                         f"p99 {figures['p99_ms']:.3f} ms (n={figures['n']})")
    return "\n".join(lines)


def run_command(prog: str, args, source, live: LiveEstimation, started: str, view=None) -> int:
    """Start ``source`` (``--wait-open``), log ``started``, run until a stop condition, log the
    reason and the counters, write ``--report``.  Returns 0 on a normal stop (duration, cycles,
    idle, Ctrl-C, SIGTERM); SystemExit when the source cannot be opened, a later wheel's
    recording exists or a recording cannot be written.  Messages go to the logger named after
    ``prog`` (``slipest.serial``): the source's notices at WARNING, the rest at INFO; with a
    ``view`` (:func:`view_from_args`) also to its ``/slipest/log``, and the view is closed at the
    end (its counters in the report: ``view``).  From the start of the run to the exit, a stop
    signal after the first is counted (``signals_ignored``) and ignored: the command is exiting."""
    log = logging.getLogger(prog.replace(" ", "."))

    def say(text: str, level: int = logging.INFO) -> None:
        log.log(level, "%s", text)
        if view is not None:
            view.notice(f"{prog}: {text}", logging.getLevelName(level).lower())

    if not args.quiet_notice > 0:
        raise SystemExit(f"{prog}: --quiet-notice must be a number of seconds > 0, not {args.quiet_notice}")
    try:
        try:
            source.start(wait_open=args.wait_open)
        except OSError as exc:
            raise SystemExit(f"{prog}: {exc}") from None
        with StopSignals(restore=False) as signals:
            say(started)

            def status():
                log.info("%s", format_counters(source.counters(), live.counters(), live.latency()))

            def stopping(reason):
                say(f"stopping ({reason}): completing the last cycles, the recordings and the report "
                    "(a further Ctrl-C or SIGTERM is ignored)")

            stop = StopConditions(duration=args.duration, cycles=args.cycles, idle_timeout=args.idle_timeout)
            t0 = time.monotonic()
            failed = None
            try:
                result = run_live(source, live, stop, signals=signals, on_status=status, on_stopping=stopping,
                                  on_notice=lambda text: say(text, logging.WARNING), quiet_notice=args.quiet_notice)
            except FileExistsError as exc:  # the recording of a wheel that appeared later
                raise SystemExit(f"{prog}: {exc}; use --overwrite") from None
            except OSError as exc:  # a recording that cannot be written (the run is closed: what was read is in)
                failed = exc.strerror if isinstance(exc.strerror, str) and exc.errno else str(exc)
                result = RunResult(f"stopped: {failed}", False, time.monotonic() - t0, source.counters(),
                                   live.counters(), live.latency())
            say(result.reason, logging.ERROR if failed else logging.INFO)
            log.info("%s", format_counters(result.source, result.estimation, result.latency))
            if view is not None:
                view.close()
                log.info("live view: %s", ", ".join(f"{k}={v}" for k, v in view.counters().items()))
            if args.report:
                report = result.report()
                report["signals_ignored"] = signals.ignored
                if view is not None:
                    report["view"] = view.counters()
                with open(args.report, "w") as fh:
                    json.dump(report, fh, indent=1, default=str)
            if failed:
                raise SystemExit(f"{prog}: {failed}")
            if signals.ignored:
                log.info("%d more stop signal(s) ignored while stopping (nothing was lost)", signals.ignored)
    finally:
        if view is not None:
            view.close()
    return 0
