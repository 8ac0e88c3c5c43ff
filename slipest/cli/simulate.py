"""``slipest simulate``: write a simulated IMU + encoder log (CSV) from options or a scenario file.

Simulate leg cycles of a wheel-leg with the stick-slip model and write the
IMU/encoder stream as a log CSV (the format `slipest replay` reads). Either
give one slip, soil and leg speed with the options, or a TOML scenario with
segments of different slip, soil and leg speed.
"""

from __future__ import annotations

import argparse
import os
import sys
import tomllib

from slipest.cli.command import add_command, leg_count
from slipest.cli.output_paths import output_problem
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario


def add_parser(sub) -> None:
    p = add_command(sub, "simulate", "write a simulated log (t, az, theta, slip) from the stick-slip model", __doc__)
    add_scenario_arguments(p)
    p.add_argument("-o", "--output", default="-", help="output CSV file ('-' or omitted: stdout); a simulated log "
                   "there is replaced, any other file only with --overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace -o whatever it holds")
    p.set_defaults(func=run)


#: The ``source`` metadata of a simulated log: what ``-o`` may replace without ``--overwrite``.
SOURCE = "slipest simulate"


def _simulated(path: str) -> bool:
    """Whether the file ``path`` is a log ``slipest simulate`` wrote (its ``# source=`` line says so)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return f"# source={SOURCE}".encode() in head.splitlines()


def add_scenario_arguments(
    p: argparse.ArgumentParser,
    noise_help: str = "IMU noise standard deviation [g] (default 0)",
    seed_help: str = "random seed of the noise",
) -> None:
    """The scenario options, read back by :func:`build_scenario` (shared with the virtual device)."""
    g = p.add_argument_group("scenario")
    g.add_argument("--scenario", metavar="TOML", help="scenario file (segments of slip and soil; see README)")
    g.add_argument("--slip", type=float, default=0.25, help="slip ratio i, 0..<1 (default 0.25)")
    g.add_argument("--kS", type=float, default=1000.0, help="soil/leg stiffness [N/m] (default 1000)")
    g.add_argument("--phiS", type=float, default=0.52, help="static friction angle [rad] (default 0.52)")
    g.add_argument("--phiD", type=float, default=0.35, help="dynamic friction angle [rad] (default 0.35)")
    g.add_argument("--kappa", type=float, default=0.3, help="lateral leg stiffness ratio (default 0.3; 0 = literal thesis)")
    g.add_argument("--legs", type=leg_count, default=4, help="number of legs of the wheel-leg (default 4)")
    g.add_argument("--omega", type=float, default=None,
                   help="leg speed [rad/s] (default 0.63; a scenario file sets it per segment)")
    g.add_argument("--cycles", type=int, default=10, help="number of leg cycles (default 10)")
    g.add_argument("--rate", type=float, default=None, help="IMU sample rate [Hz] (default 1000)")
    g.add_argument("--noise", type=float, default=None, help=noise_help)
    g.add_argument("--seed", type=int, default=None, help=seed_help)
    g.add_argument("--dt", type=float, default=None, help="model integration step [s] (default 1e-4)")
    g.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME:k=v,...",
        help="switch on a sim-to-real effect (repeatable), e.g. imu_lowpass:cutoff=40",
    )


def build_scenario(args: argparse.Namespace) -> Scenario:
    """The scenario the options describe (a TOML file's imu settings can be overridden by options)."""
    effects = []
    if args.effect:
        from slipest.model.effects import parse_effect_arg

        effects = [parse_effect_arg(text) for text in args.effect]
    if args.scenario:
        try:
            with open(args.scenario, "rb") as fh:
                doc = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise SystemExit(f"slipest simulate: {args.scenario}: not valid TOML: {exc}") from None
        except OSError as exc:
            raise SystemExit(f"slipest simulate: cannot read scenario {args.scenario}: {exc.strerror}") from None
        imu = doc.setdefault("imu", {})
        for opt, key in (("rate", "rate"), ("noise", "noise"), ("seed", "seed"), ("dt", "dt")):
            if getattr(args, opt) is not None:
                imu[key] = getattr(args, opt)
        if effects:
            doc["effect"] = list(doc.get("effect", [])) + effects
        if args.omega is not None:
            raise SystemExit("slipest simulate: --omega goes with the options; a scenario file sets the leg speed "
                             "in [model] or per [[segment]] (omega = ...)")
        try:
            return Scenario.from_dict(doc)
        except (ValueError, TypeError) as exc:
            raise SystemExit(f"slipest simulate: {args.scenario}: {exc}") from None
    params = StickSlipParams(
        slip=args.slip, kS=args.kS, phiS=args.phiS, phiD=args.phiD, kappa=args.kappa, nL=args.legs,
        **({} if args.omega is None else {"omega": args.omega}),
    )
    imu = {
        "rate": 1000.0 if args.rate is None else args.rate,
        "noise_g": 0.0 if args.noise is None else args.noise,
        "seed": args.seed,
    }
    if args.dt is not None:
        imu["dt"] = args.dt
    if args.cycles < 1:
        raise ValueError(f"--cycles={args.cycles} must be >= 1")
    return Scenario(cycles=(params,) * args.cycles, effects=tuple(effects), **imu)


def run(args: argparse.Namespace) -> int:
    from slipest.io.log_csv import LogWriter
    from slipest.model.stance import ModelFailure
    from slipest.model.stream import iter_stream

    try:
        scenario = build_scenario(args)
    except ValueError as exc:
        raise SystemExit(f"slipest simulate: {exc}") from None
    target = sys.stdout if args.output == "-" else args.output
    problem = output_problem(None if target is sys.stdout else target)
    if problem:
        raise SystemExit(f"slipest simulate: {problem}")
    # a simulated log can be made again: replacing one is what a user expects; a recorded log is not replaced
    if target is not sys.stdout and os.path.exists(target) and not (args.overwrite or _simulated(target)):
        raise SystemExit(f"slipest simulate: {target} exists and is not a simulated log: use --overwrite to "
                         "replace it")
    try:
        writer = LogWriter(target, ("t", "az", "theta", "slip"), metadata={**scenario.metadata(), "source": SOURCE},
                           overwrite=True)
    except OSError as exc:
        raise SystemExit(f"slipest simulate: cannot write {args.output}: {exc.strerror or exc}") from None
    with writer:
        try:
            for chunk in iter_stream(scenario):
                writer.write(chunk.t, chunk.az, chunk.theta, chunk.slip)
                writer.flush()
        except ModelFailure as exc:
            failure = exc
        else:
            failure = None
    if failure is not None:
        if target is not sys.stdout:
            os.remove(target)  # a partial simulated log would pass for a whole one
        raise SystemExit(f"slipest simulate: {failure}")
    if args.output != "-":
        print(f"wrote {len(scenario.cycles)} leg cycles to {args.output}", file=sys.stderr)
    return 0
