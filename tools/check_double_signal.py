#!/usr/bin/env python
"""A second signal while ``slipest serial`` shuts down: are the records and the report complete?

Each trial runs, in their own processes, a virtual device (``firmware-sim serial``, 2 wheels at
1 kHz each on a pseudo-terminal it creates) and ``slipest serial PORT --record F --report R``;
once the estimator has streamed for a while it gets a signal, then a second one 0-50 ms later
(SIGINT twice: a double Ctrl-C; SIGTERM twice: an impatient supervisor).  The trial passes when:

* the estimator exits with status 0 and printed its counters;
* the report exists, is valid JSON and says why the run ended;
* every wheel's record parses completely, with as many rows as the report's ``rows_recorded``,
  ``samples_out`` and ``samples_in`` for that wheel (every frame the wheel received was handed to
  the estimator and written, once: none held back, none inserted);
* every frame the decoder delivered reached its wheel's record (sum of ``samples_in`` over the
  wheels = the source's ``frames_ok``), the rows follow each other at the sample period with
  no gap and no lost frame (a clean pty loses nothing), the two wheels' records differ by at most
  one row (the device interleaves them), and no record holds more rows than the device sent.

    python tools/check_double_signal.py                       # 20 trials per signal (the target)
    python tools/check_double_signal.py --trials 3 --signals SIGTERM
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from slipest.io.log_csv import read_log  # noqa: E402
from slipest.live.recording import record_path  # noqa: E402
from tests.hil_support import Stopping, firmware_sim, serial_device, slipest_cmd  # noqa: E402


def trial(sig: signal.Signals, delay: float, wheels: int, speed: float, seed: int, tmp: str,
          stream_for: float) -> dict:
    """One double-signal trial; returns the figures and the list of failed checks (``problems``)."""
    rec = os.path.join(tmp, "run.csv")
    report = os.path.join(tmp, "live.json")
    dev_report = os.path.join(tmp, "device.json")
    with Stopping() as procs:
        dev = procs.add(firmware_sim("serial", "--wheels", str(wheels), "--speed", f"{speed:g}", "--cycles", "20",
                                     "--noise", "0.01", "--seed", str(seed), "--report", dev_report,
                                     "--settle", "0.05", "--quiet"))
        port = serial_device(dev)
        est = procs.add(slipest_cmd("serial", port, "--record", rec, "--report", report, "--format", "none"))
        dev.wait_line("streaming", timeout=60)
        time.sleep(stream_for)
        est.signal(sig)
        time.sleep(delay)
        second = est.p.poll() is None  # else it had already exited: the second signal comes too late to matter
        est.signal(sig)
        t0 = time.monotonic()
        try:
            rc = est.wait(60)
        except Exception:  # noqa: BLE001 - reported as a failed check
            rc = None
        shutdown = time.monotonic() - t0 + delay
        dev.signal(signal.SIGTERM)
        dev.wait(30)
    problems = []
    out = {"signal": sig.name, "delay_ms": 1e3 * delay, "rc": rc, "shutdown_s": shutdown, "second_sent": second,
           "problems": problems}
    if rc != 0:
        problems.append(f"exit status {rc}")
    if "counters:" not in est.stderr:
        problems.append("no counters printed")
    try:
        with open(report) as fh:
            live = json.load(fh)
    except (OSError, ValueError) as exc:
        problems.append(f"report: {exc}")
        return out
    out["reason"] = live.get("reason")
    out["signals_ignored"] = live.get("signals_ignored")
    if not str(live.get("reason", "")).startswith("interrupted"):
        problems.append(f"reason {live.get('reason')!r}")
    try:
        with open(dev_report) as fh:
            sent = json.load(fh)["sent"]["imu_sent_by_wheel"]
    except (OSError, ValueError, KeyError) as exc:
        problems.append(f"device report: {exc}")
        sent = [None] * wheels
    est_c = live["estimation"]
    rows = []
    samples_in = 0
    for w in range(wheels):
        wc = est_c.get(f"wheel{w}")
        if wc is None:
            problems.append(f"wheel {w}: not in the report")
            continue
        samples_in += wc["samples_in"]
        try:
            log = read_log(record_path(rec, w))
        except Exception as exc:  # noqa: BLE001 - a record that does not parse is the failure we look for
            problems.append(f"wheel {w}: record does not parse: {exc}")
            continue
        n = len(log)
        rows.append(n)
        if not n == wc["rows_recorded"] == wc["samples_out"] == wc["samples_in"]:
            problems.append(f"wheel {w}: {n} rows, report rows_recorded {wc['rows_recorded']}, "
                            f"samples_out {wc['samples_out']}, frames received samples_in {wc['samples_in']}")
        if wc["frames_lost"] or np.isnan(log.az).any():
            problems.append(f"wheel {w}: {wc['frames_lost']} frames lost, {int(np.isnan(log.az).sum())} NaN rows")
        steps = np.diff(log.t)
        if n > 1 and not np.allclose(steps, 1e-3, atol=2e-6):
            problems.append(f"wheel {w}: time steps {steps.min():.6f}..{steps.max():.6f} s (not contiguous)")
        if sent[w] is not None and n > sent[w]:
            problems.append(f"wheel {w}: {n} rows but the device sent {sent[w]} frames")
    out["rows"] = rows
    if samples_in != live["source"]["frames_ok"]:
        problems.append(f"frames decoded {live['source']['frames_ok']} != frames handed to the wheels {samples_in}")
    if len(rows) == wheels and max(rows) - min(rows) > 1:
        problems.append(f"records of different lengths {rows}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20, help="trials per signal (default 20)")
    ap.add_argument("--signals", default="SIGINT,SIGTERM", help="comma-separated (default SIGINT,SIGTERM)")
    ap.add_argument("--max-delay", type=float, default=0.05, help="largest delay between the two signals [s]")
    ap.add_argument("--wheels", type=int, default=2)
    ap.add_argument("--speed", type=float, default=4.0, help="device speed-up (default 4: 4 kHz per wheel)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the stream durations before the signals")
    ap.add_argument("--json", metavar="FILE", help="write every trial's figures")
    args = ap.parse_args(argv)
    rng = random.Random(args.seed)
    results = []
    print(f"# load: {os.getloadavg()}")
    for name in args.signals.split(","):
        sig = signal.Signals[name.strip()]
        for i in range(args.trials):
            delay = args.max_delay * i / max(1, args.trials - 1)  # 0 .. max-delay, evenly
            with tempfile.TemporaryDirectory(prefix="slipest-sig-") as tmp:
                r = trial(sig, delay, args.wheels, args.speed, seed=i, tmp=tmp, stream_for=rng.uniform(0.5, 2.0))
            results.append(r)
            status = "ok" if not r["problems"] else "FAIL: " + "; ".join(r["problems"])
            second = "" if r["second_sent"] else " (had already exited)"
            print(f"{sig.name} trial {i + 1:2d}: second signal after {r['delay_ms']:5.1f} ms{second}, exit {r['rc']}, "
                  f"rows {r.get('rows')}, stopped in {r['shutdown_s']:.2f} s, ignored in the report "
                  f"{r.get('signals_ignored')}: {status}", flush=True)
    print()
    for name in args.signals.split(","):
        mine = [r for r in results if r["signal"] == name.strip()]
        ok = sum(not r["problems"] for r in mine)
        late = sum(not r["second_sent"] for r in mine)
        print(f"{name.strip()}: {ok}/{len(mine)} trials with every record complete, the report written and "
              f"exit status 0 ({late} where the second signal came after the exit)")
    print(f"# load: {os.getloadavg()}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)
    return 0 if all(not r["problems"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
