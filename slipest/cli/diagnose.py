"""``slipest diagnose``: find which sim-to-real effect explains the gap between logs and the model.

Reads one or more logs (the CSV format of :mod:`slipest.io.log_csv`, with the
``slip`` column: slip imposed and logged, soil unknown; a live recording has
it only when the device sent reference slips, else the error says the
reference slip is missing; or ROS 2 bags, read as replay reads them, the
slip from --slip-topic), cuts them into leg cycles and runs
:func:`slipest.diagnosis.run.diagnose`: fits the nominal
model's soil, localises the remaining gap, refits soil + each catalog effect
on training cycles, compares held-out gaps and names the effect, ``none`` or
``unexplained``. The known hardware (``nL``, ``MH``, ``mF``, ``lS``) comes
from the logs' metadata when present (options override); the soil, ``kappa``
and any effect are never read from the metadata. The gap is the RMS
difference of phase-binned az waveforms in excess of the noise floor [g]
(see slipest.diagnosis.rank).

Bad data is treated as replay treats it: a reference slip outside [0, 1)
(in percent, negative) is refused before any work, naming the file; leg
cycles replay flags (a logger pause: gap, two logs appended: reverse, ...)
are left out and isolated az glitches (any size) left out of their cycles,
both counted on the report's 'data:' line (JSON: cycles_left_out,
samples_repaired). --json, -o and --plots (a directory that exists or can
be created) are checked before the diagnosis (exit 2).

Many drives: --per-log diagnoses each log on its own (a folder: its *.csv
logs, recursively, and its ROS 2 bags with --slip-topic) and writes one
table, a row per log (cycles, cycles left out, glitch samples left out,
mean slip, fitted soil, gaps, verdict, error), in parallel processes
(--jobs) or on a Dask cluster (--scheduler, pip install 'slipest[dask]'); exit status 1 when
a log failed (its row says why). --plots needs matplotlib (pip install
'slipest[plot]').
"""

from __future__ import annotations

import argparse
import json
import sys

from slipest.cli.command import add_command, job_count, leg_count
from slipest.cli.output_paths import output_problem, table_inputs
from slipest.cli.replay import add_bag_arguments, bag_topics_from_args


def add_parser(sub) -> None:
    p = add_command(sub, "diagnose", "explain the gap between real logs and the model with the sim-to-real effect "
                    "catalog", __doc__)
    p.add_argument("logs", nargs="+", metavar="LOG",
                   help="log files (t, az, theta, slip) or ROS 2 bags (--slip-topic), or folders with --per-log")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON (keys verdict, gap_nominal, where, ranking, ...)")
    p.add_argument("--plots", metavar="DIR", help="write PNG plots (waveforms, gap by angle, ranking) into DIR "
                   "(pip install 'slipest[plot]')")
    p.add_argument("--effects", metavar="NAME,...", help="catalog effects to try (default: all)")
    p.add_argument("--rank-all", action="store_true",
                   help="fit every effect even when the nominal model already explains the data")
    p.add_argument("--quick", action="store_true", help="half the optimiser budget (faster, less reliable)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the optimiser (default 0)")
    p.add_argument("--legs", type=leg_count, default=None, help="number of legs (default: log metadata nL, else 4)")
    p.add_argument("--MH", type=float, default=None, help="hub mass [kg] (default: metadata, else 1.0)")
    p.add_argument("--mF", type=float, default=None, help="foot mass [kg] (default: metadata, else 0.2)")
    p.add_argument("--lS", type=float, default=None, help="spoke length [m] (default: metadata, else 0.1763)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    add_bag_arguments(p)
    m = p.add_argument_group("many logs")
    m.add_argument("--per-log", action="store_true", help="diagnose each log on its own and write one table")
    m.add_argument("-o", "--output", default="-", help="the --per-log table (default: stdout)")
    m.add_argument("--format", choices=("csv", "jsonl"), default="csv", help="the --per-log table's format")
    m.add_argument("--jobs", type=job_count, default=None, metavar="N",
                   help="worker processes, >= 1 (default: one per core)")
    m.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on this Dask cluster (e.g. tcp://10.0.0.5:8786; pip install 'slipest[dask]')")
    p.set_defaults(func=run)


def plots_dir_problem(directory, inputs=()) -> str | None:
    """Why ``--plots DIRECTORY`` cannot take the plots, or None (also for None: no plots). It must be a
    directory that exists or can be created (tried here, before the diagnosis's minutes, and what was created
    removed again: the plots create it when written; a file of that name, or a place where no directory can be
    made, is refused up front), and none of its plots may be one of the files read
    (:func:`~slipest.cli.output_paths.output_problem`)."""
    import os

    if directory is None:
        return None
    if os.path.exists(directory) and not os.path.isdir(directory):
        return f"--plots {directory} is not a directory: name a directory (it is created if missing)"
    missing, head = [], os.path.abspath(directory)
    while not os.path.exists(head) and head != os.path.dirname(head):
        missing.append(head)
        head = os.path.dirname(head)
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError as exc:
        return f"--plots {directory}: cannot create that directory ({exc.strerror or exc})"
    finally:
        for made in missing:  # deepest first: only the directories this check created
            try:
                os.rmdir(made)
            except OSError:
                pass
    if missing:
        return None
    from slipest.diagnosis.plots import PLOT_FILES

    for name in PLOT_FILES:
        problem = output_problem(os.path.join(directory, name), inputs, "--plots")
        if problem:
            return problem
    if not os.access(directory, os.W_OK | os.X_OK):
        return f"--plots {directory}: directory not writable"
    return None


def _fail(msg: str):
    raise SystemExit(f"slipest diagnose: {msg}")


def options_from_args(args):
    from slipest.offline.diagnose import DiagnoseOptions

    effects = None
    if args.effects:
        effects = tuple(e.strip() for e in args.effects.split(",") if e.strip())
    return DiagnoseOptions(effects=effects, rank_all=args.rank_all, quick=args.quick, seed=args.seed, legs=args.legs,
                           MH=args.MH, mF=args.mF, lS=args.lS, bag=bag_topics_from_args(args))


def _progress_bar(args):
    """A tqdm bar and the diagnosis's progress callback for it (None, None with --no-progress)."""
    if args.no_progress:
        return None, None
    from tqdm import tqdm

    bar = tqdm(total=1, desc="diagnose", unit="gen", file=sys.stderr, leave=False, mininterval=0.5)
    last = {"label": None}

    def progress(done, total, label):
        bar.total = total
        if label != last["label"]:
            last["label"] = label
            bar.set_description(f"fitting {label}", refresh=False)
        bar.update(done - bar.n)

    return bar, progress


def run(args: argparse.Namespace) -> int:
    from slipest.extras import MissingExtra

    problem = (output_problem(args.json, args.logs, "--json")
               or output_problem(None if args.output == "-" else args.output, args.logs)
               or (None if args.per_log else plots_dir_problem(args.plots, args.logs)))
    if problem:  # before the diagnosis's minutes, not after; a usage error (exit 2), as replay's
        print(f"slipest diagnose: {problem}", file=sys.stderr)
        return 2
    options = options_from_args(args)
    try:
        options.checked_effects()
        if args.plots:
            from slipest.diagnosis import plots  # before the long fit: a missing matplotlib fails at once
    except (ValueError, MissingExtra) as exc:
        _fail(str(exc))
    if args.per_log:
        return _per_log(args, options)
    from slipest.diagnosis import report
    from slipest.offline.diagnose import diagnose_logs

    bar, progress = _progress_bar(args)
    try:
        diag = diagnose_logs(args.logs, options, progress=progress)
    except (ValueError, OSError, MissingExtra) as exc:  # LogFormatError is a ValueError; all name the file or extra
        _fail(str(exc))
    finally:
        if bar is not None:
            bar.close()
    print(report.summary(diag))
    if args.json:
        doc = report.to_dict(diag, logs=args.logs)
        with open(args.json, "w") as fh:
            json.dump(doc, fh, indent=2)
        print(f"wrote {args.json}", file=sys.stderr)
    if args.plots:
        for path in plots.write_all(diag, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0


def _per_log(args, options) -> int:
    from slipest.extras import MissingExtra
    from slipest.offline.diagnose import DIAGNOSE_COLUMNS, diagnose_rows
    from slipest.offline.logs import expand_logs
    from slipest.offline.many import run_many, save_table

    if args.json or args.plots:
        _fail("--json and --plots report one diagnosis: not with --per-log")
    # a folder's bags only when --slip-topic says where their slip is (without it, a bag cannot be diagnosed)
    logs = expand_logs(args.logs, kinds=("slipest", "ros2") if args.slip_topic else ("slipest",))
    if not logs:
        _fail(f"no log found in {', '.join(args.logs)}")
    try:  # before any work: -o naming a log is refused (exit 2, as run's), our own earlier table left out
        logs, left_out = table_inputs(logs, args.output, DIAGNOSE_COLUMNS)
    except ValueError as exc:
        print(f"slipest diagnose: {exc}", file=sys.stderr)
        return 2
    for old in left_out:
        print(f"diagnose: {old} left out: it is this command's table from an earlier run (written over now)",
              file=sys.stderr)
    try:
        rows = run_many(diagnose_rows, logs, options, columns=DIAGNOSE_COLUMNS, jobs=args.jobs,
                        scheduler=args.scheduler, progress=not args.no_progress, desc="diagnose")
    except (MissingExtra, OSError, ValueError) as exc:
        _fail(str(exc))
    save_table(rows, DIAGNOSE_COLUMNS, args.output, args.format)
    failed = [r["log"] for r in rows if r["verdict"] == "error"]
    verdicts = {}
    for r in rows:
        verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
    print(f"diagnose: {len(rows)} logs: " + ", ".join(f"{v} {n}" for v, n in sorted(verdicts.items()))
          + ("" if args.output == "-" else f"; table in {args.output}"), file=sys.stderr)
    return 1 if failed else 0
