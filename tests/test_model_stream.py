"""The continuous sample stream and scenarios: the conventions the rest of slipest relies on."""

import math

import numpy as np
import pytest

from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stance import simulate_stance
from slipest.model.stream import iter_stream, simulate_stream
from slipest.units import G


def _phase(theta, n_legs=4):
    k = np.floor((theta + math.pi / n_legs) / (2 * math.pi / n_legs))
    return theta - 2 * math.pi * k / n_legs, k.astype(int)


def test_theta_is_continuous_increasing_and_starts_a_whole_cycle():
    s = simulate_stream(Scenario.constant(5, rate=1000.0))
    assert s.theta[0] == pytest.approx(-math.pi / 4)
    d = np.diff(s.theta)
    assert np.all(d > 0)
    np.testing.assert_allclose(d, 0.63 / 1000.0, rtol=1e-9)  # constant leg speed, no jumps
    assert s.theta[-1] < 5 * math.pi / 2 - math.pi / 4


def test_sample_rate_and_duration():
    sc = Scenario.constant(4, rate=800.0)
    s = simulate_stream(sc)
    np.testing.assert_allclose(np.diff(s.t), 1 / 800.0, rtol=1e-9)
    period = 2 * math.pi / (4 * 0.63)
    assert len(s.t) == math.ceil(4 * period * 800.0)


def test_gravity_is_in_az_and_the_rigid_half_is_quiet():
    s = simulate_stream(Scenario.constant(3, StickSlipParams(slip=0.3)))
    phase, _ = _phase(s.theta)
    rigid = s.az[phase < 0]
    # the hub rides a rigid spoke: specific force within 1% of g (kinematic accel ~ l w^2 = 0.007 g)
    assert np.all(np.abs(rigid - G) < 0.01 * G)
    assert np.mean(s.az) == pytest.approx(G, rel=0.01)


def test_stick_slip_half_is_the_stance_simulation():
    p = StickSlipParams(slip=0.4, kS=1200.0)
    s = simulate_stream(Scenario.constant(2, p, rate=10000.0))
    phase, k = _phase(s.theta)
    stance = simulate_stance(p)
    for cycle in range(2):
        sel = (phase >= 0) & (k == cycle)
        np.testing.assert_allclose(s.az[sel] - G, np.interp(phase[sel], stance.theta, stance.az), atol=1e-9)
        da = (s.az[sel].max() - s.az[sel].min()) / G
        assert da == pytest.approx(stance.delta_a_g, rel=1e-3)


def test_per_cycle_slip_and_soil_follow_the_scenario():
    sc = Scenario.per_cycle(slip=[0.1, 0.3, 0.45], kS=[800.0, 1000.0, 1400.0], imu={"rate": 500.0})
    s = simulate_stream(sc)
    _, k = _phase(s.theta)
    np.testing.assert_array_equal(s.cycle, k)
    np.testing.assert_allclose(s.slip, np.array([0.1, 0.3, 0.45])[k])


def test_noise_level_seed_and_chunking():
    clean = simulate_stream(Scenario.constant(6, noise_g=0.0))
    noisy = simulate_stream(Scenario.constant(6, noise_g=0.02, seed=7))
    assert np.std(noisy.az - clean.az) / G == pytest.approx(0.02, rel=0.05)
    again = np.concatenate([c.az for c in iter_stream(Scenario.constant(6, noise_g=0.02, seed=7), chunk_cycles=4)])
    np.testing.assert_array_equal(noisy.az, again)
    other = simulate_stream(Scenario.constant(6, noise_g=0.02, seed=8))
    assert not np.array_equal(noisy.az, other.az)


def test_scenario_from_dict_segments_and_ramps():
    sc = Scenario.from_dict(
        {
            "model": {"kappa": 0.3},
            "imu": {"rate": 500.0, "noise": 0.01, "seed": 3},
            "segment": [
                {"cycles": 2, "slip": 0.1, "kS": 900.0},
                {"cycles": 3, "slip": [0.2, 0.4], "phiS": 0.6, "phiD": 0.3},
            ],
        }
    )
    assert len(sc.cycles) == 5 and sc.rate == 500.0 and sc.noise_g == 0.01 and sc.seed == 3
    np.testing.assert_allclose(sc.slips, [0.1, 0.1, 0.2, 0.3, 0.4])
    assert sc.cycles[0].kS == 900.0 and sc.cycles[2].kS == 1000.0
    assert sc.metadata()["slip"] == "varies" and sc.metadata()["nL"] == "4"


@pytest.mark.parametrize(
    "doc, message",
    [
        ({"segment": [{"cycles": 2, "slipp": 0.1}]}, "unknown key"),
        ({"segment": [{"slip": 0.1}]}, "'cycles' is required"),
        ({"segment": []}, "at least one"),
        ({"model": {"kappaa": 1}, "segment": [{"cycles": 1}]}, "unknown parameter"),
        ({"imu": {"rte": 1}, "segment": [{"cycles": 1}]}, "unknown key"),
        ({"segment": [{"cycles": 1, "slip": 2.0}]}, "segment 1: .*slip"),
        ({"segments": []}, "unknown scenario section"),
    ],
)
def test_scenario_errors_name_the_problem(doc, message):
    with pytest.raises(ValueError, match=message):
        Scenario.from_dict(doc)


def test_drive_speed_ripple_keeps_theta_continuous_and_cycle_aligned():
    p = StickSlipParams(ripple_amp=0.2)
    s = simulate_stream(Scenario.constant(3, p))
    assert np.all(np.diff(s.theta) > 0)
    phase, k = _phase(s.theta)
    assert set(np.unique(k)) == {0, 1, 2}
    steps = np.diff(s.theta)
    assert steps.max() / steps.min() == pytest.approx(1.2 / 0.8, rel=0.02)
