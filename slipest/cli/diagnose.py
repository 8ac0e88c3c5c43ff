"""``slipest diagnose``: find which sim-to-real effect explains the gap between logs and the model.

Reads one or more logs (the CSV format of :mod:`slipest.io.log_csv`, with the
``slip`` column: slip imposed and logged, soil unknown), cuts them into leg
cycles and runs :func:`slipest.diagnosis.run.diagnose`: fits the nominal
model's soil, localises the remaining gap, refits soil + each catalog effect
on training cycles, compares held-out gaps and names the effect, ``none`` or
``unexplained``. The known hardware (``nL``, ``MH``, ``mF``, ``lS``) comes
from the logs' metadata when present (options override); the soil, ``kappa``
and any effect are never read from the metadata. The gap is the RMS
difference of phase-binned az waveforms in excess of the noise floor [g]
(see slipest.diagnosis.rank).
"""

from __future__ import annotations

import argparse
import json
import sys

from slipest.cli.command import add_command


def add_parser(sub) -> None:
    p = add_command(sub, "diagnose", "explain the gap between real logs and the model with the sim-to-real effect "
                    "catalog", __doc__)
    p.add_argument("logs", nargs="+", metavar="LOG.csv", help="log files (t, az, theta, slip)")
    p.add_argument("--json", metavar="FILE", help="write the report as JSON (keys verdict, gap_nominal, where, ranking, ...)")
    p.add_argument("--plots", metavar="DIR", help="write PNG plots (waveforms, gap by angle, ranking) into DIR")
    p.add_argument("--effects", metavar="NAME,...", help="catalog effects to try (default: all)")
    p.add_argument("--rank-all", action="store_true",
                   help="fit every effect even when the nominal model already explains the data")
    p.add_argument("--quick", action="store_true", help="half the optimiser budget (faster, less reliable)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the optimiser (default 0)")
    p.add_argument("--legs", type=int, default=None, help="number of legs (default: log metadata nL, else 4)")
    p.add_argument("--MH", type=float, default=None, help="hub mass [kg] (default: metadata, else 1.0)")
    p.add_argument("--mF", type=float, default=None, help="foot mass [kg] (default: metadata, else 0.2)")
    p.add_argument("--lS", type=float, default=None, help="spoke length [m] (default: metadata, else 0.1763)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def _geometry(args, metas):
    from slipest.diagnosis.fit import Geometry

    default = Geometry()

    def pick(opt, key, conv, fallback):
        if getattr(args, opt) is not None:
            return conv(getattr(args, opt))
        values = {conv(m[key]) for m in metas if key in m}
        if len(values) > 1:
            raise SystemExit(f"slipest diagnose: the logs disagree on {key} ({sorted(values)}); give --{opt}")
        return values.pop() if values else fallback

    return Geometry(
        MH=pick("MH", "MH", float, default.MH),
        mF=pick("mF", "mF", float, default.mF),
        lS=pick("lS", "lS", float, default.lS),
        nL=pick("legs", "nL", int, default.nL),
        g=default.g,
    )


def run(args: argparse.Namespace) -> int:
    from slipest.diagnosis import report
    from slipest.diagnosis.cycles import concat, cut_cycles
    from slipest.diagnosis.fit import FitBudget
    from slipest.diagnosis.predict import Grid
    from slipest.diagnosis.run import diagnose
    from slipest.io.log_csv import LogFormatError, read_log
    from slipest.model.effects import ORDER

    effects = None
    if args.effects:
        effects = [e.strip() for e in args.effects.split(",") if e.strip()]
        bad = [e for e in effects if e not in ORDER]
        if bad:
            raise SystemExit(f"slipest diagnose: unknown effect(s) {', '.join(bad)}; known: {', '.join(ORDER)}")
    logs = []
    for path in args.logs:
        try:
            logs.append(read_log(path))
        except LogFormatError as exc:
            raise SystemExit(f"slipest diagnose: {exc}") from None
        except OSError as exc:
            raise SystemExit(f"slipest diagnose: cannot read {path}: {exc.strerror}") from None
    geometry = _geometry(args, [log.metadata for log in logs])
    grid = Grid(geometry.nL)
    sets = []
    for k, (path, log) in enumerate(zip(args.logs, logs)):
        if log.slip is None:
            raise SystemExit(f"slipest diagnose: {path} has no 'slip' column (the diagnosis needs the imposed slip)")
        try:
            sets.append(cut_cycles(log.t, log.az, log.theta, log.slip, geometry.nL, grid=grid, log_index=k))
        except ValueError as exc:
            raise SystemExit(f"slipest diagnose: {path}: {exc}") from None
    cycles = concat(sets)
    budget = FitBudget().scaled(0.5) if args.quick else FitBudget()

    bar = None
    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=1, desc="diagnose", unit="gen", file=sys.stderr, leave=False, mininterval=0.5)
        last = {"label": None}

        def progress(done, total, label):
            bar.total = total
            if label != last["label"]:
                last["label"] = label
                bar.set_description(f"fitting {label}", refresh=False)
            bar.update(done - bar.n)

    try:
        diag = diagnose(cycles, geometry, effects, seed=args.seed, budget=budget, rank_all=args.rank_all,
                        progress=progress)
    except ValueError as exc:
        raise SystemExit(f"slipest diagnose: {exc}") from None
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
        from slipest.diagnosis import plots

        for path in plots.write_all(diag, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0
