"""``slipest simulate``: write a simulated IMU + encoder log (CSV) from options or a scenario file.

Simulate leg cycles of a wheel-leg with the stick-slip model and write the
IMU/encoder stream as a log CSV (the format `slipest replay` reads). Either
give one slip, soil and leg speed with the options, or a TOML scenario with
segments of different slip, soil and leg speed.

The log's header records the scenario: the IMU settings and every model
parameter the run sets (those left at their default are not listed). A
file (-o) is written whole or not at all: the run goes to a temporary file
beside it, which replaces the file only once the last cycle is written; on
an error or an interruption (Ctrl-C, SIGTERM) the previous file is left as
it was. A leg cycle is simulated at once, so a cycle may last at most
6,000,000 model steps (10 minutes at the default dt=1e-4 s), and it must last
at least 8 IMU samples. A run holds at most 1,000,000 leg cycles and
1,000,000,000 samples (a log of about 40 GB; 11.6 days at 1 kHz).
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import stat
import sys
import tempfile
import tomllib

import numpy as np

from slipest.cli.command import add_command, interrupt_on_sigterm, leg_count, seed_number
from slipest.cli.output_paths import output_problem
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario


def add_parser(sub) -> None:
    p = add_command(sub, "simulate", "write a simulated log (t, az, theta, slip) from the stick-slip model", __doc__)
    add_scenario_arguments(p)
    p.add_argument("-o", "--output", default="-", help="output CSV file ('-' or omitted: stdout, streamed), "
                   "written whole or not at all; a simulated log there is replaced, any other file only with "
                   "--overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace -o whatever it holds")
    p.set_defaults(func=run)


#: The ``source`` metadata of a simulated log: what ``-o`` may replace without ``--overwrite``.
SOURCE = "slipest simulate"

#: Most model steps one leg cycle may take: a cycle is simulated whole, at about 80 bytes of memory per step
#: (6e6 steps: 10 minutes at the default dt=1e-4 s, about 0.5 GB).
MAX_CYCLE_STEPS = 6_000_000
#: Fewest IMU samples a leg cycle may last: a shorter one (a leg speed too fast for the rate) is no cycle a log
#: shows (``--omega 1e6`` wrote one row for 20 cycles).
MIN_CYCLE_SAMPLES = 8
#: Most samples a run may have: 1e9 rows are a log of about 40 GB (11.6 days at 1 kHz).
MAX_SAMPLES = 1_000_000_000
#: Bytes a log row takes (``t,az,theta,slip``), for the messages.
_ROW_BYTES = 40


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
                   help="leg speed [rad/s] (default 0.63; a scenario file sets it per segment); a leg cycle may "
                   "last at most 6e6 model steps (10 min at the default dt: omega >= 0.0027 with 4 legs) and at "
                   "least 8 IMU samples (omega <= 196 with 4 legs at 1000 Hz)")
    g.add_argument("--cycles", type=int, default=10,
                   help="number of leg cycles (default 10; at most 1e6, and 1e9 samples in all)")
    g.add_argument("--rate", type=float, default=None, help="IMU sample rate [Hz] (default 1000)")
    g.add_argument("--noise", type=float, default=None, help=noise_help)
    g.add_argument("--seed", type=seed_number, default=None, help=seed_help + " (a whole number >= 0)")
    g.add_argument("--dt", type=float, default=None,
                   help="model integration step [s] (default 1e-4; at most the IMU period 1/rate)")
    g.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME:k=v,...",
        help="switch on a sim-to-real effect (repeatable), e.g. imu_lowpass:cutoff=40",
    )


def _ceil_2_digits(x: float) -> float:
    """``x > 0`` rounded up to two significant digits (a floor a user can type and that is enough)."""
    scale = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.ceil(x / scale * (1 - 1e-12)) * scale


def _floor_2_digits(x: float) -> float:
    """``x > 0`` rounded down to two significant digits (a ceiling a user can type and that is enough)."""
    scale = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.floor(x / scale * (1 + 1e-12)) * scale


def check_lengths(scenario: Scenario) -> None:
    """ValueError when a leg cycle of ``scenario`` would take more than :data:`MAX_CYCLE_STEPS` model steps
    (a cycle is simulated whole: its memory grows with its length) or last fewer than :data:`MIN_CYCLE_SAMPLES`
    IMU samples, naming the cycle, its leg speed, the rate and the leg speed (or rate) that would do; or when the
    run would have more than :data:`MAX_SAMPLES` samples, naming how many and the log's size."""
    from slipest.model.stream import cycle_starts

    starts = cycle_starts(scenario)
    periods = np.diff(starts)
    j = int(np.argmax(periods))
    steps = periods[j] / scenario.dt
    if steps > MAX_CYCLE_STEPS:
        omega = scenario.cycles[j].omega
        floor = _ceil_2_digits(omega * steps / MAX_CYCLE_STEPS)  # a cycle's length goes as 1 / omega
        raise ValueError(
            f"leg cycle {j + 1} at omega={omega:g} rad/s lasts {periods[j]:.0f} s, {steps:.3g} model steps of "
            f"dt={scenario.dt:g} s; a cycle is simulated at once and may take at most {MAX_CYCLE_STEPS:.0e} "
            f"steps (10 minutes at the default dt; more would need gigabytes of memory): give a leg speed "
            f"omega >= {floor:g} rad/s")
    short = np.flatnonzero(periods * scenario.rate < MIN_CYCLE_SAMPLES)
    if short.size:
        j = int(short[0])
        samples = periods[j] * scenario.rate
        omega = scenario.cycles[j].omega
        raise ValueError(
            f"leg cycle {j + 1} at omega={omega:g} rad/s with {scenario.n_legs} legs lasts {periods[j]:.3g} s, "
            f"{samples:.3g} samples at the IMU rate {scenario.rate:g} Hz; a leg cycle must last at least "
            f"{MIN_CYCLE_SAMPLES} samples: give a leg speed omega <= "
            f"{_floor_2_digits(omega * samples / MIN_CYCLE_SAMPLES):g} rad/s or a rate >= "
            f"{_ceil_2_digits(scenario.rate * MIN_CYCLE_SAMPLES / samples):g} Hz")
    total = math.ceil(starts[-1] * scenario.rate - 1e-9)
    if total > MAX_SAMPLES:
        raise ValueError(
            f"{len(scenario.cycles):,} leg cycles lasting {starts[-1]:.4g} s at the IMU rate {scenario.rate:g} Hz are "
            f"{total:.3g} samples, a log of about {total * _ROW_BYTES / 1e9:.3g} GB; a run may have at most "
            f"{MAX_SAMPLES:.0e} samples ({MAX_SAMPLES * _ROW_BYTES / 1e9:.0f} GB): simulate fewer cycles (--cycles, or "
            "cycles in a scenario's [[segment]]) or at a lower rate")


def build_scenario(args: argparse.Namespace) -> Scenario:
    """The scenario the options describe (a TOML file's imu settings can be overridden by options).

    ValueError when there is none, worded for any command that takes these options (``slipest simulate``,
    ``firmware-sim``: each says its name): naming the scenario file (and its section, segment and key) when it
    cannot be read, is not UTF-8 TOML or describes no valid scenario; naming the option or parameter when the
    options describe none (e.g. a negative ``--seed``, a non-finite parameter, more than
    :data:`~slipest.model.scenario.MAX_CYCLES` leg cycles: refused before they are built); and from
    :func:`check_lengths` (a leg cycle longer than :data:`MAX_CYCLE_STEPS` model steps or shorter than
    :data:`MIN_CYCLE_SAMPLES` samples, a run of more than :data:`MAX_SAMPLES` samples).
    """
    from slipest.model.scenario import check_cycle_count

    effects = []
    if args.effect:
        from slipest.model.effects import parse_effect_arg

        effects = [parse_effect_arg(text) for text in args.effect]
    if args.scenario:
        try:
            with open(args.scenario, "rb") as fh:
                doc = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{args.scenario}: not valid TOML: {exc}") from None
        except UnicodeDecodeError as exc:
            raise ValueError(f"{args.scenario}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset "
                             f"{exc.start}): a scenario file is TOML text") from None
        except OSError as exc:
            raise ValueError(f"cannot read scenario {args.scenario}: {exc.strerror or exc}") from None
        # the options go into the document only where its sections have the right shape: a wrong one is
        # reported by Scenario.from_dict, naming the section
        imu = doc.setdefault("imu", {})
        if isinstance(imu, dict):
            for opt, key in (("rate", "rate"), ("noise", "noise"), ("seed", "seed"), ("dt", "dt")):
                if getattr(args, opt) is not None:
                    imu[key] = getattr(args, opt)
        if effects and isinstance(doc.get("effect", []), list):
            doc["effect"] = list(doc.get("effect", [])) + effects
        if args.omega is not None:
            raise ValueError("--omega goes with the options; a scenario file sets the leg speed in [model] or per "
                             "[[segment]] (omega = ...)")
        try:
            scenario = Scenario.from_dict(doc)
            check_lengths(scenario)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{args.scenario}: {exc}") from None
        return scenario
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
    check_cycle_count(args.cycles, f"--cycles={args.cycles}")
    scenario = Scenario(cycles=(params,) * args.cycles, effects=tuple(effects), **imu)
    check_lengths(scenario)
    return scenario


def _stream_log(scenario: Scenario, target) -> None:
    """Simulate ``scenario`` into ``target`` (a path or an open stream) as a log, chunk by chunk."""
    from slipest.io.log_csv import LogWriter
    from slipest.model.stream import iter_stream

    with LogWriter(target, ("t", "az", "theta", "slip"), metadata={**scenario.metadata(), "source": SOURCE},
                   overwrite=True) as writer:
        for chunk in iter_stream(scenario):
            writer.write(chunk.t, chunk.az, chunk.theta, chunk.slip)
            writer.flush()


def _write_direct(scenario: Scenario, target) -> None:
    """Simulate straight into ``target`` (stdout, a device or a pipe: streamed, what is written stays written);
    a model failure, a scenario the stages refuse or an OSError becomes SystemExit with the message."""
    from slipest.model.stance import ModelFailure

    try:
        _stream_log(scenario, target)
    except (ModelFailure, ValueError) as exc:
        raise SystemExit(f"slipest simulate: {exc}") from None
    except OSError as exc:
        if target is sys.stdout:  # a closed pipe (| head): the command line's own quiet handling
            raise
        raise SystemExit(f"slipest simulate: cannot write {target}: {exc.strerror or exc}") from None


def _write_file(scenario: Scenario, output: str) -> None:
    """Simulate into a temporary file beside ``output`` and move it onto ``output`` once whole (a regular file
    or none; anything else, e.g. /dev/null, is written directly: :func:`_write_direct`). On any error or
    interruption (Ctrl-C, SIGTERM: KeyboardInterrupt) the temporary file is removed, ``output`` is left as it
    was and stderr says so; a model failure, a scenario the stages refuse or an OSError becomes SystemExit
    with the message, anything else goes on."""
    from slipest.model.stance import ModelFailure

    dest = os.path.realpath(output)  # through a symbolic link: the file it names is replaced, not the link
    try:
        mode = os.stat(dest).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise SystemExit(f"slipest simulate: cannot write {output}: {exc.strerror or exc}") from None
    if mode is not None and not stat.S_ISREG(mode):  # a device or a pipe: nothing to replace
        _write_direct(scenario, output)
        return
    kept = f"{output} left as it was" if mode is not None else f"no {output} made"
    restore = interrupt_on_sigterm()
    tmp = None
    done = False
    try:
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(dest)}.", suffix=".part",
                                       dir=os.path.dirname(dest))
            os.close(fd)
            if mode is not None:  # the permissions of the file replaced, else those of a new file
                os.chmod(tmp, stat.S_IMODE(mode))
            else:
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(tmp, 0o666 & ~umask)
        except OSError as exc:
            raise SystemExit(f"slipest simulate: cannot write {output}: {exc.strerror or exc} (the log is "
                             f"written first into a temporary file in {os.path.dirname(dest)})") from None
        _stream_log(scenario, tmp)
        os.replace(tmp, dest)
        done = True
    except (ModelFailure, ValueError) as exc:
        raise SystemExit(f"slipest simulate: {exc}; nothing written ({kept})") from None
    except OSError as exc:
        raise SystemExit(f"slipest simulate: cannot write {output}: {exc.strerror or exc}; nothing written "
                         f"({kept})") from None
    except KeyboardInterrupt:
        print(f"slipest simulate: interrupted: nothing written ({kept})", file=sys.stderr)
        raise
    except SystemExit:
        raise
    except BaseException:
        print(f"slipest simulate: nothing written ({kept})", file=sys.stderr)
        raise
    finally:
        if tmp is not None and not done:
            try:
                os.remove(tmp)
            except FileNotFoundError:
                pass
            except OSError as exc:
                print(f"slipest simulate: cannot remove the partial log {tmp}: {exc.strerror or exc}",
                      file=sys.stderr)
        if restore is not None:
            signal.signal(signal.SIGTERM, restore)


def run(args: argparse.Namespace) -> int:
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
    if target is sys.stdout:
        _write_direct(scenario, target)
        return 0
    _write_file(scenario, target)
    print(f"wrote {len(scenario.cycles)} leg cycles to {args.output}", file=sys.stderr)
    return 0
