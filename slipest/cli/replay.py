"""``slipest replay``: run the slip estimator over recorded logs, one output row per leg cycle.

Run the online slip estimator over what a rover recorded and write one row
per leg cycle, to stdout (or -o FILE) as CSV (default) or JSON lines: the
fields of slipest.online.Estimate. Units: t [s], delta_a [g], slip [-],
dphi, phiS [rad], kS [N/m]. A cycle that cannot be estimated has NaN values
and its quality says why. A summary (samples, skipped rows, cycles estimated
and flagged, and with --truth the errors against the log's reference slip)
goes to stderr, so stdout stays machine-readable. Logs are read in
bounded-memory chunks. Kinds of log (found from the name, --log-format to
say it):

  slipest CSV  columns t, az, theta, optional slip; '# key=value' metadata
               such as '# nL=4'
  CAN log      python-can's formats (.asc, .blf, .log from candump -l,
               .trc, .csv, .db, .mf4, also gzipped): decoded with the
               shipped DBC, every wheel estimated through the live
               runtime's own path, so the rows are those `slipest can`
               printed on the same frames (with a leading wheel column)
  ROS 2 bag    a rosbag2 directory, .mcap or .db3 (pip install
               'slipest[ros]'): sensor_msgs/Imu z acceleration, the
               wheel-leg joint's angle from sensor_msgs/JointState
               interpolated onto the IMU times

The reference slip (slip column, SlipReference messages, --slip-topic) is
ignored by the estimator unless --use-reference is given, so a log with the
truth in it is still a blind test; --truth only compares.

Several logs or a folder: one summary table instead (per log and wheel:
cycles, estimated, mean slip, the soil at the end, verdict, error: for a
log with no cycle estimated, what looked wrong with its data), the logs
replayed in parallel processes (--jobs) or on a Dask cluster (--scheduler,
pip install 'slipest[dask]'). -o naming one of the logs read (a folder's
too) is refused; the command's own table from an earlier run, found in a
folder, is left out (and written over). Exit status: 1 when a log failed
(its row says why), no log had a cycle estimated, or a single log had no
cycle estimated (its summary says why), 2 on a bad single log or option.

Examples::

    slipest replay drive.blf --truth --plot drive.png
    slipest replay drive_bag/ --joint wheel_leg_joint --imu-topic /hub/imu --slip-topic /slip
    slipest replay drives/ -o table.csv --jobs 8
"""

from __future__ import annotations

import argparse
import math
import os
import sys

from slipest.cli import estimate_output
from slipest.cli.command import add_command, job_count, leg_count
from slipest.cli.estimator_args import add_estimator_arguments, soil_from_args
from slipest.cli.output_paths import output_problem, table_inputs
from slipest.online import ESTIMATE_FIELDS
from slipest.stuck import STUCK_TIME

#: Output columns, in order (a CAN log's rows have ``wheel`` first).
COLUMNS = ESTIMATE_FIELDS


def joint_gap_seconds(text: str) -> float:
    """``--max-joint-gap``: a finite number of seconds > 0 (argparse type)."""
    try:
        s = float(text)
    except ValueError:
        s = math.nan
    if not (math.isfinite(s) and s > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a joint-state gap (a number of seconds > 0)")
    return s


def add_bag_arguments(p) -> None:
    """The options saying where a ROS 2 bag's samples are (:class:`~slipest.io.rosbag.BagTopics`), shared by the
    commands that read bags (``replay``, ``diagnose``): :func:`bag_topics_from_args` reads them back."""
    r = p.add_argument_group("ROS 2 bags")
    r.add_argument("--imu-topic", default="/imu", help="sensor_msgs/msg/Imu topic (default /imu)")
    r.add_argument("--joint-states-topic", default="/joint_states",
                   help="sensor_msgs/msg/JointState topic (default /joint_states)")
    r.add_argument("--joint", default=None, help="the wheel-leg joint's name (default: the only joint there)")
    r.add_argument("--slip-topic", default=None, help="std_msgs/msg/Float64 reference slip topic (default: none)")
    r.add_argument("--bag-time", action="store_true",
                   help="time the samples by the bag's receive times, not the header stamps")
    r.add_argument("--max-joint-gap", type=joint_gap_seconds, default=None, metavar="S",
                   help="longest joint-state step interpolated over [s] (default: 5 median steps)")


def bag_topics_from_args(args):
    """The :class:`~slipest.io.rosbag.BagTopics` of :func:`add_bag_arguments`' options."""
    from slipest.io.rosbag import BagTopics

    return BagTopics(imu=args.imu_topic, joint_states=args.joint_states_topic, joint=args.joint, slip=args.slip_topic,
                     bag_time=args.bag_time, max_joint_gap=args.max_joint_gap)


def add_parser(sub) -> None:
    from slipest.offline.logs import KINDS

    p = add_command(sub, "replay", "estimate slip (and soil) per leg cycle from recorded logs (slipest CSV, "
                    "CAN logs, ROS 2 bags)", __doc__)
    p.add_argument("logs", nargs="+", metavar="LOG",
                   help="log file, bag or folder ('-': a slipest CSV on stdin); several, or a folder: a table")
    p.add_argument("-o", "--output", default="-", help="output file ('-' or omitted: stdout)")
    p.add_argument("--format", choices=("csv", "jsonl"), default="csv", help="output format (default csv)")
    p.add_argument("--log-format", choices=("auto",) + KINDS, default="auto",
                   help="what the log is (default: from its name; a .csv by its header)")
    p.add_argument("--legs", type=leg_count, default=None, help="legs of the wheel-leg (default: the log's nL, else 4)")
    add_estimator_arguments(p)
    p.add_argument("--truth", action="store_true",
                   help="summarise the errors against the log's reference slip (RMSE, bias, 95%% coverage)")
    p.add_argument("--use-reference", action="store_true",
                   help="let the estimator learn the soil from the log's reference slip (default: ignored)")
    p.add_argument("--skip-bad", action="store_true",
                   help="count and skip malformed CSV rows (default: stop with an error naming the line)")
    p.add_argument("--plot", metavar="FILE.png",
                   help="draw slip (95%% band, reference), dphi and the soil over time, flagged cycles marked "
                   "(pip install 'slipest[plot]')")
    p.add_argument("--chunk-rows", type=int, default=65536, help=argparse.SUPPRESS)
    c = p.add_argument_group("CAN logs")
    c.add_argument("--wheel", type=int, action="append", default=None, metavar="W",
                   help="estimate only this wheel (repeat for several; default: every wheel in the log)")
    c.add_argument("--stuck-time", type=float, default=STUCK_TIME, metavar="S",
                   help=f"az repeated bit-identically for S seconds is a stuck sensor (default {STUCK_TIME:g}, "
                   "as the live commands)")
    c.add_argument("--stuck-samples", type=int, default=None, metavar="N",
                   help="a fixed run length in samples instead of --stuck-time (0: never)")
    add_bag_arguments(p)
    m = p.add_argument_group("many logs")
    m.add_argument("--jobs", type=job_count, default=None, metavar="N",
                   help="worker processes, >= 1 (default: one per core)")
    m.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on this Dask cluster (e.g. tcp://10.0.0.5:8786; pip install 'slipest[dask]')")
    m.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def options_from_args(args):
    from slipest.offline.replay import ReplayOptions

    bag = bag_topics_from_args(args)
    return ReplayOptions(legs=args.legs, method=args.method, soil=soil_from_args(args) or None, model=args.model,
                         rover=args.rover,
                         use_reference=args.use_reference, truth=args.truth, carry_reference=bool(args.plot),
                         skip_bad=args.skip_bad, log_format=args.log_format,
                         wheels=tuple(args.wheel) if args.wheel else None, stuck_samples=args.stuck_samples,
                         stuck_time=args.stuck_time, bag=bag, chunk_rows=args.chunk_rows)


class _Writer:
    """Estimate rows as CSV or JSON lines; ``wheel_column``: a leading ``wheel`` (CAN logs)."""

    def __init__(self, stream, fmt: str, wheel_column: bool):
        self.stream = stream
        self.fmt = fmt
        self.prefix = ("wheel",) if wheel_column else ()
        if fmt == "csv":
            stream.write(estimate_output.header(self.prefix) + "\n")

    def write(self, wheel, e) -> None:
        if self.fmt == "csv":
            self.stream.write(estimate_output.row(e, (wheel,) if self.prefix else ()) + "\n")
        else:
            self.stream.write(estimate_output.json_row(e, {"wheel": wheel} if self.prefix else None) + "\n")


def _fail(msg: str) -> int:
    print(f"slipest replay: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from slipest.io.rosbag import is_bag
    from slipest.offline.logs import expand_logs

    problem = output_problem(args.output, args.logs) or output_problem(args.plot, args.logs, "--plot")
    if problem:
        return _fail(problem)
    if args.logs == ["-"]:
        return _replay_one(args, sys.stdin.buffer, "-")
    (first, *more) = args.logs
    if not more and (not os.path.isdir(first) or is_bag(first)):
        return _replay_one(args, first, first)
    return _replay_many(args, expand_logs(args.logs))


def _replay_one(args, source, name: str) -> int:
    from slipest.extras import MissingExtra
    from slipest.io.log_csv import LogFormatError
    from slipest.offline.replay import Replay

    try:
        options = options_from_args(args)
        if args.plot:
            from slipest.offline import replay_plot as plot  # before reading: a missing matplotlib fails at once
        replay = Replay(source, options, name=name)
    except FileNotFoundError:
        return _fail(f"{name}: no such file")
    except MissingExtra as exc:
        return _fail(str(exc))
    except OSError as exc:
        return _fail(f"{name}: {exc.strerror or exc}")
    except (ValueError, TypeError) as exc:  # LogFormatError, InverseModelError (naming the file), option errors
        return _fail(str(exc))
    series: dict = {}

    def on_estimate(wheel, e):
        writer.write(wheel, e)
        if args.plot:
            series.setdefault(wheel, []).append(e)

    out = None
    try:
        out = sys.stdout if args.output == "-" else open(args.output, "w", encoding="utf-8", newline="\n")
        writer = _Writer(out, args.format, replay.kind == "can")
        result = replay.run(on_estimate)
        out.flush()
    except LogFormatError as exc:
        return _fail(str(exc))
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            raise
        return _fail(f"{exc.filename or args.output}: {exc.strerror or exc}")
    finally:
        replay.close()
        if out is not None and out is not sys.stdout:
            out.close()
    print("\n".join(result.summary_lines()), file=sys.stderr)
    if args.plot:
        try:
            print(f"wrote {plot.plot_replay(args.plot, series, title=name)}", file=sys.stderr)
        except (ValueError, OSError) as exc:
            return _fail(f"--plot {args.plot}: {exc}")
    return 0 if result.estimated else 1


def _replay_many(args, logs: list[str]) -> int:
    from slipest.extras import MissingExtra
    from slipest.offline.many import run_many, save_table
    from slipest.offline.replay import TABLE_COLUMNS, replay_rows

    if args.plot:
        return _fail("--plot draws one log: give one")
    try:  # before any work: -o naming a log (in a folder too) is refused, our own earlier table left out
        logs, left_out = table_inputs(logs, args.output, TABLE_COLUMNS)
    except ValueError as exc:
        return _fail(str(exc))
    for old in left_out:
        print(f"replay: {old} left out: it is this command's table from an earlier run (written over now)",
              file=sys.stderr)
    if not logs:
        return _fail(f"no log found in {', '.join(args.logs)}")
    try:
        rows = run_many(replay_rows, logs, options_from_args(args), columns=TABLE_COLUMNS, jobs=args.jobs,
                        scheduler=args.scheduler, progress=not args.no_progress, desc="replay")
    except (MissingExtra, OSError, ValueError) as exc:
        return _fail(str(exc))
    save_table(rows, TABLE_COLUMNS, args.output, args.format)
    failed = sorted({r["log"] for r in rows if r["verdict"] == "error"})
    estimated = sum(r["verdict"] == "ok" for r in rows)
    print(f"replay: {len(logs)} logs, {len(rows)} rows: {estimated} with estimates, "
          f"{len(failed)} log(s) failed" + (f" (first: {failed[0]})" if failed else "")
          + ("" if args.output == "-" else f"; table in {args.output}"), file=sys.stderr)
    if not estimated and not failed:
        print("replay: no leg cycle was estimated in any log (the error column says why)", file=sys.stderr)
    return 1 if failed or not estimated else 0
