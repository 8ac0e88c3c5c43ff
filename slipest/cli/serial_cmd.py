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
import sys


def add_parser(sub) -> None:
    p = sub.add_parser(
        "serial",
        help="estimate slip live from a serial port (binary frames; e.g. firmware-sim serial)",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("port", metavar="PORT", help="serial port or pyserial URL, e.g. /dev/ttyUSB0, /dev/pts/3")
    p.add_argument("--baudrate", type=int, default=921600, help="baud rate (default 921600; ignored by ptys)")
    p.add_argument("--wait-open", type=float, default=5.0, metavar="S",
                   help="keep trying to open PORT for S seconds at start (default 5)")
    from slipest.cli.live import add_live_arguments

    add_live_arguments(p)
    p.set_defaults(func=run)


def make_printer(args, out=None):
    """The ``on_estimate`` callback that prints rows (header first)."""
    from slipest.cli import estimate_output

    out = out or sys.stdout
    state = {"header": False}

    def on_estimate(wheel, est, info):
        if args.quiet:
            return
        if not state["header"]:
            print(estimate_output.header(("wheel",)), file=out)
            state["header"] = True
        print(estimate_output.row(est, (wheel,)), file=out, flush=True)

    return on_estimate


def run(args: argparse.Namespace) -> int:
    import serial

    from slipest.cli.live import feed_batches, live_from_args, run_live
    from slipest.io.serial_source import SerialSource

    # before the port is open: a device that waits for its reader starts after the estimator's warm-up
    live = live_from_args(args, seq_modulus=1 << 16, source=f"serial:{args.port}", on_estimate=make_printer(args))
    source = SerialSource(args.port, baudrate=args.baudrate)
    try:
        source.start(wait_open=args.wait_open)
    except serial.SerialException as exc:
        raise SystemExit(f"slipest serial: {exc}") from None
    print(f"slipest: reading {args.port}", file=sys.stderr, flush=True)
    try:
        return run_live(source, live, args, handle_batches=lambda bs: feed_batches(live, bs, 1e-6),
                        notices=source.notices, source_counters=source.counters)
    except FileExistsError as exc:  # the recording of a wheel that appeared later
        raise SystemExit(f"slipest serial: {exc}; use --overwrite") from None
