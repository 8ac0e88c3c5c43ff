#!/usr/bin/env python3
"""False alarms and misses of the glitch filter (slipest.despike) on simulated clean cycles over the envelope.

Draws ``--drives`` drives (IMU rate log-uniform 200-2000 Hz, noise 0-0.03 g,
leg speed 0.3-1.2 rad/s, soil over the domain, 4 cycles of random slip
each), cuts them into whole cycles and counts the samples the filter calls
outliers (every one a false alarm: the data are clean); then adds one spike
of 3-15 g (either sign) at a random sample of each cycle and counts the
spikes missed.

    python tools/check_despike.py                 # 24 drives, ~1 min
    python tools/check_despike.py --seed 2 --drives 48
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
from tqdm import tqdm

from slipest.despike import outliers
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.segmentation import CycleSegmenter
from slipest.units import G


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--drives", type=int, default=24)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    samples = false = spikes = missed = 0
    misses = []
    for run in tqdm(range(args.drives), desc="drives", file=sys.stderr):
        rate = float(np.exp(rng.uniform(math.log(200), math.log(2000))))
        noise = float(rng.uniform(0, 0.03))
        omega = float(rng.uniform(0.3, 1.2))
        phiS = rng.uniform(0.2, 0.8)
        p = StickSlipParams(kS=rng.uniform(500, 1500), phiS=phiS, phiD=rng.uniform(0.1, phiS)).with_(omega=omega)
        s = simulate_stream(Scenario.per_cycle(p, dict(noise_g=noise, seed=run, rate=rate), slip=rng.uniform(0, 0.5, 4)))
        seg = CycleSegmenter(window=(-math.pi / 4, math.pi / 4))
        for c in seg.push_many(s.t, s.az, s.theta) + seg.finish():
            m = outliers(c.az)
            samples += m.size
            false += int(m.sum())
            az = c.az.copy()
            j = int(rng.integers(5, az.size - 5))
            az[j] += rng.choice([-1.0, 1.0]) * rng.uniform(3, 15) * G
            spikes += 1
            if not outliers(az)[j]:
                missed += 1
                misses.append(f"{rate:.0f} Hz, {noise:.3f} g, {omega:.2f} rad/s")
    print(f"clean samples called outliers: {false} of {samples}; spikes of 3-15 g missed: {missed} of {spikes}"
          + (f" ({'; '.join(misses[:5])})" if misses else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
