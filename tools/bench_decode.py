#!/usr/bin/env python3
"""Benchmark the serial wire format (slipest.io.serial_frames): encoding and decoding.

* Encoding: builds a capture of N frames (6 wheels of IMU_SAMPLE, one
  SLIP_REFERENCE after every 49 IMU frames) with ``encode_imu_sample`` /
  ``encode_slip_reference``, one call per frame; and encodes rows of a
  firmware_sim frame table with the device's own path (``Link.encode`` of a
  serial link), in bursts of 64 rows (paced device) and 256 (``--speed 0``).
  Prints frames/s and the CPU share the virtual device's encoding takes at
  6 wheels x 1 kHz.
* Decoding: the protocol object ``FrameDecoder`` fed 4 KB chunks, as a port
  reader thread would, keeping every frame, on the clean capture and on a
  copy with one bit flipped in 1 % of the bytes.  Checks that the clean
  capture decodes to exactly the frames sent and that the corrupted one
  delivers only frames that were sent, in order (a subsequence).

Times are process CPU time (cpu) and wall clock (wall; lower when other
processes share the CPUs), best of ``--repeat``.

Run from the repository root:  python tools/bench_decode.py [--frames N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from firmware_sim.link import FRAME_TABLE_DTYPE, KIND_IMU
from firmware_sim.serial_link import PtyLink
from slipest.io import serial_frames as sf

IMU_PER_BLOCK = 49
REAL_TIME_RATE = 6 * 1000  # frames/s of 6 wheels at 1 kHz


def build_frames(n_frames: int, rng: np.random.Generator) -> list:
    """About ``n_frames`` records in send order: blocks of 49 IMU samples + 1 reference."""
    blocks = max(1, n_frames // (IMU_PER_BLOCK + 1))
    n_imu = blocks * IMU_PER_BLOCK
    k = np.arange(n_imu)
    t_us = (1_000_000_000 + k * 1_000 // 6).tolist()  # 6 wheels sampled at 1 kHz each
    phase = 2 * np.pi * (k // 6) / 1000.0
    az = np.float32(9.81 + 3.0 * np.sin(5 * phase) + rng.normal(0, 0.5, n_imu)).tolist()
    theta = np.float32((phase + np.pi) % (2 * np.pi) - np.pi).tolist()
    slip = np.float32(rng.uniform(0, 0.3, blocks)).tolist()
    out = []
    for b in range(blocks):
        for i in range(b * IMU_PER_BLOCK, (b + 1) * IMU_PER_BLOCK):
            out.append(sf.ImuSample(i % 6, (i // 6) % sf.SEQ_MODULUS, t_us[i], az[i], theta[i]))
        out.append(sf.SlipReference(b % 6, b // 6, 1_000_000_000 + b * 8_000, slip[b]))
    return out


def timed(fn, repeat: int):
    """-> ((best wall s, best cpu s), result of the last call)"""
    wall = cpu = float("inf")
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        wall, cpu = min(wall, time.perf_counter() - w0), min(cpu, time.process_time() - c0)
    return (wall, cpu), result


def encode_all(frames: list) -> bytes:
    imu, ref = sf.encode_imu_sample, sf.encode_slip_reference
    return b"".join([imu(*f) if f.kind == sf.FRAME_IMU_SAMPLE else ref(*f) for f in frames])


def frame_table(frames: list) -> tuple[np.ndarray, np.ndarray]:
    """The frames as a firmware_sim frame table, and their ``t_us``."""
    table = np.zeros(len(frames), FRAME_TABLE_DTYPE)
    table["kind"] = [f.kind for f in frames]
    table["wheel"] = [f.wheel for f in frames]
    table["seq"] = [f.seq for f in frames]
    imu = table["kind"] == KIND_IMU
    table["az"] = np.where(imu, [getattr(f, "az", np.nan) for f in frames], np.nan)
    table["theta"] = np.where(imu, [getattr(f, "theta", np.nan) for f in frames], np.nan)
    table["slip"] = [getattr(f, "slip", 0.0) for f in frames]
    return table, np.array([f.t_us for f in frames], np.int64)


def encode_table(link, table: np.ndarray, t_us: np.ndarray, burst: int) -> bytes:
    out = []
    for i in range(0, len(table), burst):
        out += link.encode(table, t_us, list(range(i, min(i + burst, len(table)))))
    return b"".join(out)


def decode(data: bytes, chunk: int):
    dec = sf.FrameDecoder()
    frames = []
    for i in range(0, len(data), chunk):
        frames.extend(dec.feed(data[i:i + chunk]))
    return frames, dec.counters()


def is_subsequence(sub: list, seq: list) -> bool:
    it = iter(seq)
    return all(any(x == y for y in it) for x in sub)


def corrupt(data: bytes, fraction: float, rng: np.random.Generator) -> bytes:
    """Flip one random bit in ``fraction`` of the bytes."""
    buf = np.frombuffer(data, np.uint8).copy()
    pos = np.unique(rng.integers(0, buf.size, int(buf.size * fraction)))
    buf[pos] ^= (1 << rng.integers(0, 8, pos.size)).astype(np.uint8)
    return buf.tobytes()


def rate(n: int, seconds: float) -> str:
    return f"{n / seconds / 1e6:>8.2f} M fr/s"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Benchmark slipest's serial frame encoding and decoding.")
    parser.add_argument("--frames", type=int, default=1_000_000, help="frames in the capture (default 1e6)")
    parser.add_argument("--chunk", type=int, default=4096, help="bytes per feed() call (default 4096)")
    parser.add_argument("--corruption", type=float, default=0.01, help="fraction of bytes with a bit flipped")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs of each measurement; the best counts")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    sent = build_frames(args.frames, rng)
    n = len(sent)
    ok = True

    t_enc, clean = timed(lambda: encode_all(sent), args.repeat)
    table, t_us = frame_table(sent)
    link = PtyLink()  # encodes only: never opened
    print(f"capture: {n:,} frames, {len(clean) / 1e6:.1f} MB; best of {args.repeat}")
    header = f"{'encoding':<44}{'cpu':>16}{'wall':>16}  {'cpu at 6 kHz':>12}  identical"
    print(header)
    print("-" * len(header))
    rows = [("encode_imu_sample / encode_slip_reference", t_enc, clean)]
    for burst in (64, 256):
        t, data = timed(lambda: encode_table(link, table, t_us, burst), args.repeat)
        rows.append((f"device: serial Link.encode, bursts of {burst}", t, data))
    for name, (wall, cpu), data in rows:
        same = data == clean
        ok &= same
        print(f"{name:<44}{rate(n, cpu):>16}{rate(n, wall):>16}  {100 * REAL_TIME_RATE * cpu / n:>11.2f}%"
              f"  {'yes' if same else 'NO'}")

    print()
    header = f"{'FrameDecoder, ' + str(args.chunk) + '-byte chunks':<32}{'delivered':>10}{'cpu':>16}{'wall':>16}  check"
    print(header)
    print("-" * len(header))
    streams = [("clean", clean),
               (f"{100 * args.corruption:g}% bytes corrupted", corrupt(clean, args.corruption, rng))]
    for name, data in streams:
        (wall, cpu), (frames, c) = timed(lambda: decode(data, args.chunk), args.repeat)
        if data is clean:
            good, check = frames == sent, "frames == sent"
        else:
            good, check = is_subsequence(frames, sent), "frames a subsequence of sent"
        good &= c["bytes_in"] == len(data)
        ok &= good
        print(f"{name:<32}{len(frames):>10,}{rate(n, cpu):>16}{rate(n, wall):>16}  {check}: {'yes' if good else 'NO'}")
        if data is not clean:
            print(f"{'':<32}counters: crc_errors={c['crc_errors']:,} malformed={c['malformed']:,} "
                  f"seq_gaps={c['seq_gaps']:,} bytes_discarded={c['bytes_discarded']:,}")
    print("frames/s = frames in the capture / time; 'cpu at 6 kHz' = CPU share of encoding 6 wheels x 1 kHz.")
    if not ok:
        print("ERROR: a check failed")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
