"""Reference slips read in one batch with the IMU frames hold from where they arrived among them; one outside
[0, 1) on a live CAN bus is counted and skipped."""

from __future__ import annotations

import time
import uuid

import can
import numpy as np
import pytest

from slipest.cli.live_args import format_counters
from slipest.io.bus_args import BusConfig
from slipest.io.can_source import CanSource
from slipest.io.source import Source, SourceBatch
from slipest.live import LiveEstimation
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from tests.log_makers import can_frames, with_references


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


def test_a_live_can_reference_outside_0_1_is_counted_and_skipped_never_learnt():
    """`slipest can --use-reference` on a bus whose SlipReference frames carry -0.2 and 1.5 (the DBC's field is
    signed): the stream goes on, those two are skipped (each cycle keeps the reference before them) and counted
    beside the invalid ones, in the counters the command logs at exit."""
    s = simulate_stream(Scenario.per_cycle(StickSlipParams(), {"rate": 1000.0, "noise_g": 0.01, "seed": 2},
                                           slip=[0.1, 0.2, 0.3, 0.4]))
    frames = with_references(can_frames({0: s}), {1: -0.2, 2: 1.5})
    channel = f"slipest-refs-{uuid.uuid4().hex}"
    got = []
    source = CanSource(BusConfig("virtual", channel)).start(wait_open=5)
    live = LiveEstimation(source, use_reference=True, on_estimate=lambda w, e, info: got.append(e))
    try:
        with can.Bus(interface="virtual", channel=channel) as tx:
            for m in frames:
                tx.send(m)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                done = source.counters()["ok"] == len(frames)  # all decoded: a last get takes what they filed
                batches = source.get(0.1)
                if batches:
                    live.feed(batches)
                elif done:
                    break
    finally:
        source.close()
        live.close()
    c = source.counters()
    assert c["ok"] == len(frames) and c["references_out_of_range"] == 2 and c["references_invalid"] == 0
    refs = {e.cycle: e.slip_ref for e in got if np.isfinite(e.slip_ref)}
    assert refs and all(0.0 <= r < 1.0 for r in refs.values()), refs
    assert refs[1] == pytest.approx(0.1) and refs[3] == pytest.approx(0.4)  # cycle 1 kept cycle 0's, 3 got its own
    summary = format_counters(c, live.counters(), live.latency())
    assert "references_invalid=0, references_out_of_range=2" in summary


def test_a_serial_reference_outside_0_1_is_counted_and_skipped():
    """The serial link's SLIP_REFERENCE frames carry a float32: percent (25.0) or a negative slip can arrive. Read
    from a real pseudo-terminal, those are counted and never handed on; the ones in [0, 1) are."""
    import os

    from slipest.io.serial_frames import encode_imu_sample, encode_slip_reference
    from slipest.io.serial_source import SerialSource

    master, slave = os.openpty()
    path = os.ttyname(slave)
    sent = [0.25, 25.0, -0.1, 0.3]
    data = b"".join(encode_slip_reference(0, k, 1000 * k, slip) + encode_imu_sample(0, k, 1000 * k, 9.81, 0.01 * k)
                    for k, slip in enumerate(sent))
    source = SerialSource(path)
    got = []
    try:
        source.start(wait_open=5)
        os.write(master, data)
        deadline = time.monotonic() + 10
        while sum(len(b.imu) for b in got) < len(sent) and time.monotonic() < deadline:
            got += source.get(0.1)
    finally:
        source.close()
        os.close(master)
        os.close(slave)
    assert sum(len(b.imu) for b in got) == len(sent)
    assert [r[3] for b in got for r in b.refs] == pytest.approx([0.25, 0.3])
    assert source.counters()["references_out_of_range"] == 2
