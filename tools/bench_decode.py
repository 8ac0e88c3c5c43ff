#!/usr/bin/env python3
"""Benchmark the serial frame decoders (slipest.io.serial_frames).

Builds a capture of N frames (6 wheels of IMU_SAMPLE, one SLIP_REFERENCE
after every 49 IMU frames), then decodes it

* with the protocol object ``FrameDecoder`` fed 4 KB chunks, as a port
  reader thread would, keeping every frame, and
* with the vectorised ``decode_capture`` on the whole capture (best of 3),

on the clean capture and on a copy with one bit flipped in 1 % of the bytes,
checks that both give identical frames and counters, and prints frames/s.

Run from the repository root:  python tools/bench_decode.py [--frames N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from slipest.io import serial_frames as sf

IMU_PER_BLOCK = 49


def build_capture(n_frames: int, rng: np.random.Generator) -> bytes:
    """About ``n_frames`` frames: blocks of 49 IMU samples + 1 reference."""
    blocks = max(1, n_frames // (IMU_PER_BLOCK + 1))
    n_imu, n_ref = blocks * IMU_PER_BLOCK, blocks
    k = np.arange(n_imu)
    t_us = 1_000_000_000 + k * 1_000 // 6  # 6 wheels sampled at 1 kHz each
    phase = 2 * np.pi * (k // 6) / 1000.0
    imu = sf.encode_imu_samples(k % 6, k // 6, t_us, 9.81 + 3.0 * np.sin(5 * phase) + rng.normal(0, 0.5, n_imu),
                                (phase + np.pi) % (2 * np.pi) - np.pi)
    j = np.arange(n_ref)
    ref = sf.encode_slip_references(j % 6, j // 6, 1_000_000_000 + j * 8_000, rng.uniform(0, 0.3, n_ref))
    imu_len, ref_len = 24, 20
    block = np.empty((blocks, IMU_PER_BLOCK * imu_len + ref_len), np.uint8)
    block[:, :IMU_PER_BLOCK * imu_len] = np.frombuffer(imu, np.uint8).reshape(blocks, -1)
    block[:, IMU_PER_BLOCK * imu_len:] = np.frombuffer(ref, np.uint8).reshape(blocks, -1)
    return block.tobytes()


def corrupt(data: bytes, fraction: float, rng: np.random.Generator) -> bytes:
    """Flip one random bit in ``fraction`` of the bytes."""
    buf = np.frombuffer(data, np.uint8).copy()
    pos = np.unique(rng.integers(0, buf.size, int(buf.size * fraction)))
    buf[pos] ^= (1 << rng.integers(0, 8, pos.size)).astype(np.uint8)
    return buf.tobytes()


def run_protocol_object(data: bytes, chunk: int):
    """-> ((wall s, cpu s), frames, counters)"""
    dec = sf.FrameDecoder()
    frames = []
    w0, c0 = time.perf_counter(), time.process_time()
    for i in range(0, len(data), chunk):
        frames.extend(dec.feed(data[i:i + chunk]))
    return (time.perf_counter() - w0, time.process_time() - c0), frames, dec.counters()


def run_vectorised(data: bytes, repeats: int = 3):
    """-> ((best wall s, best cpu s), frames array, counters)"""
    wall = cpu = float("inf")
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        arr, counters = sf.decode_capture(data)
        wall, cpu = min(wall, time.perf_counter() - w0), min(cpu, time.process_time() - c0)
    return (wall, cpu), arr, counters


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Benchmark slipest's serial frame decoders.")
    parser.add_argument("--frames", type=int, default=1_000_000, help="frames in the capture (default 1e6)")
    parser.add_argument("--chunk", type=int, default=4096, help="bytes per feed() call (default 4096)")
    parser.add_argument("--corruption", type=float, default=0.01, help="fraction of bytes with a bit flipped")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    clean = build_capture(args.frames, rng)
    streams = [("clean", clean),
               (f"{100 * args.corruption:g}% bytes corrupted", corrupt(clean, args.corruption, rng))]

    print(f"capture: {len(clean) / 1e6:.1f} MB; FrameDecoder fed {args.chunk}-byte chunks (frames kept); "
          f"decode_capture on the whole capture, best of 3")
    header = (f"{'stream':<26}{'sent':>10}{'delivered':>10}  {'FrameDecoder':>14}  {'decode_capture':>14}"
              f"{'ratio':>7}  identical")
    print(header)
    print("-" * len(header))
    ok = True
    n_sent = clean.count(b"\x00")
    for name, data in streams:
        t_proto, frames, c_proto = run_protocol_object(data, args.chunk)
        t_vec, arr, c_vec = run_vectorised(data)
        same = c_proto == c_vec and sf.frames_to_array(frames).tobytes() == arr.tobytes()
        ok &= same
        for k, clock in enumerate(("cpu", "wall")):
            label = f"{name} ({clock})"
            print(f"{label:<26}{n_sent:>10,}{len(frames):>10,}  {n_sent / t_proto[1 - k] / 1e6:>8.2f} M fr/s"
                  f"  {n_sent / t_vec[1 - k] / 1e6:>8.2f} M fr/s{t_proto[1 - k] / t_vec[1 - k]:>6.1f}x"
                  f"  {'yes' if same else 'NO'}")
        if data is not clean:
            print(f"{'':<26}counters: crc_errors={c_vec['crc_errors']:,} malformed={c_vec['malformed']:,} "
                  f"seq_gaps={c_vec['seq_gaps']:,} bytes_discarded={c_vec['bytes_discarded']:,}")
    print("frames/s = frames in the capture / decoding time, by process CPU time (cpu) and wall clock\n"
          "(wall; lower when other processes share the CPUs); 'identical': same frames and counters.")
    if not ok:
        print("ERROR: the two decoders disagree")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
