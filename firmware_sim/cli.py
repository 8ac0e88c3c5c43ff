"""``firmware-sim``: the virtual IMU device on the command line.

::

    firmware-sim serial [--link PATH | --port PORT] [scenario options] [device options] [faults]
    firmware-sim can -i socketcand -c can0 --bus-option host=127.0.0.1 --bus-option port=P [...]

``serial`` creates a pseudo-terminal pair and prints the device to connect
to (``firmware-sim: serial device /dev/pts/N``, again after each
reconnection), or writes to ``--port``.  ``can`` sends on any python-can
bus.  The scenario options are those of ``slipest simulate``; every wheel
(``--wheels N``) drives the same scenario with its own noise seed (``seed +
wheel``; ``--same-noise`` for identical wheels).  Faults: ``--corrupt-rate``,
``--drop-rate``, ``--fault KIND@T[:k=v,...]`` (see :mod:`firmware_sim.faults`).
Lines on stdout start with ``firmware-sim:`` (machine-readable events); the
summary goes to stderr, the full report to ``--report FILE`` (JSON).
SIGINT/SIGTERM stop the device cleanly (the report is still written).
Numeric options are checked as they are parsed (NaN, infinities, negative
or zero values where they mean nothing: a usage error, exit 2), and so are
``--report`` and ``--send-log`` before the run (a directory that does not
exist, a directory named as the file); a file that still cannot be written
at the end (a full disk) is named on stderr, the other one is written, and
the exit status is 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import os
import signal
import sys
import threading

import numpy as np

from firmware_sim.device import STATUS_NAMES, Device, ScenarioFeed
from firmware_sim.faults import FaultPlan, parse_fault
from slipest import __version__
from slipest.cli.output_paths import output_problem
from slipest.io.source import one_line, one_line_logs


#: The device's IMU noise when neither --noise nor the scenario file says [g].
DEFAULT_NOISE_G = 0.01


def _announce(text: str) -> None:
    print(f"firmware-sim: {one_line(text)}", flush=True)


def number(what: str, minimum: float, *, above: bool = False, maximum: float | None = None):
    """An argparse type: a finite number >= ``minimum`` (> with ``above``; <= ``maximum`` when given), else
    ``argparse.ArgumentTypeError`` saying it is not ``what`` (NaN and infinities are never taken)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        fits = value > minimum if above else value >= minimum
        if not (fits and math.isfinite(value) and (maximum is None or value <= maximum)):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return value

    return parse


def whole_number(what: str, minimum: int, maximum: int | None = None):
    """An argparse type: a whole number in ``minimum..maximum`` (no upper bound when None), else
    ``argparse.ArgumentTypeError`` saying it is not ``what``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}")
        return value

    return parse


#: The most wheels a device streams (the wire formats' wheel field; six wheel-legs on a rover).
MAX_WHEELS = 6
_SECONDS_OR_0 = number("a number of seconds >= 0", 0.0)
_PROBABILITY = number("a probability in [0, 1]", 0.0, maximum=1.0)
_SEED = whole_number("a seed (a whole number >= 0)", 0)


def add_scenario_arguments(p: argparse.ArgumentParser) -> None:
    """The scenario options of ``slipest simulate``, with the device's noise default."""
    from slipest.cli.simulate import add_scenario_arguments as add_simulate_scenario_arguments

    add_simulate_scenario_arguments(
        p,
        noise_help="IMU noise standard deviation [g] (default 0.01, or the scenario file's: a real IMU is "
        "never noise-free, and noise-free data sent over CAN repeats values like a stuck sensor)",
        seed_help="random seed of the noise (wheel w uses seed + w)",
    )


def add_device_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("device")
    g.add_argument("--wheels", type=whole_number(f"a number of wheels 1..{MAX_WHEELS}", 1, MAX_WHEELS), default=1,
                   help=f"wheel-legs streamed, indices 0..N-1 (default 1, at most {MAX_WHEELS})")
    g.add_argument("--same-noise", action="store_true", help="every wheel gets the same noise (default: seed + wheel)")
    g.add_argument("--speed", type=number("a time factor >= 0 (0: as fast as possible)", 0.0), default=1.0,
                   help="time factor: 1 real time (default), 10 ten times faster, 0 as fast as possible")
    g.add_argument("--duration", type=number("a duration > 0 [s]", 0.0, above=True), default=None,
                   help="stop after this much scenario time [s]")
    g.add_argument("--send-reference", action="store_true",
                   help="send the true slip once per leg cycle (SLIP_REFERENCE frames / CAN reference message)")
    g.add_argument("--clock", choices=("monotonic", "zero"), default="monotonic",
                   help="timestamps: 'monotonic' (default) = speed x host monotonic time at the start + scenario "
                   "time, so a receiver on this host can measure latency; 'zero' = scenario time")
    g.add_argument("--wait-peer", type=number("a number of seconds > 0", 0.0, above=True), default=None, metavar="S",
                   help="give up if no receiver connected within S seconds (default: wait)")
    g.add_argument("--linger", type=_SECONDS_OR_0, default=0.5,
                   help="keep the link open this long after the last frame [s]")
    g.add_argument("--report", metavar="FILE",
                   help="write a JSON report of what was sent and injected (its directory must exist)")
    g.add_argument("--send-log", metavar="FILE.npz",
                   help="write one row per frame (kind, wheel, seq, t_us, send_ns, status, cycle, slip, az, theta: "
                   "the values sent, before any corruption) for latency and fault analysis (numpy .npz, to FILE "
                   "as named; its directory must exist)")
    g.add_argument("-q", "--quiet", action="store_true", help="no summary on stderr")
    f = p.add_argument_group("faults")
    f.add_argument("--corrupt-rate", type=_PROBABILITY, default=0.0, metavar="P",
                   help="probability that each byte on the serial wire is corrupted (serial only)")
    f.add_argument("--drop-rate", type=_PROBABILITY, default=0.0, metavar="P",
                   help="probability that each frame is not sent")
    f.add_argument("--fault", action="append", default=[], metavar="KIND@T[:k=v,...]",
                   help="scheduled fault at scenario time T [s] (repeatable): drop@T:n=N,wheel=W; "
                   "corrupt@T:n=N,wheel=W; stuck@T:n=N,wheel=W; disconnect@T:down=S (scenario seconds); "
                   "unknown-ids@T:n=N")
    f.add_argument("--fault-seed", type=_SEED, default=None, help="seed of the random faults (>= 0)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="firmware-sim",
        description="Virtual IMU device of slipest: streams the stick-slip model's hub acceleration and leg angle "
        "in real time over a serial link (a pseudo-terminal it creates, or a port) or a CAN bus, "
        "and injects faults on demand.",
    )
    parser.add_argument("--version", action="version", version=f"firmware-sim {__version__}")
    sub = parser.add_subparsers(dest="link_kind", metavar="LINK", required=True)
    ps = sub.add_parser("serial", help="stream over a pseudo-terminal it creates (default) or a serial port",
                        description="Stream binary frames (slipest.io.serial_frames) over a serial link.")
    where = ps.add_mutually_exclusive_group()
    where.add_argument("--port", help="write to this existing serial port (pyserial URL) instead of creating a pty")
    where.add_argument("--link", metavar="PATH",
                       help="also keep a symbolic link PATH to the pty (stable across reconnections)")
    ps.add_argument("--baudrate", type=whole_number("a baud rate (a whole number > 0)", 1), default=921600,
                    help="baud rate of --port (default 921600)")
    ps.add_argument("--settle", type=_SECONDS_OR_0, default=0.5,
                    help="seconds a reader must have had the pty open before frames are sent (default 0.5; "
                    "pyserial empties its input buffer right after opening, and later than that under load)")
    add_scenario_arguments(ps)
    add_device_arguments(ps)
    pc = sub.add_parser("can", help="stream on a python-can bus",
                        description="Stream the DBC's messages (slipest/io/data/slipest.dbc) on a python-can bus.")
    from slipest.io.bus_args import add_bus_arguments

    add_bus_arguments(pc)
    pc.add_argument("--wait-bus", type=_SECONDS_OR_0, default=10.0,
                    help="seconds to wait for the bus to open (default 10)")
    add_scenario_arguments(pc)
    add_device_arguments(pc)
    return parser


def build_scenarios(args) -> list:
    """One scenario per wheel (seed + wheel unless --same-noise).  ValueError on a wheel count outside
    1..:data:`MAX_WHEELS`, or from :func:`slipest.cli.simulate.build_scenario` (a negative seed, ``--seed`` or
    the scenario file's, among others), before the device streams."""
    from slipest.cli.simulate import build_scenario

    if not 1 <= args.wheels <= MAX_WHEELS:
        raise ValueError(f"--wheels={args.wheels} must be 1..{MAX_WHEELS}")
    if args.noise is None and not _scenario_sets_noise(args.scenario):
        args.noise = DEFAULT_NOISE_G
    base = build_scenario(args)
    out = []
    for w in range(args.wheels):
        seed = base.seed
        if seed is not None and not args.same_noise:
            seed = seed + w
        elif seed is None and args.same_noise:
            seed = int(np.random.SeedSequence().entropy % (2**31))
            base = dataclasses.replace(base, seed=seed)
        out.append(dataclasses.replace(base, seed=seed))
    return out


def _scenario_sets_noise(path: str | None) -> bool:
    if not path:
        return False
    import tomllib

    try:
        with open(path, "rb") as fh:
            return "noise" in tomllib.load(fh).get("imu", {})
    except (OSError, ValueError):  # not TOML, not UTF-8 text (TOMLDecodeError, UnicodeDecodeError: ValueErrors)
        return False  # build_scenario reports the problem


def build_plan(args) -> FaultPlan:
    """The faults the options ask for; ValueError on a bad ``--fault`` or one of a wheel not streamed."""
    scheduled = []
    for text in args.fault:
        fault = parse_fault(text)
        wheel = fault.params.get("wheel")
        if wheel is not None and wheel >= args.wheels:
            raise ValueError(f"--fault {text}: wheel {wheel} is not streamed (--wheels {args.wheels}: wheels "
                             f"0..{args.wheels - 1})")
        scheduled.append(fault)
    return FaultPlan(corrupt_rate=args.corrupt_rate, drop_rate=args.drop_rate, scheduled=tuple(scheduled),
                     seed=args.fault_seed)


def output_problems(args) -> list[str]:
    """Why ``--report`` and ``--send-log`` could not be written at the end of the run: a directory that does
    not exist or cannot be written in, a directory named as the file, a file that cannot be written, the
    scenario file, both options naming the same file.  Checked before the run, which they would outlast.  And why
    ``--link`` (serial) could not be made: its directory does not exist or cannot be written in, or it names a
    directory or the scenario file (the symbolic link to the pty is made there when the device opens)."""
    problems = []
    link = getattr(args, "link", None)
    if link:
        problem = output_problem(link, inputs=[args.scenario] if args.scenario else [], what="--link")
        if problem:
            problems.append(f"{problem} (the symbolic link to the device's pty is made there)")
    named = {}
    for option, path in (("--report", args.report), ("--send-log", args.send_log)):
        if not path:
            continue
        problem = output_problem(path, inputs=[args.scenario] if args.scenario else [], what=option)
        if problem is None:
            parent = os.path.dirname(os.path.abspath(path))
            if os.path.exists(path) and not os.access(path, os.W_OK):
                problem = f"{option} {path}: not writable"
            elif not os.path.exists(path) and not os.access(parent, os.W_OK | os.X_OK):
                problem = f"{option} {path}: cannot create files in {parent}"
            elif os.path.abspath(path) in named:
                problem = f"{option} {path}: the same file as {named[os.path.abspath(path)]}"
        named[os.path.abspath(path)] = option
        if problem:
            problems.append(problem)
    return problems


def write_outputs(args, report: dict, device: Device) -> list[str]:
    """Write ``--report`` (JSON) and ``--send-log`` (npz, to the file as named); one line per file that
    could not be written (e.g. a full disk), naming it and why (the other one is written all the same)."""
    failed = []
    if args.report:
        try:
            with open(args.report, "w") as fh:
                json.dump(report, fh, indent=1)
        except OSError as exc:
            failed.append(f"cannot write the report {args.report}: {exc.strerror or exc}")
    if args.send_log:
        log = device.send_log()
        try:
            with open(args.send_log, "wb") as fh:
                np.savez(fh, status_names=np.array(STATUS_NAMES), **log)
        except OSError as exc:
            failed.append(f"cannot write the send log {args.send_log}: {exc.strerror or exc}")
    return failed


def make_link(args):
    if args.link_kind == "serial":
        from firmware_sim.serial_link import PortLink, PtyLink

        if args.port:
            return PortLink(args.port, baudrate=args.baudrate, announce=_announce)
        return PtyLink(link_path=args.link, settle=args.settle, announce=_announce)
    from firmware_sim.can_link import CanLink
    from slipest.io.bus_args import bus_config_from_args
    from slipest.io.can_source import SOCKETCAND_LOGGER

    one_line_logs(SOCKETCAND_LOGGER)

    return CanLink(bus_config_from_args(args), announce=_announce, wait=args.wait_bus)


def _summary(report: dict) -> str:
    s, f = report["sent"], report["injected"]
    lines = [
        f"firmware-sim: sent {s['imu_frames_sent']} IMU and {s['ref_frames_sent']} reference frames "
        f"({s['bytes_sent']} bytes) of {s['imu_frames_generated']} + {s['ref_frames_generated']} generated, "
        f"{report['elapsed_s']:.1f} s at speed {report['speed']:g}",
        f"firmware-sim: injected: dropped {f['frames_dropped']}, corrupted {f['frames_corrupted']} "
        f"({f['bytes_corrupted']} bytes), stuck {f['stuck_samples']} samples, disconnects {f['disconnects']} "
        f"(lost {f['frames_lost_disconnected']} frames), unknown {f['unknown_sent']}",
    ]
    if s["frames_unsent_no_peer"] or s["frames_unsent_link_error"]:
        lines.append(f"firmware-sim: not sent (no receiver / link errors): {s['frames_unsent_no_peer']} / "
                     f"{s['frames_unsent_link_error']}")
    lat = report["lateness"]
    if lat.get("n"):
        lines.append(f"firmware-sim: send lateness median {lat['median_ms']:.3f} ms, p99 {lat['p99_ms']:.3f} ms")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    # libraries' warnings (python-can's) on stderr, one line each, marked as ours
    logging.basicConfig(format="firmware-sim: %(name)s: %(message)s", level=logging.WARNING, stream=sys.stderr)
    parser = build_parser()
    args = parser.parse_args(argv)
    problems = output_problems(args)
    if problems:
        parser.error("; ".join(problems))
    stop = threading.Event()
    link = None
    try:
        scenarios = build_scenarios(args)
        plan = build_plan(args)
        if args.link_kind == "can" and (plan.corrupt_rate or plan.of_kind("corrupt")):
            raise ValueError("byte corruption is a serial fault (CAN frames are protected by the bus's own CRC)")
        feed = ScenarioFeed(scenarios, send_reference=args.send_reference, duration=args.duration)
        link = make_link(args)
        device = Device(feed, link, plan, speed=args.speed, clock=args.clock, announce=_announce, stop=stop,
                        wait_peer=args.wait_peer, linger=args.linger, send_log=bool(args.send_log))
    except ValueError as exc:
        if link is not None:
            link.close()
        parser.error(str(exc))

    def _on_signal(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    code = 0
    from slipest.startup_gc import freeze_startup_objects

    freeze_startup_objects()  # no 10 ms full garbage collection over the start-up objects while pacing frames
    try:
        report = device.run()
    except (TimeoutError, OSError) as exc:
        print(f"firmware-sim: {exc}", file=sys.stderr)
        report = device.report()
        report["error"] = str(exc)
        code = 1
    finally:
        link.close()
    _announce("done" if report.get("finished") else "stopped")
    for failure in write_outputs(args, report, device):
        print(f"firmware-sim: {failure}", file=sys.stderr)
        code = 1
    if not args.quiet:
        print(_summary(report), file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
