"""The data not fitting the estimator's model is said live as it is in a replay (slipest.online.fit_advice).

A CAN log of a wheel whose hub takes touchdown impacts the model does not have, written with python-can's
own writer, read back by slipest's CAN log source and run through the live runtime
(:class:`slipest.live.LiveEstimation`): the runtime hands on the estimator's ``"fit"`` hint as a notice.
"""

import numpy as np

from slipest.io.can_log import CanLogFile
from slipest.live import LiveEstimation
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from tests.log_makers import can_frames, write_can_log


def test_the_live_runtime_says_when_the_data_do_not_fit_the_model(tmp_path):
    sc = Scenario.per_cycle(StickSlipParams(kS=1000.0, phiS=0.55, phiD=0.4), dict(noise_g=0.01, seed=4),
                            slip=np.repeat([0.1, 0.3, 0.2, 0.4], 2))
    sc = Scenario(cycles=sc.cycles, rate=sc.rate, noise_g=sc.noise_g, seed=sc.seed,
                  effects=({"name": "touchdown_impact", "amplitude": -13.2, "tau": 0.9, "freq": 9.6},))
    log = write_can_log(tmp_path / "impacts.blf", can_frames({2: simulate_stream(sc)}, references=False))
    source = CanLogFile(log)
    got = []
    live = LiveEstimation(source, on_estimate=lambda wheel, e, info: got.append(e))
    try:
        for batches in source.batches():
            live.feed(batches)
    finally:
        live.close()
    assert len(got) == 8 and all(e.quality == "misfit" for e in got)
    notices = live.notices()
    fit = [n for n in notices if "do not fit the estimator's model" in n]
    assert len(fit) == 1 and fit[0].startswith("wheel 2: ") and "'slipest calibrate'" in fit[0]
    assert live.counters()["wheel2"]["qualities"] == {"misfit": 8}
