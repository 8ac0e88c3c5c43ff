"""``slipest serial PORT``: estimate slip live from a device on a serial port.

Reads the binary frames of :mod:`slipest.io.serial_frames` from PORT (a
UART, a USB adapter, a pseudo-terminal such as the one ``firmware-sim
serial`` prints; any pyserial URL), runs one estimator per wheel-leg and
prints one row per leg cycle as it closes (the columns of ``slipest
replay``, wheel first).  The port is reopened when it disappears and comes
back.  Corrupted frames are counted and skipped; a cycle that lost a frame
is flagged, never estimated.  Counters at exit and on SIGUSR1.
"""

from __future__ import annotations

import argparse

from slipest.cli.command import add_command


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
    from slipest.cli.live_args import live_from_args, make_printer, run_command
    from slipest.io.serial_source import SerialSource

    if not args.port:
        raise SystemExit("slipest serial: no PORT: give it on the command line or as port = \"...\" in --config")
    source = SerialSource(args.port, baudrate=args.baudrate)
    # warmed up before the port is open: a device that waits for its reader starts after it
    live = live_from_args(args, source, make_printer(args))
    return run_command("slipest serial", args, source, live, f"reading {args.port}")
