"""``slipest can``: estimate slip live from a CAN bus and publish the estimates on it.

Receives the ImuSample (and SlipReference) messages of the DBC
(slipest/io/data/slipest.dbc) on any python-can bus, runs one estimator per
wheel-leg, prints one row per leg cycle as it closes (the columns of
``slipest replay``, wheel first) and sends one SlipEstimate message per leg
cycle back on the bus (``--no-publish`` to only listen).  Bus errors and a
dead socketcand server are reported and the bus reconnected; unknown IDs,
bad frames and reference slips flagged invalid or outside [0, 1) are
counted and skipped (references_invalid, references_out_of_range); a cycle
that lost a message is flagged, never estimated.  Counters at exit and on
SIGUSR1.  ``--record drive.blf``
(or ``.asc``, ``.log``...) records every frame received in a python-can
log, which ``slipest replay`` turns into the same estimates; ``--view
PORT`` shows the run live in Foxglove (docs/live-view.md).

Examples::

    slipest can -i socketcan -c vcan0
    slipest can -i socketcand -c can0 --bus-option host=127.0.0.1 --bus-option port=29536
    slipest can -i socketcan -c can0 --record drive.blf --view 8765
"""

from __future__ import annotations

import argparse

from slipest.cli.command import add_command


def add_parser(sub) -> None:
    from slipest.cli.live_args import add_live_arguments
    from slipest.io.bus_args import add_bus_arguments

    p = add_command(sub, "can",
                    "estimate slip live from a CAN bus (DBC messages) and publish the estimates on it", __doc__)
    add_bus_arguments(p)
    p.add_argument("--no-publish", action="store_true", help="do not send SlipEstimate messages")
    add_live_arguments(p, "the bus", frames=True)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from slipest.cli.live_args import live_from_args, make_printer, run_command, view_from_args
    from slipest.io.bus_args import bus_config_from_args
    from slipest.io.can_source import CanSource

    try:
        config = bus_config_from_args(args)
    except ValueError as exc:
        raise SystemExit(f"slipest can: {exc}") from None
    source = CanSource(config)
    printer = make_printer(args)

    def on_estimate(wheel, est, info):
        if not args.no_publish:
            source.publish(wheel, est)
        printer(wheel, est, info)

    live = live_from_args(args, source, on_estimate)
    view = view_from_args("slipest can", args, live)
    return run_command("slipest can", args, source, live, f"listening on CAN bus {config.describe()}", view)
