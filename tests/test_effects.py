"""The sim-to-real effect catalog: equations at known values, parsing, and effect sizes."""

import math

import numpy as np
import pytest

from slipest.diagnosis.synth import da_change
from slipest.model.effects import (
    CATALOG,
    EFFECTS,
    ORDER,
    AngleOffset,
    LowPass,
    Saturation,
    TouchdownImpact,
    compile_effects,
    impact_response,
    normalise_spec,
    parse_effect_arg,
)
from slipest.model import kernel as K
from slipest.model.params import PARAM_NAMES, StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stance import simulate_batch, simulate_stance
from slipest.model.stream import SampleChunk, iter_stream, simulate_stream

NAMES = (
    "contact_damping",
    "stribeck",
    "imu_lowpass",
    "imu_saturation",
    "angle_offset",
    "touchdown_impact",
    "speed_ripple",
    "time_skew",
)


def test_catalog_names_units_and_ranges():
    assert set(EFFECTS) == set(NAMES) and set(ORDER) == set(NAMES)
    for name, spec in EFFECTS.items():
        assert spec.name == name and spec.kind in ("physics", "continuous", "sampled")
        assert spec.equation and spec.description
        for p in spec.params:
            assert p.unit
            lo, hi = p.bounds
            assert lo <= p.default <= hi
            assert p.typical[0] <= p.typical[1] and p.moderate[0] <= p.moderate[1]
            assert p.check(name, p.default) == p.default
        d = spec.as_dict()
        assert [q["name"] for q in d["params"]] == list(spec.param_names)


def test_each_effect_object_holds_its_pieces():
    """Every catalog object: its fit parameters, and a simulator part of its kind that agrees with its prediction's."""
    assert [e.name for e in CATALOG] == list(ORDER) and all(EFFECTS[e.name] is e for e in CATALOG)
    base = StickSlipParams()
    for e in CATALOG:
        assert e.fit_params, e.name
        for fp in e.fit_params:
            assert fp.unit and fp.lo < fp.hi and fp.lo <= fp.start <= fp.hi, (e.name, fp.name)
        values = e.defaults()
        if e.kind == "physics":
            # the simulator's fields and the prediction's kernel columns are one mapping
            row = e.physics(base, values).to_row()
            cols = e.kernel_columns(values)
            assert cols and all(row[c] == v for c, v in cols.items()), e.name
            assert all(field in PARAM_NAMES for _, field, _ in e.fields)
            with pytest.raises(ValueError, match="not a sensor effect"):
                e.stage(values)
        else:
            assert e.stage(values).domain == e.kind
            assert e.kernel_columns(values) == {}
            with pytest.raises(ValueError, match="not a physics effect"):
                e.physics(base, values)
    assert not hasattr(__import__("slipest.model.effects", fromlist=["x"]), "effect_names")


def test_ripple_columns_are_the_kernel_fields():
    e = EFFECTS["speed_ripple"]
    assert e.kernel_columns({"amplitude": 0.2, "phase": 0.7, "harmonic": 2}) == {
        K.P_RIPPLE_A: 0.2, K.P_RIPPLE_PH: 0.7, K.P_RIPPLE_H: 2}


# --- parsing -----------------------------------------------------------------------------------


def test_parse_effect_arg_values_and_defaults():
    assert parse_effect_arg("imu_lowpass:cutoff=40,order=3") == {"name": "imu_lowpass", "cutoff": 40.0, "order": 3}
    assert parse_effect_arg(" angle_offset : offset = -0.05 ") == {"name": "angle_offset", "offset": -0.05}
    assert parse_effect_arg("stribeck") == {"name": "stribeck"}
    full = normalise_spec(parse_effect_arg("stribeck:vs=0.01"))
    assert full == {"name": "stribeck", "vs": 0.01, "delta": EFFECTS["stribeck"].param("delta").default,
                    "viscous": EFFECTS["stribeck"].param("viscous").default}


@pytest.mark.parametrize(
    "text, words",
    [
        ("imu_lowpas:cutoff=4", ["unknown effect", "imu_lowpass"]),
        ("imu_lowpass:cutof=4", ["unknown parameter", "cutoff", "order"]),
        ("imu_lowpass:cutoff=fast", ["cutoff", "not a number"]),
        ("imu_lowpass:cutoff=nan", ["finite"]),
        ("imu_lowpass:order=2.5", ["order", "integer"]),
        ("imu_lowpass:cutoff=-3", ["cutoff", "outside"]),
        ("imu_lowpass:cutoff=4,cutoff=5", ["given twice"]),
        ("imu_lowpass:cutoff", ["param=value"]),
        ("imu_lowpass:", ["nothing after"]),
        ("", ["empty"]),
    ],
)
def test_parse_errors_name_the_problem(text, words):
    with pytest.raises(ValueError) as info:
        parse_effect_arg(text)
    for w in words:
        assert w in str(info.value)


def test_compile_rejects_duplicates_and_unknown():
    with pytest.raises(ValueError, match="more than once"):
        compile_effects([{"name": "stribeck"}, {"name": "stribeck", "vs": 0.01}])
    with pytest.raises(ValueError, match="unknown effect"):
        compile_effects([{"name": "gravity_waves"}])
    with pytest.raises(ValueError, match="unknown parameter"):
        compile_effects([{"name": "stribeck", "speed": 1.0}])


def test_compile_maps_kernel_fields_and_orders_stages():
    transform, stages = compile_effects(
        [
            {"name": "angle_offset", "offset": 0.1},
            {"name": "imu_lowpass", "cutoff": 20.0},
            {"name": "contact_damping", "b_hc": 250.0, "n_hc": 1.2},
            {"name": "stribeck", "vs": 0.02, "delta": 1.5, "viscous": 0.5},
            {"name": "speed_ripple", "amplitude": 0.1, "phase": 0.3},
            {"name": "touchdown_impact"},
            {"name": "imu_saturation", "full_scale": 30.0},
        ]
    )
    p = transform(StickSlipParams(nL=3))
    assert (p.b_hc, p.n_hc) == (250.0, 1.2)
    assert (p.stribeck_vs, p.stribeck_exp, p.viscous) == (0.02, 1.5, 0.5)
    assert (p.ripple_amp, p.ripple_phase) == (0.1, 0.3)
    assert [type(s).__name__ for s in stages] == ["TouchdownImpact", "LowPass", "Saturation", "AngleOffset"]
    assert [s.domain for s in stages] == ["continuous", "continuous", "sampled", "sampled"]
    assert stages[0].n_legs == 3  # the transform told the impact stage the leg count
    # off by default: no effect named, nothing changes
    t0, s0 = compile_effects([])
    assert t0(StickSlipParams()) == StickSlipParams() and s0 == []


# --- equations at known values ---------------------------------------------------------------------


def test_lowpass_gain_at_cutoff_and_passband_and_chunking():
    fs, fc = 10000.0, 25.0
    t = np.arange(int(2.0 * fs)) / fs
    for order in (1, 2, 4):
        for f, gain in ((fc, 1 / math.sqrt(2)), (fc / 20, 1.0)):
            x = 9.81 + np.sin(2 * math.pi * f * t)
            y, _ = LowPass(fc, order).apply(t, x, t, None)
            tail = y[t > 1.0] - 9.81  # steady state; the mean (gravity) passes unchanged
            amp = (tail.max() - tail.min()) / 2
            assert amp == pytest.approx(gain, rel=0.01), (order, f)
        # the filter keeps its state across chunks: chunked == one shot
        x = 9.81 + np.sin(2 * math.pi * 7 * t)
        whole, _ = LowPass(fc, order).apply(t, x, t, None)
        lp = LowPass(fc, order)
        parts = [lp.apply(t[a:b], x[a:b], t[a:b], None)[0] for a, b in ((0, 777), (777, 5000), (5000, len(t)))]
        np.testing.assert_allclose(np.concatenate(parts), whole, atol=1e-12)


def test_saturation_clips_at_full_scale():
    az = np.array([-30.0, -12.0, 0.0, 9.81, 12.0, 12.5, 40.0])
    out, th = Saturation(12.0).apply(None, az, np.zeros(7), None)
    np.testing.assert_array_equal(out, [-12.0, -12.0, 0.0, 9.81, 12.0, 12.0, 12.0])
    np.testing.assert_array_equal(th, np.zeros(7))


def test_angle_offset_shifts_theta_only():
    th = np.linspace(-0.7, 3.0, 11)
    az = np.full(11, 9.81)
    out_az, out_th = AngleOffset(-0.05).apply(None, az, th, None)
    np.testing.assert_array_equal(out_az, az)
    np.testing.assert_allclose(out_th, th - 0.05)


def test_touchdown_impact_envelope_at_known_times():
    n_legs, omega, fs = 4, 0.63, 1000.0
    A, tau, f = 10.0, 0.2, 10.0
    t = np.arange(0, 6.0, 1 / fs)
    theta = -math.pi / 4 + omega * t  # the stream's convention: the run starts on a boundary
    stage = TouchdownImpact(A, tau, f, n_legs)
    out, _ = stage.apply(t, np.zeros_like(t), theta, None)
    period = 2 * math.pi / (n_legs * omega)  # the next boundary
    for tb in (0.0, period):
        for s in (1 / (4 * f), 3 / (4 * f), 0.3):
            j = int(round((tb + s) * fs))
            expected = A * math.exp(-(t[j] - tb) / tau) * math.sin(2 * math.pi * f * (t[j] - tb))
            assert out[j] == pytest.approx(expected, abs=2e-3 * A)
    # a quarter period after the boundary the envelope is at A exp(-s/tau)
    s = 1 / (4 * f)
    assert impact_response(np.array([s]), A, tau, f)[0] == pytest.approx(A * math.exp(-s / tau))
    assert impact_response(np.array([-0.01]), A, tau, f)[0] == 0.0
    # chunked == one shot (transients carry over)
    st2 = TouchdownImpact(A, tau, f, n_legs)
    parts = [st2.apply(t[a:b], np.zeros(b - a), theta[a:b], None)[0] for a, b in ((0, 1234), (1234, 2000), (2000, len(t)))]
    np.testing.assert_allclose(np.concatenate(parts), out, atol=1e-9)


def test_a_touchdown_stream_is_the_same_however_it_is_chunked():
    """A chunk that starts right after a boundary used its first sample as the touchdown time (not the crossing),
    and a transient older than the 12 tau horizon was kept to its chunk's end: the stream changed by up to 4e-5
    m/s^2 with the chunking (firmware_sim streams a cycle a chunk, simulate 32). Bit for bit now."""
    sc = Scenario.constant(8, StickSlipParams(omega=0.5), rate=1000.0, noise_g=0.01, seed=3,
                           effects=({"name": "touchdown_impact", "amplitude": -12.0, "tau": 0.5, "freq": 14.0},))
    whole = SampleChunk.concatenate(iter_stream(sc, chunk_cycles=32))
    for cycles in (1, 3):
        np.testing.assert_array_equal(SampleChunk.concatenate(iter_stream(sc, chunk_cycles=cycles)).az, whole.az)


def test_speed_ripple_law_in_the_stance_and_the_stream():
    transform, _ = compile_effects([{"name": "speed_ripple", "amplitude": 0.2, "phase": 0.7}])
    p = transform(StickSlipParams())
    r = simulate_stance(p)
    dth = np.diff(r.theta) / r.dt
    law = 0.63 * (1 + 0.2 * np.sin(4 * r.theta[:-1] + 0.7))
    np.testing.assert_allclose(dth, law, rtol=1e-9)
    s = simulate_stream(Scenario.constant(2, StickSlipParams(), rate=2000.0,
                                          effects=({"name": "speed_ripple", "amplitude": 0.2, "phase": 0.7},)))
    w = np.diff(s.theta) * 2000.0
    mid = 0.5 * (s.theta[1:] + s.theta[:-1])
    np.testing.assert_allclose(w, 0.63 * (1 + 0.2 * np.sin(4 * mid + 0.7)), rtol=2e-3)


def _friction_coefficient(r):
    """mu = (FE - mF aC - sigma_v vC) / (FN sgn vC) on sliding steps (semi-implicit Euler, aC from vC)."""
    p = r.params
    a = np.diff(r.vC) / r.dt
    v = r.vC[:-1]
    sliding = (~r.stick[:-1]) & (~r.stick[1:]) & r.contact[:-1] & (v != 0) & (np.sign(r.vC[1:]) == np.sign(v))
    s = sliding
    mu = (r.FE[:-1][s] - p.mF * a[s] - p.viscous * v[s]) / (r.FN[:-1][s] * np.sign(v[s]))
    return v[s], mu


def test_stribeck_friction_at_zero_and_high_speed_via_a_stance():
    vs = 0.004
    p = StickSlipParams(slip=0.4, stribeck_vs=vs, stribeck_exp=2.0)
    v, mu = _friction_coefficient(simulate_stance(p))
    slow, fast = np.abs(v) < 0.03 * vs, np.abs(v) > 5 * vs
    assert slow.sum() >= 3 and fast.sum() >= 50
    np.testing.assert_allclose(mu[slow], p.muS, rtol=0.01)  # mu(0) = muS
    np.testing.assert_allclose(mu[fast], p.muD, rtol=0.01)  # mu(v >> vs) = muD
    law = p.muD + (p.muS - p.muD) * np.exp(-((np.abs(v) / vs) ** 2))
    np.testing.assert_allclose(mu, law, atol=0.01 * p.muS)
    # viscous term: sigma_v v adds to the Coulomb part
    pv = StickSlipParams(slip=0.4, viscous=2.0)
    v2, mu2 = _friction_coefficient(simulate_stance(pv))
    assert len(v2) > 50
    np.testing.assert_allclose(mu2, pv.muD, rtol=0.01)


def test_contact_damping_changes_da():
    da = simulate_batch([StickSlipParams(slip=s, b_hc=b) for b in (0.0, 300.0) for s in (0.15, 0.3, 0.5)]).delta_a_g
    nominal, damped = da[:3], da[3:]
    assert np.all(damped < 0.9 * nominal)  # the moderate damping reduces Da by more than 10%


def test_impact_and_lowpass_in_the_stream_use_the_leg_count():
    base = StickSlipParams(nL=3, slip=0.2)
    sc = Scenario.constant(2, base, rate=1000.0, effects=({"name": "touchdown_impact", "amplitude": 5.0,
                                                           "tau": 0.05, "freq": 20.0},))
    s = simulate_stream(sc)
    clean = simulate_stream(Scenario.constant(2, base, rate=1000.0))
    diff = s.az - clean.az
    period = 2 * math.pi / (3 * base.omega)
    for tb in (0.0, period):
        j = int(round((tb + 1 / 80) * 1000))  # a quarter of the ringing period after the boundary
        assert diff[j] == pytest.approx(5.0 * math.exp(-(s.t[j] - tb) / 0.05) * math.sin(2 * math.pi * 20 * (s.t[j] - tb)),
                                        abs=0.05)


# --- each effect at its default (moderate) size changes Da by >= 10% ---------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_default_size_changes_da_by_ten_percent(name):
    """The catalog default of every effect is in its moderate range and changes Da by >= 10%.

    Da as the project defines it (slipest.features: max - min over the stance
    window of the logged phase), default soil, slips 0.05-0.5, noise-free.
    """
    spec = EFFECTS[name]
    for p in spec.params:
        assert p.moderate[0] <= p.default <= p.moderate[1] or p.integer
    sc = Scenario.per_cycle(StickSlipParams(), imu={"rate": 1000.0}, slip=[0.05, 0.1, 0.2, 0.3, 0.4, 0.5])
    assert da_change(sc, ({"name": name},)) >= 0.10


# --- widened parametrisations: ripple harmonic, impact onset, time skew -------------------------------


def test_speed_ripple_at_a_higher_harmonic_in_the_stance_and_the_stream():
    spec = {"name": "speed_ripple", "amplitude": 0.15, "phase": -0.4, "harmonic": 3}
    transform, _ = compile_effects([spec])
    p = transform(StickSlipParams())
    assert p.ripple_harmonic == 3 and p.to_row()[K.P_RIPPLE_H] == 3
    r = simulate_stance(p)
    dth = np.diff(r.theta) / r.dt
    np.testing.assert_allclose(dth, 0.63 * (1 + 0.15 * np.sin(12 * r.theta[:-1] - 0.4)), rtol=1e-9)
    s = simulate_stream(Scenario.constant(2, StickSlipParams(), rate=2000.0, effects=(spec,)))
    w = np.diff(s.theta) * 2000.0
    mid = 0.5 * (s.theta[1:] + s.theta[:-1])
    np.testing.assert_allclose(w, 0.63 * (1 + 0.15 * np.sin(12 * mid - 0.4)), rtol=3e-3)
    # an integer harmonic keeps the cycle period of the law (the same mean speed for any h)
    one = simulate_stream(Scenario.constant(2, StickSlipParams(), rate=2000.0, effects=({**spec, "harmonic": 1},)))
    assert s.t[-1] == pytest.approx(one.t[-1], abs=1e-3)
    with pytest.raises(ValueError, match="ripple_harmonic"):
        StickSlipParams(ripple_harmonic=1.5)
    with pytest.raises(ValueError, match="harmonic.*integer"):
        parse_effect_arg("speed_ripple:harmonic=2.5")


def test_touchdown_impact_onset_phase_starts_with_a_jump():
    n_legs, omega, fs = 4, 0.63, 1000.0
    A, tau, f = 6.0, 1.5, 4.0
    t = np.arange(0, 3.0, 1 / fs)
    theta = -math.pi / 4 + omega * t
    out, _ = TouchdownImpact(A, tau, f, n_legs, onset=math.pi / 2).apply(t, np.zeros_like(t), theta, None)
    assert out[0] == pytest.approx(A)  # cos onset: the full amplitude at touchdown
    s = 0.3
    assert out[int(s * fs)] == pytest.approx(A * math.exp(-s / tau) * math.cos(2 * math.pi * f * s), abs=1e-9)
    assert impact_response(np.array([0.0]), A, tau, f, onset=math.pi / 2)[0] == pytest.approx(A)
    # the catalog's default onset (0) is the transient of before: starts at zero
    stage = EFFECTS["touchdown_impact"].stage(EFFECTS["touchdown_impact"].defaults())
    assert stage.onset == 0.0


def test_time_skew_delays_az_against_theta_and_streams_in_chunks():
    from slipest.model.effects import TimeSkew

    fs = 1000.0
    t = np.arange(4000) / fs
    theta = -math.pi / 4 + 0.7 * t
    az = 9.81 + np.sin(2 * math.pi * 3.0 * t)
    for skew in (0.2374, -0.1337):
        whole = TimeSkew(skew).apply(t, az, theta, None)
        stage = TimeSkew(skew)
        parts = [stage.apply(t[a:b], az[a:b], theta[a:b], None) for a, b in ((0, 2), (2, 700), (700, 701), (701, 4000))]
        np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), whole[0])
        np.testing.assert_array_equal(np.concatenate([p[1] for p in parts]), whole[1])
        # away from the start, each logged pair holds az from `skew` seconds before its angle's time
        late = t > 0.5
        t_theta = (whole[1][late] + math.pi / 4) / 0.7  # the time the logged angle belongs to
        expected = 9.81 + np.sin(2 * math.pi * 3.0 * (t_theta - skew))
        np.testing.assert_allclose(whole[0][late], expected, atol=2e-3 if skew > 0 else 0.02)
    # positive skew: az moved by whole samples (its noise is not smoothed)
    stage = TimeSkew(0.2374)
    noisy = np.random.default_rng(0).normal(size=t.size)
    out, _ = stage.apply(t, noisy, theta, None)
    np.testing.assert_array_equal(out[238:], noisy[:-238])


def test_time_skew_is_an_angle_offset_at_one_leg_speed():
    e = EFFECTS["time_skew"]
    assert e.equivalent_on(np.full(20, 0.63)) == "angle_offset"
    assert e.equivalent_on(np.repeat([0.5, 0.9, 0.7], 5)) is None
    # at one speed the stream is that of an angle offset omega * skew (up to the sample grid)
    sc = dict(rate=1000.0, noise_g=0.0)
    a = simulate_stream(Scenario.constant(3, StickSlipParams(), effects=({"name": "time_skew", "skew": 0.2},), **sc))
    b = simulate_stream(Scenario.constant(3, StickSlipParams(),
                                          effects=({"name": "angle_offset", "offset": 0.63 * 0.2},), **sc))
    m = 200  # the skew in whole samples: the skewed stream is the offset one, m samples later
    np.testing.assert_allclose(a.az[m:], b.az[:-m], atol=1e-12)
    np.testing.assert_allclose(a.theta[m:], b.theta[:-m], atol=1e-9)


def test_a_time_skewed_run_starts_with_the_signal_from_before_its_start():
    """The IMU's first samples of a skewed run were taken before the run's start: the stream simulates them (a
    lead-in cycle like the first) instead of holding the first value, which the estimator would call a stuck
    sensor."""
    from slipest.model.stream import CycleTimeline

    sc = dict(rate=1000.0, noise_g=0.0)
    a = simulate_stream(Scenario.constant(3, StickSlipParams(), effects=({"name": "time_skew", "skew": 0.2},), **sc))
    b = simulate_stream(Scenario.constant(3, StickSlipParams(), **sc))
    assert a.t[0] == 0.0 and a.cycle[0] == 0 and len(a.t) == len(b.t)
    np.testing.assert_allclose(a.theta, b.theta, atol=1e-12)  # 0.2 s is whole samples: the angle is not delayed
    # az at t < 0.2 s is the signal 0.2 s earlier: the end of the cycle before, which repeats the first
    period = CycleTimeline(StickSlipParams()).period
    early = a.t < 0.2
    np.testing.assert_allclose(a.az[early], np.interp(a.t[early] - 0.2 + period, b.t, b.az), atol=2e-3)
    assert np.ptp(a.az[early]) > 1.0
