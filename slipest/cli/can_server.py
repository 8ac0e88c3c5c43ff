"""``slipest can-server``: a shared virtual CAN bus for machines without SocketCAN.

Runs slipest's socketcand-protocol server (:mod:`slipest.io.socketcand_server`)
on a loopback address: every process that opens it with python-can's
``socketcand`` interface shares one bus (``slipest can``, ``firmware-sim
can``, ``python -m can.logger`` / ``can.player`` / ``can.viewer``).  Stops on
Ctrl-C or SIGTERM and prints its counters.
"""

from __future__ import annotations

import argparse

from slipest.cli.command import add_command
import sys


def add_parser(sub) -> None:
    from slipest.io.socketcand_server import DEFAULT_CHANNEL, DEFAULT_PORT

    p = add_command(sub, "can-server",
                    "run a shared virtual CAN bus (socketcand protocol, loopback only)", __doc__)
    p.add_argument("--host", default="127.0.0.1", help="loopback address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT}; 0: a free one)")
    p.add_argument("--channel", action="append", dest="channels", metavar="NAME",
                   help=f"channel clients may open (repeatable; default: any; clients usually use {DEFAULT_CHANNEL})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from slipest.io.socketcand_server import DEFAULT_CHANNEL, run_server

    channel = (args.channels or [DEFAULT_CHANNEL])[0]

    def ready(host: str, port: int) -> None:
        print(f"socketcand server listening on {host}:{port}", flush=True)
        print(f"  slipest can -i socketcand -c {channel} --bus-option host={host} --bus-option port={port}", flush=True)
        print(f"  firmware-sim can -i socketcand -c {channel} --bus-option host={host} --bus-option port={port}",
              flush=True)

    try:
        stats = run_server(args.host, args.port, on_ready=ready, channels=args.channels)
    except ValueError as exc:
        raise SystemExit(f"slipest can-server: {exc}") from None
    except OSError as exc:
        why = exc.strerror or exc
        raise SystemExit(f"slipest can-server: cannot listen on {args.host}:{args.port}: {why}") from None
    print("slipest can-server stopped: " + ", ".join(f"{k}={v}" for k, v in stats.items()), file=sys.stderr, flush=True)
    return 0
