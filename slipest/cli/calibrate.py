"""``slipest calibrate``: calibrate the estimator to a rover from its testbed logs; write the rover file.

Reads one or more logs of the rover with the slip of every leg cycle in
their 'slip' column (testbed runs, runs with visual odometry), each on its
own soil (unknown), and fits what they say about this rover: the
diagnosis's kappa and the catalog effect it names with its parameters, the
IMU noise, and a correction of the estimator's model (a feature
discrepancy over slip and soil from the simulator with the named effect,
or a disturbance locked to the leg phase learnt from the logs' waveforms
and removed from the samples; plus a correction in slip learnt from the
logs where that helps logs it was not fitted on), with the extra
uncertainty of what the correction does not explain.
It refits the thesis's Eq. 5.15 on the same logs. Everything goes into one
file (JSON) that the estimator takes with --rover:

    slipest calibrate testbed_a.csv testbed_b.csv --legs 4 -o rover.json
    slipest replay drive.csv --rover rover.json
    slipest serial /dev/ttyUSB0 --rover rover.json
    slipest replay drive.csv --rover rover.json --method eq515 --kS 900 --dphi 0.2

``-o`` is checked before any work: a file read, a directory, a place this
user cannot write are refused; an existing rover file is replaced (a
recalibration), any other existing file only with ``--overwrite``.

Progress goes to stderr, the report to stdout: the effects named, the
estimates of the testbed logs before and after (blind: soil unknown,
reference ignored), the held-out feature misfit, what is left unexplained.
Two 40-cycle logs take about 30-70 s on 2 quiet cores (the diagnosis and the
simulated batch are most of it; --thorough doubles the diagnosis budget). docs/calibration.md: the design.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

from slipest.cli.command import add_command, leg_count
from slipest.cli.output_paths import output_problem


def add_parser(sub) -> None:
    p = add_command(sub, "calibrate", "calibrate the estimator to a rover from testbed logs with known slip "
                    "(writes the rover file for --rover)", __doc__)
    p.add_argument("logs", nargs="+", metavar="LOG.csv", help="testbed logs (slipest CSV with a 'slip' column), "
                   "each on its own soil")
    p.add_argument("-o", "--output", required=True, metavar="ROVER.json",
                   help="the rover file to write (an existing one is replaced; any other file only with --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace -o whatever it holds")
    p.add_argument("--legs", type=leg_count, default=None, help="legs of the wheel-leg (default: the logs' nL, else 4)")
    p.add_argument("--MH", type=float, default=None, help="hub mass [kg] (default: the logs' metadata, else 1.0)")
    p.add_argument("--mF", type=float, default=None, help="foot mass [kg] (default: the logs' metadata, else 0.2)")
    p.add_argument("--lS", type=float, default=None, help="spoke length [m] (default: the logs' metadata, else 0.1763)")
    p.add_argument("--model", metavar="FILE", default=None,
                   help="inverse model file (.npz) to correct (default: the shipped one)")
    p.add_argument("--effects", metavar="NAME,...", help="catalog effects the diagnosis tries (default: all)")
    p.add_argument("--no-diagnosis", action="store_true",
                   help="skip the diagnosis: only the correction learnt from the logs themselves")
    p.add_argument("--thorough", action="store_true", help="the diagnosis's full optimiser budget (about twice as long)")
    p.add_argument("--batch", type=int, default=None, metavar="N",
                   help="simulated leg cycles per candidate effect (default 1500)")
    p.add_argument("--seed", type=int, default=0, help="seed of the optimiser and the simulated batches (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def _fail(msg: str):
    raise SystemExit(f"slipest calibrate: {msg}")


def _progress_bar(args):
    """A tqdm bar per stage and the calibration's progress callback for it (None, None with --no-progress)."""
    if args.no_progress:
        return None, None
    from tqdm import tqdm

    state = {"bar": None, "stage": None}

    def progress(done, total, label):
        stage = label.split(":")[0]
        if stage != state["stage"] or state["bar"] is None:
            if state["bar"] is not None:
                state["bar"].close()
            state["stage"] = stage
            state["bar"] = tqdm(total=max(total, 1), desc=stage, file=sys.stderr, leave=False, mininterval=0.5)
        bar = state["bar"]
        bar.total = max(total, 1)
        bar.set_description(label[:60], refresh=False)
        bar.update(max(0, done - bar.n))

    class _Closer:
        def close(self):
            if state["bar"] is not None:
                state["bar"].close()

    return _Closer(), progress


def run(args: argparse.Namespace) -> int:
    from slipest.offline.calibrate import calibrate_logs, write_rover
    from slipest.rover.calibrate import CalibrateOptions
    from slipest.rover.report import report_lines

    problem = output_problem(args.output, args.logs, makes_dirs=True)  # (write_rover creates them)
    if problem:  # before the calibration's minutes, not after
        _fail(problem)
    from slipest.rover.file import is_rover_file

    if os.path.exists(args.output) and not (args.overwrite or is_rover_file(args.output)):
        _fail(f"{args.output} exists and is not a rover file: use --overwrite to replace it")
    effects = tuple(e.strip() for e in args.effects.split(",") if e.strip()) if args.effects else None
    if args.batch is not None and args.batch < 50:
        _fail(f"--batch {args.batch}: at least 50 simulated cycles are needed to fit a discrepancy")
    options = CalibrateOptions(diagnose=not args.no_diagnosis, quick=not args.thorough, effects=effects,
                               batch=args.batch or CalibrateOptions.batch, seed=args.seed)
    closer, progress = _progress_bar(args)
    try:
        cal = calibrate_logs(args.logs, options, legs=args.legs, MH=args.MH, mF=args.mF, lS=args.lS,
                             model=args.model, progress=progress)
    except (ValueError, OSError) as exc:  # LogFormatError and InverseModelError are ValueErrors; all name the file
        _fail(str(exc))
    finally:
        if closer is not None:
            closer.close()
    print("\n".join(report_lines(cal.report)))
    command = "slipest calibrate " + " ".join(shlex.quote(str(a)) for a in args.logs) + f" -o {shlex.quote(args.output)}"
    try:
        path = write_rover(cal, args.output, created_by=command, model=args.model)
    except OSError as exc:
        _fail(f"cannot write {args.output}: {exc}")
    print(f"wrote {path}: use it with --rover {path}", file=sys.stderr)
    return 0
