"""``slipest serial PORT``: estimate slip live from a device on a serial port.

Reads the binary frames of :mod:`slipest.io.serial_frames` from PORT (a
UART, a USB adapter, a pseudo-terminal such as the one ``firmware-sim
serial`` prints; any pyserial URL), runs one estimator per wheel-leg and
prints one row per leg cycle as it closes (the columns of ``slipest
replay``, wheel first).  The port is reopened when it disappears and comes
back.  Corrupted frames are counted and skipped; a cycle that lost a frame
is flagged, never estimated.  Counters at exit and on SIGUSR1.

``--record run.csv`` records the samples the estimator gets; a python-can
log (``.asc``, ``.blf``...) is refused: :data:`NO_CAN_LOG` says why.
``--view PORT`` shows the run live in Foxglove (docs/live-view.md).
"""

from __future__ import annotations

import argparse

from slipest.cli.command import add_command

#: Why ``slipest serial`` records no python-can log (docs/live-view.md, "Recording").
NO_CAN_LOG = ("a python-can log records CAN frames, and a serial device sends serial frames (float32 az and theta, "
              "16-bit counters, microsecond times): as CAN frames they would be rounded (az to 0.005 m/s^2, "
              "theta to 1e-4 rad, 8-bit counters, 10 us times modulo 0.65536 s) and their replay would not give "
              "this run's estimates; record the samples the estimator gets to a .csv instead (--record run.csv), "
              "which slipest replay reads")


def add_parser(sub) -> None:
    from slipest.cli.live_args import add_live_arguments

    p = add_command(sub, "serial",
                    "estimate slip live from a serial port (binary frames; e.g. firmware-sim serial)", __doc__)
    add_live_arguments(p, "PORT")
    p.add_argument("port", metavar="PORT", nargs="?",
                   help="serial port or pyserial URL, e.g. /dev/ttyUSB0, /dev/pts/3 (or `port` in --config)")
    p.add_argument("--baudrate", type=int, default=921600, help="baud rate (default 921600; ignored by ptys)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from slipest.cli.live_args import live_from_args, make_printer, run_command, view_from_args
    from slipest.io.serial_source import SerialSource

    if not args.port:
        raise SystemExit("slipest serial: no PORT: give it on the command line or as port = \"...\" in --config")
    from slipest.live.recording import record_kind

    for path in args.record or ():
        if record_kind(path) == "frames":
            raise SystemExit(f"slipest serial: --record {path}: {NO_CAN_LOG}")
    source = SerialSource(args.port, baudrate=args.baudrate)
    # warmed up before the port is open: a device that waits for its reader starts after it
    live = live_from_args(args, source, make_printer(args))
    view = view_from_args("slipest serial", args, live)
    return run_command("slipest serial", args, source, live, f"reading {args.port}", view)
