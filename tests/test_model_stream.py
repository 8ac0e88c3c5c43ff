"""The continuous sample stream and scenarios: the conventions the rest of slipest relies on."""

import math

import numpy as np
import pytest

from slipest.model.params import PARAM_NAMES, StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stance import simulate_stance
from slipest.model.stream import MAX_CHUNK_SECONDS, SampleChunk, iter_stream, simulate_stream
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


# --- defects found by QA (s23): each of these failed before the fix ---------------------------------------------

@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("name", PARAM_NAMES)
def test_every_model_parameter_must_be_finite_and_the_error_names_it(name, bad):
    with pytest.raises(ValueError, match=rf"\b{name}={bad} must be a finite number"):
        StickSlipParams(**{name: bad})


@pytest.mark.parametrize("changes, message", [
    ({"n_hc": -0.5}, "n_hc=-0.5 must be >= 0"),
    ({"stribeck_exp": 0.0}, "stribeck_exp=0.0 must be a positive"),
    ({"b_hc": -1.0}, "b_hc=-1.0 must be >= 0"),
    ({"viscous": -1.0}, "viscous=-1.0 must be >= 0"),
])
def test_extension_parameters_are_range_checked_by_name(changes, message):
    with pytest.raises(ValueError, match=message):
        StickSlipParams(**changes)


def test_chunks_cover_at_most_max_chunk_seconds_and_do_not_change_the_samples():
    # a slow leg: 7.85 s cycles, so 32 cycles would be 250 s of model grid in one chunk
    sc = Scenario.constant(12, StickSlipParams(omega=0.2), rate=200.0, noise_g=0.02, seed=3,
                           effects=({"name": "imu_lowpass", "cutoff": 20.0},))
    period = 2 * math.pi / (4 * 0.2)
    chunks = list(iter_stream(sc))
    assert len(chunks) > 1
    for c in chunks:
        n_cycles = len(np.unique(c.cycle))
        assert 1 <= n_cycles and n_cycles * period <= MAX_CHUNK_SECONDS + 1e-9
    one_by_one = SampleChunk.concatenate(iter_stream(sc, chunk_cycles=1))
    whole = SampleChunk.concatenate(chunks)
    for f in ("t", "az", "theta", "slip", "cycle"):
        np.testing.assert_array_equal(getattr(whole, f), getattr(one_by_one, f))
    # one cycle longer than the bound is still one whole chunk
    long = Scenario.constant(2, StickSlipParams(omega=0.015), rate=10.0)  # 105 s cycles
    assert [len(np.unique(c.cycle)) for c in iter_stream(long)] == [1, 1]


def test_scenario_refuses_a_negative_seed_and_bad_effects_when_built():
    with pytest.raises(ValueError, match="seed=-1 must be a non-negative integer"):
        Scenario.constant(1, seed=-1)
    with pytest.raises(ValueError, match=r"\[imu\]: seed = -5 must be a non-negative integer"):
        Scenario.from_dict({"imu": {"seed": -5}, "segment": [{"cycles": 1}]})
    with pytest.raises(ValueError, match="effect 1: imu_lowpass: cutoff=-5 Hz is outside"):
        Scenario.constant(1, effects=({"name": "imu_lowpass", "cutoff": -5},))
    with pytest.raises(ValueError, match="named more than once: angle_offset"):
        Scenario.constant(1, effects=({"name": "angle_offset"}, {"name": "angle_offset", "offset": 0.1}))
    with pytest.raises(ValueError, match="--dt"):
        Scenario.constant(1, rate=20000.0)


@pytest.mark.parametrize("doc, message", [
    ({"segment": {"cycles": 2}}, r"\[segment\] is a single table: write \[\[segment\]\]"),
    ({"segment": [{"cycles": 2}], "effect": {"name": "imu_lowpass"}}, r"\[effect\] is a single table"),
    ({"model": [1, 2], "segment": [{"cycles": 2}]}, r"model = \[1, 2\] is an array: \[model\] must be a table"),
    ({"segment": [1, 2]}, "segment 1 is a number, not a table"),
    ({"segment": [{"cycles": True}]}, "cycles = true is a boolean"),
    ({"segment": [{"cycles": 1, "omega": float("nan")}]}, "segment 1: omega = nan must be a finite number"),
])
def test_scenario_shape_errors_name_the_section_and_the_shape(doc, message):
    with pytest.raises(ValueError, match=message):
        Scenario.from_dict(doc)


def test_metadata_lists_every_model_parameter_that_is_not_the_default():
    p = StickSlipParams(g=3.71, b_hc=40.0, stribeck_vs=0.01, ripple_amp=0.2)
    meta = Scenario.per_cycle(base=p, slip=[0.1, 0.2], n_hc=[1.0, 1.5]).metadata()
    assert (meta["g"], meta["b_hc"], meta["stribeck_vs"], meta["ripple_amp"]) == ("3.71", "40", "0.01", "0.2")
    assert meta["n_hc"] == "varies" and meta["slip"] == "varies"
    assert "viscous" not in meta and "ripple_phase" not in meta
    assert not {"g", "b_hc", "n_hc"} & set(Scenario.constant(1).metadata())
