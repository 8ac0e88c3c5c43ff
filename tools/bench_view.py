#!/usr/bin/env python
"""Does the live view (``--view``) hold up the live estimator?  Latencies and losses with and without it.

Each run, in its own processes: a virtual device (``firmware-sim serial`` on a pseudo-terminal, or
``firmware-sim can`` over ``slipest can-server`` with ``--bus can``) and the live estimator
(``slipest serial|can --report``), in one of these modes:

* ``none``: no view (the baseline);
* ``view``: ``--view`` with no viewer connected;
* ``reading``: a Foxglove client (``tests/foxglove_client.py``, websockets) subscribed to every
  topic, reading everything;
* ``stalled``: a client that subscribes to every topic, then stops reading (its socket's receive
  buffer shrunk to 2 KiB), as a hung viewer would.

The modes run interleaved, ``--repeats`` times each.  Printed per mode: the estimator's
``intake -> estimate`` latency (a cycle's closing sample arriving to its estimate being ready:
median, p99, max [ms], pooled over the repeats), ``device -> intake`` (a sample's instant on the
device to its arrival: median, p99, max [ms]), frames lost, cycles estimated, the estimator's CPU
time per second of run (the estimator's process: its view thread and foxglove-sdk's server included),
and the viewer's ``/slipest/wheel0/imu`` messages received / published (a stalled viewer is served
again only after the run: 0 received).

    python tools/bench_view.py                        # serial, speed 2, 12 cycles, 2 repeats
    python tools/bench_view.py --bus can --speed 10 --cycles 30 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from tests.foxglove_client import FoxgloveClient  # noqa: E402
from tests.hil_support import Stopping, can_server, firmware_sim, serial_device, slipest_cmd, socketcand_args  # noqa: E402

MODES = ("none", "view", "reading", "stalled")


def run_once(mode: str, bus: str, speed: float, cycles: int, seed: int, tmp: str) -> dict:
    report = os.path.join(tmp, f"live-{mode}.json")
    if os.path.exists(report):
        os.remove(report)
    common = ["--report", report, "--format", "none", "--cycles", str(cycles), "--idle-timeout", "5",
              "--sim-speed", f"{speed:g}"] + (["--view", "0"] if mode != "none" else [])
    dev_args = ["--cycles", str(cycles + 1), "--speed", f"{speed:g}", "--noise", "0.01", "--seed", str(seed)]
    client = None
    with Stopping() as procs:
        if bus == "serial":
            dev = procs.add(firmware_sim("serial", *dev_args, "--settle", "0.05"))
            est = procs.add(slipest_cmd("serial", serial_device(dev), *common))
        else:
            server, port = can_server()
            procs.add(server)
            est = procs.add(slipest_cmd("can", *socketcand_args(port), *common))
        if mode in ("reading", "stalled"):
            est.wait_err("live view on ws://", timeout=60)
            vport = int(re.search(r"live view on ws://[\d.]+:(\d+)", est.stderr).group(1))
            client = FoxgloveClient(vport, stall="/slipest/wheel0/" if mode == "stalled" else None,
                                    rcvbuf=2048 if mode == "stalled" else None)
            client.ready.wait(10)
        if bus == "can":
            est.wait_err("listening on CAN bus", timeout=60)
            dev = procs.add(firmware_sim("can", *socketcand_args(port), *dev_args))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        rc = est.wait(600)
        wall = time.monotonic() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        dev.wait(60)
        if client is not None:
            client.resume()
            time.sleep(0.5)
            client.close()
    if rc != 0:
        raise RuntimeError(f"{mode}: the estimator exited with {rc}: {est.stderr[-2000:]}")
    with open(report) as fh:
        live = json.load(fh)
    wheels = [v for k, v in live["estimation"].items() if k.startswith("wheel")]
    out = {"mode": mode, "latency": live["latency"], "elapsed": live["elapsed_s"],
           "cpu_per_s": (after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime) / max(wall, 1e-9),
           "frames_lost": sum(w["frames_lost"] for w in wheels),
           "estimated": live["estimation"]["estimates"], "cycles": sum(w["cycles"] for w in wheels)}
    if client is not None:
        out["received"] = len(client.of("/slipest/wheel0/imu"))
        out["published"] = live["view"]["imu"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bus", choices=("serial", "can"), default="serial")
    ap.add_argument("--speed", type=float, default=2.0, help="device speed-up (default 2: 2 kHz)")
    ap.add_argument("--cycles", type=int, default=12, help="leg cycles per run (default 12: 15 s at speed 2)")
    ap.add_argument("--repeats", type=int, default=2, help="runs per mode, interleaved (default 2)")
    ap.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--json", metavar="FILE", help="write every run's figures as JSON")
    args = ap.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    print(f"# bus {args.bus}, speed {args.speed:g}, {args.cycles} cycles, {args.repeats} repeats; "
          f"load {os.getloadavg()}")
    runs = []
    with tempfile.TemporaryDirectory(prefix="slipest-view-") as tmp:
        for r in range(args.repeats):
            for mode in modes:
                res = run_once(mode, args.bus, args.speed, args.cycles, 10 + r, tmp)
                runs.append(res)
                lat = res["latency"]["intake_to_estimate"]
                print(f"  run {r} {mode:8s}: intake->estimate median {lat['median_ms']:.2f} p99 {lat['p99_ms']:.2f} "
                      f"ms; lost {res['frames_lost']}", flush=True)
    print(f"{'mode':8s} {'intake->estimate ms (med/p99/max)':>34s} {'device->intake ms (med/p99/max)':>33s} "
          f"{'lost':>5s} {'estimated':>9s} {'cpu s/s':>8s}  viewer")
    for mode in modes:
        rs = [r for r in runs if r["mode"] == mode]

        def pooled(key, rs=rs):
            med = np.median([r["latency"][key]["median_ms"] for r in rs])
            p99 = max(r["latency"][key]["p99_ms"] for r in rs)
            mx = max(r["latency"][key]["max_ms"] for r in rs)
            return f"{med:8.2f} {p99:8.2f} {mx:8.2f}"

        viewer = ""
        if "received" in rs[0]:
            viewer = ", ".join(f"{r['received']}/{r['published']}" for r in rs)
        print(f"{mode:8s} {pooled('intake_to_estimate'):>34s} {pooled('device_to_intake'):>33s} "
              f"{sum(r['frames_lost'] for r in rs):5d} {sum(r['estimated'] for r in rs):9d} "
              f"{np.mean([r['cpu_per_s'] for r in rs]):8.3f}  {viewer}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(runs, fh, indent=1)
    print(f"# load at the end {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
