"""``slipest can-server``: a shared virtual CAN bus for machines without SocketCAN.

Runs slipest's socketcand-protocol server (:mod:`slipest.io.socketcand_server`)
on a loopback address: every process that opens it with python-can's
``socketcand`` interface shares one bus (``slipest can``, ``firmware-sim
can``, ``python -m can.logger`` / ``can.player`` / ``can.viewer``).  Its
memory has a budget: at most ``--max-clients`` connections and
``--max-buffer`` bytes queued for all clients together (the slowest client
is disconnected past it), ``--max-client-buffer`` bytes for one (frames are
dropped for it past that).  Stops on Ctrl-C or SIGTERM and prints its
counters.
"""

from __future__ import annotations

import argparse
import sys

from slipest.cli.command import add_command

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30}


def byte_size(text: str) -> int:
    """``"4194304"``, ``"64M"``, ``"512k"``, ``"1G"`` (binary units) -> bytes; ArgumentTypeError otherwise."""
    t = text.strip().lower().removesuffix("ib").removesuffix("b")
    unit = t[-1:] if t[-1:] in _UNITS else ""
    try:
        value = float(t[: len(t) - len(unit)]) * _UNITS[unit]
    except ValueError:
        value = -1.0
    if not 1 <= value < 1 << 62:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a positive size in bytes, e.g. 64M, 512k, 4194304")
    return int(value)


def add_parser(sub) -> None:
    from slipest.io.socketcand_server import DEFAULT_CHANNEL, DEFAULT_MAX_BUFFER, DEFAULT_MAX_CLIENTS, DEFAULT_PORT

    p = add_command(sub, "can-server",
                    "run a shared virtual CAN bus (socketcand protocol, loopback only)", __doc__)
    p.add_argument("--host", default="127.0.0.1", help="loopback address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT}; 0: a free one)")
    p.add_argument("--channel", action="append", dest="channels", metavar="NAME",
                   help=f"channel clients may open (repeatable; default: any; clients usually use {DEFAULT_CHANNEL})")
    b = p.add_argument_group("memory budget")
    b.add_argument("--max-clients", type=int, default=DEFAULT_MAX_CLIENTS, metavar="N",
                   help=f"connections at once; more are refused (default {DEFAULT_MAX_CLIENTS})")
    b.add_argument("--max-buffer", type=byte_size, default=DEFAULT_MAX_BUFFER, metavar="SIZE",
                   help=f"bytes queued for all clients together; past it the client with the most queued (the "
                   f"slowest) is disconnected (default {DEFAULT_MAX_BUFFER >> 20}M)")
    b.add_argument("--max-client-buffer", type=byte_size, default=4 << 20, metavar="SIZE",
                   help="bytes queued for one client; past it its frames are dropped (default 4M)")
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
        stats = run_server(args.host, args.port, on_ready=ready, channels=args.channels,
                           max_clients=args.max_clients, max_buffer=args.max_buffer,
                           max_client_buffer=args.max_client_buffer)
    except ValueError as exc:
        raise SystemExit(f"slipest can-server: {exc}") from None
    except OSError as exc:
        why = exc.strerror or exc
        raise SystemExit(f"slipest can-server: cannot listen on {args.host}:{args.port}: {why}") from None
    print("slipest can-server stopped: " + ", ".join(f"{k}={v}" for k, v in stats.items()), file=sys.stderr, flush=True)
    return 0
