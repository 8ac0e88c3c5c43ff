"""What ``slipest serial`` and ``slipest can`` share: options, printing, the run.

The runtime is the library's (:mod:`slipest.live`); this module turns the
command line into it and prints: the live options (:func:`add_live_arguments`),
the :class:`~slipest.live.LiveEstimation` they describe
(:func:`live_from_args`), the estimate rows (:func:`make_printer`), the
counters for people (:func:`format_counters`), and the run of a command
around a source (:func:`run_command`: counters at exit and on SIGUSR1, the
``--report`` JSON, exit code 0 on a normal stop; a second Ctrl-C or SIGTERM
while it stops is ignored, so the recording and the report are complete).

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

from slipest.cli.command import add_logging_arguments
from slipest.cli.estimator_args import add_estimator_arguments, model_from_args, soil_from_args
from slipest.io.device_stream import STUCK_TIME
from slipest.live import LiveEstimation, StopConditions, run_live
from slipest.live.loop import StopSignals

#: What ``--format`` offers: CSV rows, JSON lines, or no estimates printed.
FORMATS = ("csv", "jsonl", "none")


def add_live_arguments(p: argparse.ArgumentParser, link: str) -> None:
    """Options shared by the live commands; ``link``: what ``--wait-open`` opens (for its help)."""
    p.add_argument("--config", metavar="FILE.toml",
                   help="read options from a TOML file: its keys are this command's long options (e.g. legs = 4, "
                   "wheel = [0, 1], model = \"m.json\"); options on the command line override it")
    p.add_argument("--wait-open", type=float, default=5.0, metavar="S",
                   help=f"keep trying to open {link} for S seconds at start (default 5)")
    e = p.add_argument_group("estimation")
    e.add_argument("--legs", type=int, default=4, help="legs of each wheel-leg (default 4)")
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
    o.add_argument("--record", metavar="FILE",
                   help="record the input to a log CSV (wheel 0: FILE; wheel k: STEM.wheelK.EXT, or FILE with "
                   "{wheel} replaced); flushed continuously, complete after Ctrl-C or SIGTERM")
    o.add_argument("--overwrite", action="store_true", help="overwrite existing --record files")
    o.add_argument("--report", metavar="FILE", help="write the counters and latency figures as JSON at exit")
    o.add_argument("--format", choices=FORMATS, default="csv",
                   help="estimates on stdout: csv (default; a header, then one row per leg cycle, wheel first), "
                   "jsonl (one JSON object per line, wheel first), none (not printed)")
    add_logging_arguments(p)
    s = p.add_argument_group("stopping")
    s.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    s.add_argument("--cycles", type=int, default=None, metavar="N",
                   help="stop once every wheel seen has N leg cycles estimated or flagged")
    s.add_argument("--idle-timeout", type=float, default=None, metavar="S",
                   help="stop when no frame arrived for S seconds (after the first one); without a stop option "
                   "the run goes on until Ctrl-C or SIGTERM, saying when no data came for 5 s")
    t = p.add_argument_group("timing")
    t.add_argument("--sim-speed", type=float, default=None, metavar="S",
                   help="the device is firmware-sim on this host with --speed S: its timestamps are this host's "
                   "monotonic clock x S, so the latency from each sample's instant to its intake is measured, and "
                   "wrapped CAN timestamps are unwrapped across outages knowing that device time runs S times "
                   "faster than this host's")


def live_from_args(args, source, on_estimate) -> LiveEstimation:
    """The warmed-up :class:`~slipest.live.LiveEstimation` the live options describe for ``source``
    (SystemExit on a bad combination or an existing recording)."""
    try:
        live = LiveEstimation(source, n_legs=args.legs, method=args.method, soil=soil_from_args(args),
                              use_reference=args.use_reference, model=model_from_args(args, args.legs), wheels=args.wheel,
                              stuck_samples=args.stuck_samples, stuck_time=args.stuck_time,
                              sim_speed=args.sim_speed, record=args.record,
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
    for key, wc in estimation.items():
        if isinstance(wc, dict):
            flat = {k: v for k, v in wc.items() if not isinstance(v, dict)}
            lines.append(f"  {key}: " + ", ".join(f"{k}={v}" for k, v in flat.items())
                         + (f", qualities={wc['qualities']}" if wc.get("qualities") else ""))
    for name, figures in latency.items():
        if figures.get("n"):
            lines.append(f"  latency {name.replace('_', ' ')}: median {figures['median_ms']:.3f} ms, "
                         f"p99 {figures['p99_ms']:.3f} ms (n={figures['n']})")
    return "\n".join(lines)


def run_command(prog: str, args, source, live: LiveEstimation, started: str) -> int:
    """Start ``source`` (``--wait-open``), log ``started``, run until a stop condition, log the
    reason and the counters, write ``--report``.  Returns 0 on a normal stop (duration, cycles,
    idle, Ctrl-C, SIGTERM); SystemExit when the source cannot be opened or a later wheel's
    recording exists.  Messages go to the logger named after ``prog`` (``slipest.serial``):
    the source's notices at WARNING, the rest at INFO.  From the start of the run to the exit, a
    stop signal after the first is counted (``signals_ignored``) and ignored: the command is exiting."""
    log = logging.getLogger(prog.replace(" ", "."))
    try:
        source.start(wait_open=args.wait_open)
    except OSError as exc:
        raise SystemExit(f"{prog}: {exc}") from None
    with StopSignals(restore=False) as signals:
        log.info("%s", started)

        def status():
            log.info("%s", format_counters(source.counters(), live.counters(), live.latency()))

        stop = StopConditions(duration=args.duration, cycles=args.cycles, idle_timeout=args.idle_timeout)
        try:
            result = run_live(source, live, stop, signals=signals, on_status=status,
                              on_notice=lambda text: log.warning("%s", text))
        except FileExistsError as exc:  # the recording of a wheel that appeared later
            raise SystemExit(f"{prog}: {exc}; use --overwrite") from None
        log.info("%s", result.reason)
        log.info("%s", format_counters(result.source, result.estimation, result.latency))
        if args.report:
            report = result.report()
            report["signals_ignored"] = signals.ignored
            with open(args.report, "w") as fh:
                json.dump(report, fh, indent=1, default=str)
        if signals.ignored:
            log.info("%d more stop signal(s) ignored while stopping (nothing was lost)", signals.ignored)
    return 0
