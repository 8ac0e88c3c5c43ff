#!/usr/bin/env python3
"""Speed of replaying what a rover records, against the slipest CSV replay in the same process.

Simulates one wheel-leg drive (1 kHz, 0.01 g noise, ``--cycles`` leg cycles
of 2.5 s) and writes it as a slipest log CSV, as a python-can BLF and ASC
(ImuSample frames of ``--wheels`` wheels, python-can's writers) and as a ROS 2
bag in sqlite3 and MCAP (Imu at 1 kHz, JointState at 200 Hz, rosbags), then
replays each with :class:`slipest.offline.replay.Replay` and prints samples per
second and the ratio to the CSV replay.  It also splits a CAN log's time
into python-can's reader, the DBC decoder and the rest (the live runtime's
frames -> samples -> estimator path), and times ``--logs`` copies of the BLF
replayed as a table with 1 and with 2 worker processes.

    python tools/bench_logs.py                 # ~1-2 min
    python tools/bench_logs.py --cycles 200 --wheels 4
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import can  # noqa: E402

from slipest.io.can_messages import CanDecoder  # noqa: E402
from slipest.offline.many import run_many  # noqa: E402
from slipest.offline.replay import TABLE_COLUMNS, Replay, ReplayOptions, replay_rows  # noqa: E402
from tests.log_makers import can_frames, stream, write_bag, write_can_log, write_csv  # noqa: E402


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def replay_seconds(path, options=ReplayOptions()) -> tuple[float, int]:
    with Replay(path, options) as r:
        res, sec = timed(r.run)
    return sec, sum(w.estimator_counters.get("samples", 0) for w in res.wheels.values())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=40)
    ap.add_argument("--wheels", type=int, default=2)
    ap.add_argument("--logs", type=int, default=4)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="slipest-bench-logs-"))
    try:
        s, sc = stream(args.cycles, seed=3)
        n = len(s.t)
        csv_log = write_csv(tmp / "drive.csv", s, sc)
        frames = can_frames({w: s for w in range(args.wheels)}, references=False)
        blf = write_can_log(tmp / "drive.blf", frames)
        asc = write_can_log(tmp / "drive.asc", frames)
        bags = {st: write_bag(tmp / f"bag_{st}", s, storage=st, joints=("wheel_leg",)) for st in ("sqlite3", "mcap")}
        print(f"drive: {args.cycles} leg cycles, {n} samples per wheel; CAN logs of {args.wheels} wheels "
              f"({len(frames)} frames); load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
        replay_seconds(csv_log)  # compiled code and the model loaded before timing
        base, n_csv = replay_seconds(csv_log)
        print(f"slipest CSV: {n_csv / base / 1e6:.2f} M samples/s ({base:.3f} s)   [baseline]")
        for name, path in (("CAN .blf", blf), ("CAN .asc", asc)):
            sec, k = replay_seconds(path)
            print(f"{name}: {k / sec / 1e3:.1f} k samples/s ({sec:.2f} s, {k} samples): "
                  f"{sec / k / (base / n_csv):.0f}x the CSV's time per sample")
        for st, path in bags.items():
            sec, k = replay_seconds(path)
            print(f"ROS 2 bag ({st}): {k / sec / 1e3:.1f} k samples/s ({sec:.2f} s): "
                  f"{sec / k / (base / n_csv):.0f}x the CSV's time per sample")
        msgs, read = timed(lambda: list(can.LogReader(blf)))
        _, one_by_one = timed(lambda: [CanDecoder().decode(m) for m in msgs])
        dec = CanDecoder()
        _, decode = timed(lambda: [dec.decode_many(msgs[i:i + 4096]) for i in range(0, len(msgs), 4096)])
        whole, k = replay_seconds(blf)
        print(f"CAN .blf per frame: python-can reader {read / len(msgs) * 1e6:.1f} us, DBC decode "
              f"{decode / len(msgs) * 1e6:.1f} us (chunks of 4096, as a replay decodes; frame by frame "
              f"{one_by_one / len(msgs) * 1e6:.1f} us), the rest (frames -> samples -> estimates) "
              f"{(whole - read - decode) / len(msgs) * 1e6:.1f} us")
        logs = []
        for i in range(args.logs):
            logs.append(str(tmp / f"copy{i}.blf"))
            shutil.copy(blf, logs[-1])
        times = {}
        for jobs in (1, 2):
            rows, times[jobs] = timed(lambda: run_many(replay_rows, logs, ReplayOptions(), columns=TABLE_COLUMNS,
                                                       jobs=jobs, progress=False))
            assert all(r["verdict"] == "ok" for r in rows), rows
        print(f"{args.logs} CAN logs as a table: {times[1]:.1f} s in this process, {times[2]:.1f} s with 2 worker "
              f"processes (x{times[1] / times[2]:.2f}; worker start-up included)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
