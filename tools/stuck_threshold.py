#!/usr/bin/env python
"""How long must ``az`` repeat bit for bit before the live receiver calls the sensor stuck?

A frozen sensor (or a stuck driver) repeats its last value; a working one never repeats a
noisy value for long.  This script measures how often real-looking data repeats, on each link
as the receiver sees it, and what false-alarm rate each run length gives:

* ``serial``: ``az`` as float32 (the IMU_SAMPLE frame);
* ``can``: ``az`` in steps of 0.005 m/s^2 (the DBC's ImuSample.Az), which repeats far more.

For each IMU rate and noise level it simulates the model's stream (a wheel-leg driving: the hub
shakes) and a rover at rest (gravity + noise only: the worst case), sends ``az`` through the
link's quantisation (checked against the real encoders on the first samples), and prints the
probability ``p`` that a sample repeats the previous one bit for bit, the longest run seen, and,
for the receiver's rule (a run lasting ``stuck_time`` at the rate, never fewer than its floor of
samples), the run length in samples and the expected interval between false alarms,
``1 / (rate * p**(n-1))``.

    python tools/stuck_threshold.py                  # the default table (about 30 s)
    python tools/stuck_threshold.py --seconds 600    # longer streams
"""

from __future__ import annotations

import argparse
import math
import os
import struct
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from slipest.io.can_messages import decode, encode_imu  # noqa: E402
from slipest.stuck import STUCK_MIN_SAMPLES, STUCK_TIME, stuck_run_length  # noqa: E402
from slipest.io.serial_frames import FrameDecoder, encode_imu_sample  # noqa: E402
from slipest.model.scenario import Scenario  # noqa: E402
from slipest.model.stream import simulate_stream  # noqa: E402
from slipest.units import G  # noqa: E402

CAN_AZ_STEP = 0.005  # [m/s^2] ImuSample.Az scale in the DBC


def on_link(az: np.ndarray, link: str) -> np.ndarray:
    """``az`` as the receiver gets it over ``link``."""
    if link == "serial":
        return az.astype(np.float32).astype(np.float64)
    return np.round(az / CAN_AZ_STEP) * CAN_AZ_STEP


def check_against_codecs(az: np.ndarray) -> None:
    """The quantisation of :func:`on_link` is the real encoders' (first samples)."""
    dec = FrameDecoder()
    frames = dec.feed(b"".join(encode_imu_sample(0, i, i, float(a), 0.0) for i, a in enumerate(az)))
    got = np.array([f.az for f in frames])
    assert np.array_equal(got, on_link(az, "serial")), "serial quantisation differs from the frame codec"
    got = np.array([decode(encode_imu(0, i, float(a), 0.0)).az for i, a in enumerate(az)])
    assert np.allclose(got, on_link(az, "can"), rtol=0, atol=1e-9), "CAN quantisation differs from the DBC codec"
    assert len(set(struct.pack("<d", x) for x in got[:50])) > 1


def stream(kind: str, rate: float, noise_g: float, seconds: float, seed: int) -> np.ndarray:
    if kind == "rest":
        n = int(seconds * rate)
        return G + np.random.default_rng(seed).normal(0.0, noise_g * G, n)
    omega = 0.63
    period = 2 * math.pi / (4 * omega)
    cycles = max(1, int(math.ceil(seconds / period)))
    doc = {"imu": {"rate": rate, "noise": noise_g, "seed": seed},
           "segment": [{"cycles": cycles, "slip": 0.3, "kS": 1000.0, "phiS": 0.6, "phiD": 0.35}]}
    return simulate_stream(Scenario.from_dict(doc)).az


def runs(az: np.ndarray) -> tuple[float, int]:
    """(probability a sample repeats the previous one bit for bit, longest run of equal samples)."""
    same = az[1:] == az[:-1]
    p = float(same.mean()) if same.size else 0.0
    breaks = np.flatnonzero(~same)  # a run of equal samples ends before each break
    longest = int(np.diff(np.concatenate(([-1], breaks, [same.size]))).max())
    return p, longest


def interval(p: float, n: int, rate: float) -> str:
    """Expected time between false stuck alarms (a run of n equal samples starting) [human]."""
    if p <= 0:
        return "never seen"
    per_s = rate * p ** (n - 1) * (1 - p)
    s = 1.0 / per_s if per_s > 0 else math.inf
    if s > 3.15e13:
        return "> 1e6 years"
    for unit, size in (("years", 3.15e7), ("days", 86400.0), ("h", 3600.0), ("min", 60.0), ("s", 1.0)):
        if s >= size:
            return f"{s / size:.3g} {unit}"
    return f"{s:.2g} s"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="stream length per case [s] (default 120)")
    ap.add_argument("--rates", default="1000,200,100", help="IMU rates [Hz]")
    ap.add_argument("--noise", default="0.01,0.003,0.001", help="noise levels [g] (0.01: firmware-sim's default)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    check_against_codecs(stream("drive", 1000.0, 0.01, 3.0, args.seed)[:3000])
    print(f"receiver's rule: a run of bit-identical az lasting stuck_time = {STUCK_TIME * 1e3:g} ms at the "
          f"IMU rate, never fewer than {STUCK_MIN_SAMPLES} samples")
    print(f"{'link':6} {'state':5} {'rate':>5} {'noise':>6} {'p(repeat)':>10} {'longest':>7}  "
          f"{'n(rule)':>7} {'false alarm every':>18}  {'n=50 (old)':>12}")
    for rate in (float(r) for r in args.rates.split(",")):
        n_rule = stuck_run_length(STUCK_TIME, 1.0 / rate)
        for noise in (float(x) for x in args.noise.split(",")):
            for kind in ("drive", "rest"):
                az = stream(kind, rate, noise, args.seconds, args.seed)
                for link in ("serial", "can"):
                    p, longest = runs(on_link(az, link))
                    print(f"{link:6} {kind:5} {rate:5.0f} {noise:6.3f} {p:10.2e} {longest:7d}  {n_rule:7d} "
                          f"{interval(p, n_rule, rate):>18}  {interval(p, 50, rate):>12}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
