"""Reference slips read in one batch with the IMU frames hold from where they arrived among them."""

from __future__ import annotations

import numpy as np

from slipest.io.source import Source, SourceBatch
from slipest.live import LiveEstimation
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream


class _OneBatch(Source):
    """A link whose reader was behind: every frame of the run arrives in one batch."""

    seq_modulus = 1 << 16
    time_unit = 1e-6

    def describe(self) -> str:
        return "one batch"

    def counters(self) -> dict:
        return {}

    def _open(self, wait: float) -> None:
        pass

    def _read(self):
        return None


def test_references_in_a_batch_hold_from_their_place_among_the_imu_frames():
    """A testbed rover sends its reference slip as each cycle starts; a reader that fell behind gets all of it in
    one batch. Each cycle is labelled with its own reference, not with the batch's last one (what happened when
    a batch's references were applied before its IMU frames)."""
    slips = [0.1, 0.3, 0.2, 0.4, 0.15]
    s = simulate_stream(Scenario.per_cycle(StickSlipParams(), {"rate": 1000.0, "noise_g": 0.01, "seed": 2},
                                           slip=slips))
    imu, refs = [], []
    starts = np.flatnonzero(np.r_[True, np.diff(s.slip) != 0])
    for i in range(s.t.size):
        if i in starts:
            refs.append((0, i, round(s.t[i] * 1e6), float(s.slip[i]), len(imu)))
        imu.append((0, i, round(s.t[i] * 1e6), float(s.az[i]), float(s.theta[i])))
    got = []
    live = LiveEstimation(_OneBatch(), use_reference=True, on_estimate=lambda w, e, info: got.append(e))
    live.feed([SourceBatch(0.0, imu, refs)])
    live.close()
    labelled = [e for e in got if np.isfinite(e.slip_ref)]
    assert len(labelled) >= len(slips) - 1
    for e in labelled:
        assert e.slip_ref == slips[e.cycle], (e.cycle, e.slip_ref)
