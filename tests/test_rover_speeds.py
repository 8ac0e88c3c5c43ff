"""A rover file holds at its testbed's leg speeds: cycles at other speeds are flagged ``speed`` and the summary says
why, instead of estimates with intervals that no longer hold (QA: calibrated at 0.63 rad/s, a drive at 0.9 rad/s
covered 60 % of its slips)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slipest.inverse.surrogate import load_inverse_model
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.online import SlipEstimator
from slipest.rover.discrepancy import Discrepancy
from slipest.rover.file import RoverFileError, load_rover, save_rover
from slipest.rover.surrogate import SPEED_MARGIN, RoverSurrogate
from tests.cli_support import slipest_in_process
from tests.log_makers import write_csv


def _rover_file(tmp_path, speeds=(0.6, 0.66)):
    m = load_inverse_model()
    model = RoverSurrogate.of(m, Discrepancy.zero(m.features, m.center[:4], m.halfwidth[:4]),
                              np.zeros((len(m.features),) * 2))
    report = {"note": "test"} if speeds is None else {"leg_speed": {"omega": float(np.mean(speeds)),
                                                                    "range": list(speeds)}}
    return save_rover(model, report, tmp_path / "rover.json")


def _drive(omega: float):
    sc = Scenario.per_cycle(StickSlipParams(kS=900.0, phiS=0.5, phiD=0.3, omega=omega),
                            {"rate": 1000.0, "noise_g": 0.01, "seed": 4}, slip=np.full(8, 0.2))
    return simulate_stream(sc), sc


def _qualities(model, s):
    est = SlipEstimator(n_legs=4, model=model)
    got = est.push_many(s.t, s.az, s.theta) + est.finish()
    return [e.quality for e in got], est.hints


def test_a_rover_file_covers_its_testbed_speeds_within_the_margin_and_flags_others(tmp_path):
    rover = load_rover(_rover_file(tmp_path), n_legs=4)
    assert rover.testbed_speeds == (0.6, 0.66)
    assert rover.covered_range("omega") == pytest.approx((0.6 * (1 - SPEED_MARGIN), 0.66 * (1 + SPEED_MARGIN)))
    at_testbed, hints = _qualities(rover, _drive(0.63)[0])
    assert at_testbed.count("ok") >= 6 and "speed" not in at_testbed and "rover_speed" not in hints
    faster, hints = _qualities(rover, _drive(0.9)[0])
    assert faster and set(faster) == {"speed"}
    assert "0.6-0.66 rad/s" in hints["rover_speed"] and "without --rover" in hints["rover_speed"]
    shipped, _ = _qualities(load_inverse_model(), _drive(0.9)[0])  # the shipped model covers 0.9 rad/s
    assert "speed" not in shipped


def test_a_rover_file_without_its_testbed_speeds_keeps_the_models_range(tmp_path):
    """Files written before the range was read: the base model's range, as before."""
    rover = load_rover(_rover_file(tmp_path, speeds=None), n_legs=4)
    assert rover.testbed_speeds is None
    assert rover.covered_range("omega") == load_inverse_model().covered_range("omega")


@pytest.mark.parametrize("bad", [[0.7, 0.6], [0.6], [-1.0, 0.6], ["0.6", 0.7], [0.01, 0.02]])
def test_a_rover_file_with_a_bad_speed_range_is_refused_naming_it(tmp_path, bad):
    path = _rover_file(tmp_path)
    doc = json.loads(path.read_text())
    doc["report"]["leg_speed"]["range"] = bad
    path.write_text(json.dumps(doc))
    with pytest.raises(RoverFileError, match="rover.json"):
        load_rover(path, n_legs=4)


def test_replay_with_a_rover_file_at_another_speed_says_why_nothing_was_estimated(tmp_path, capsys):
    rover = _rover_file(tmp_path)
    s, sc = _drive(0.9)
    log = write_csv(tmp_path / "fast.csv", s, sc)
    rc, err = slipest_in_process(capsys, "replay", log, "--rover", rover)
    assert rc == 1 and "calibrated on testbed runs at 0.6-0.66 rad/s" in err and "speed" in err
