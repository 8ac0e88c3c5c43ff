"""The sim-to-real diagnosis: localisation, gap and verdict logic, prediction, CLI report, end to end."""

import json
import math

import numpy as np
import pytest

from slipest.diagnosis import localize
from slipest.diagnosis.cycles import cut_cycles
from slipest.diagnosis.fit import FitBudget, Geometry
from slipest.diagnosis.predict import Evaluator, Grid
from slipest.diagnosis.rank import (
    Candidate,
    Thresholds,
    gap_of,
    noise_floor,
    rank,
    shrink_of,
    split_cycles,
    verdict,
)
from slipest.diagnosis.run import diagnose
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream
from slipest.units import G

GRID = Grid(4)


def _log(slips, soil=None, effects=(), noise=0.01, seed=3, rate=1000.0):
    base = StickSlipParams(**(soil or {}))
    sc = Scenario.per_cycle(base, imu={"rate": rate, "noise_g": noise, "seed": seed}, slip=slips)
    return simulate_stream(Scenario(cycles=sc.cycles, rate=rate, noise_g=noise, seed=seed, effects=tuple(effects)))


def _cycles(s):
    return cut_cycles(s.t, s.az, s.theta, s.slip, 4)


# --- where -------------------------------------------------------------------------------------


def test_localisation_finds_a_gap_placed_in_one_window():
    rng = np.random.default_rng(0)
    n_cyc, sigma = 12, 0.02
    resid = rng.normal(0.0, sigma, (n_cyc, GRID.nb))
    centres = GRID.bin_centres
    inside = (centres >= 0.2) & (centres < 0.39)  # window 6 of 8: [0.196, 0.393)
    resid[:, inside] += 0.5  # a systematic 0.5 m/s^2 error there only
    var = np.full_like(resid, sigma**2)
    win = localize.by_window(resid, var, GRID)
    shares = np.array([w["share"] for w in win])
    assert np.argmax(shares) == 5 and shares[5] > 0.95
    assert sum(shares) == pytest.approx(1.0)
    assert win[5]["gap"] == pytest.approx(0.5 * inside.sum() / inside[(centres >= win[5]["from"]) & (centres < win[5]["to"])].size / G, rel=0.05)
    # and by slip level: only the cycles of slip 0.3 carry the error
    slips = np.repeat([0.1, 0.3, 0.5], 4)
    resid2 = rng.normal(0.0, sigma, (n_cyc, GRID.nb))
    resid2[slips == 0.3] += 0.3
    lv = localize.by_slip(resid2, var, slips, heldout_levels=(0.3,))
    assert [x["slip"] for x in lv] == [0.1, 0.3, 0.5]
    assert lv[1]["share"] > 0.95 and lv[1]["heldout_level"] and not lv[0]["heldout_level"]
    assert lv[1]["gap"] == pytest.approx(0.3 / G, rel=0.05)


def test_feature_localisation_points_at_the_amplitude_not_the_onset():
    s = _log([0.3, 0.3, 0.3, 0.3], noise=0.005)
    cs = _cycles(s)
    y = cs.y
    pred = y.copy()
    half = GRID.nb_half
    pred[:, half:] = 9.81 + 0.7 * (y[:, half:] - 9.81)  # model with 30 % less oscillation, same onset
    feats = {f["feature"]: f for f in localize.by_feature(y, pred, cs.slip, GRID, 0.63)}
    assert feats["delta_a"]["mean_diff"] > 0.2  # data Da larger than the model's, in g
    assert feats["onset"]["share"] < 0.05
    top = max(feats.values(), key=lambda f: f["share"])
    assert top["unit"] == "g"
    assert sum(f["share"] for f in feats.values()) == pytest.approx(1.0)


# --- gap, split, verdict -----------------------------------------------------------------------


def test_gap_is_the_error_in_excess_of_noise():
    rng = np.random.default_rng(1)
    sigma = 0.05
    noise = rng.normal(0.0, sigma, (40, GRID.nb))
    var = np.full_like(noise, sigma**2)
    assert gap_of(noise, var) < 0.1 * sigma / G  # pure noise: gap ~ 0
    assert gap_of(noise + 0.2, var) == pytest.approx(0.2 / G, rel=0.03)
    assert shrink_of(0.04, 0.01) == pytest.approx(0.75)
    assert shrink_of(0.0, 0.01) == 0.0


def test_noise_floor_from_repeatability_matches_white_noise():
    s = _log(np.repeat([0.2, 0.4], 4), noise=0.01)
    cs = _cycles(s)
    nf = noise_floor(cs)
    assert nf.source == "repeatability"
    assert nf.sample_g == pytest.approx(0.01, rel=0.1)
    assert nf.repeat_g == pytest.approx(nf.white_bin_g, rel=0.15)


def test_split_holds_out_levels_and_cycles():
    slips = np.repeat(np.round(np.linspace(0.05, 0.5, 10), 3), 5)
    sp = split_cycles(slips)
    assert set(sp.train) | set(sp.test) == set(range(50)) and not set(sp.train) & set(sp.test)
    assert sp.heldout_levels and min(slips) not in sp.heldout_levels and max(slips) not in sp.heldout_levels
    assert not set(np.round(slips[sp.train], 6)) & set(sp.heldout_levels)  # never fitted
    assert len(sp.train_levels) <= 6
    for lv in sp.train_levels:  # some cycles of fitted levels are held out too
        assert np.any(np.round(slips[sp.test], 6) == lv)


def _cand(name, gap, gap_nom, k=2):
    return Candidate(effect=name, params={}, gap_heldout=gap, shrink=shrink_of(gap_nom, gap), n_params=k)


def test_verdict_logic_on_constructed_rankings():
    th = Thresholds(none_factor=1.5, none_floor_g=0.004, min_shrink=0.5, min_gain_factor=1.0)
    noise = 0.004  # bin noise [g]; 'none' below 0.006 g
    # the nominal model explains the data within noise
    r = rank([_cand("stribeck", 0.001, 0.005)], 0.005)
    assert verdict(0.005, r, noise, th) == "none"
    # a clear winner: named, and marked
    gap_nom = 0.05
    r = rank([_cand("imu_lowpass", 0.004, gap_nom), _cand("stribeck", 0.03, gap_nom), _cand("angle_offset", 0.045, gap_nom)],
             gap_nom)
    assert [c.effect for c in r] == ["imu_lowpass", "stribeck", "angle_offset"]
    assert verdict(gap_nom, r, noise, th) == "imu_lowpass" and r[0].named and not r[1].named
    # nothing shrinks the gap enough: unexplained
    r = rank([_cand("imu_lowpass", 0.03, gap_nom), _cand("stribeck", 0.035, gap_nom)], gap_nom)
    assert verdict(gap_nom, r, noise, th) == "unexplained" and not any(c.named for c in r)
    # enough relative shrink but less than one noise level in absolute terms: unexplained
    r = rank([_cand("imu_lowpass", 0.003, 0.0065)], 0.0065)
    assert r[0].shrink >= 0.5
    assert verdict(0.0065, r, noise, th) == "unexplained"
    # ties within 2 % of the nominal gap: fewer parameters first
    r = rank([_cand("stribeck", 0.0100, gap_nom, k=3), _cand("angle_offset", 0.0105, gap_nom, k=1)], gap_nom)
    assert r[0].effect == "angle_offset"


# --- prediction matches the simulated stream ------------------------------------------------------


@pytest.mark.parametrize(
    "effect, values",
    [
        (None, {}),
        ("imu_lowpass", {"cutoff": 6.0, "order": 2}),
        ("angle_offset", {"offset": 0.15}),
        ("touchdown_impact", {"a_sin": -12.0, "a_cos": 0.0, "tau": 0.9, "freq": 11.0}),
        ("time_skew", {"skew": 0.22}),
    ],
)
def test_prediction_at_the_truth_matches_the_stream_within_noise(effect, values):
    from slipest.diagnosis.fit import catalog_params

    soil = {"kS": 1100.0, "phiS": 0.6, "phiD": 0.42, "kappa": 0.33}
    effects = ({"name": effect, **catalog_params(effect, {**soil, "dphi": 0.18, **values}, Geometry())},) if effect else ()
    s = _log([0.15, 0.15, 0.4, 0.4, 0.3, 0.3], soil=soil, effects=effects, noise=0.01)
    cs = _cycles(s)
    ev = Evaluator(cs, np.arange(len(cs)), effect, Geometry())
    truth = {"kS": soil["kS"], "phiS": soil["phiS"], "dphi": soil["phiS"] - soil["phiD"], "kappa": soil["kappa"],
             **values}
    mse, bias = ev.mse(ev.z_of(truth)[None])
    nf = noise_floor(cs)
    excess = math.sqrt(max(mse[0] - np.mean(nf.var_bin), 0.0)) / G
    assert excess < 0.005  # g: within the prediction's resampling error
    assert abs(bias[0]) < 0.01


@pytest.mark.parametrize(
    "effect, fitted, catalog",
    [
        ("contact_damping", {"c_hc": 300.0 * (G / 1100.0), "n_hc": 1.0}, {"b_hc": 300.0, "n_hc": 1.0}),
        ("stribeck", {"vs": 0.03, "delta": 2.0, "viscous": 0.5}, {"vs": 0.03, "delta": 2.0, "viscous": 0.5}),
        ("speed_ripple", {"ripple_c": 0.2 * math.cos(0.6), "ripple_s": 0.2 * math.sin(0.6), "harmonic": 1},
         {"amplitude": 0.2, "phase": 0.6, "harmonic": 1}),
        ("speed_ripple", {"ripple_c": 0.15 * math.cos(-2.0), "ripple_s": 0.15 * math.sin(-2.0), "harmonic": 3},
         {"amplitude": 0.15, "phase": -2.0, "harmonic": 3}),
        ("touchdown_impact", {"a_sin": 9.0 * math.cos(0.8), "a_cos": 9.0 * math.sin(0.8), "tau": 2.5, "freq": 7.0},
         {"amplitude": 9.0, "tau": 2.5, "freq": 7.0, "onset": 0.8}),
        ("touchdown_impact", {"a_sin": -6.0, "a_cos": 3.0, "tau": 0.3, "freq": 2.0},
         {"amplitude": -math.hypot(6.0, 3.0), "tau": 0.3, "freq": 2.0, "onset": math.atan2(-3.0, 6.0)}),
        ("imu_saturation", {"full_scale": 12.5}, {"full_scale": 12.5}),
    ],
)
def test_fit_parametrisation_maps_to_the_catalog_and_predicts_the_stream(effect, fitted, catalog):
    """The fitted form converts to the simulator's parameters, and predicts the simulated stream at the truth."""
    from slipest.diagnosis.fit import catalog_params

    soil = {"kS": 1100.0, "phiS": 0.6, "phiD": 0.42, "kappa": 0.33}
    truth = {"kS": soil["kS"], "phiS": soil["phiS"], "dphi": soil["phiS"] - soil["phiD"], "kappa": soil["kappa"],
             **fitted}
    got = catalog_params(effect, truth, Geometry())
    assert got.keys() == catalog.keys()
    for k, v in catalog.items():
        assert got[k] == pytest.approx(v, rel=1e-9, abs=1e-12)
    # four warm-up cycles: the prediction is the steady train of touchdown transients (tau up to 2.5 s here)
    s = _log([0.3] * 4 + [0.15, 0.15, 0.4, 0.4, 0.3, 0.3], soil=soil, effects=({"name": effect, **catalog},),
             noise=0.01)
    cs = _cycles(s)
    ev = Evaluator(cs, np.arange(4, len(cs)), effect, Geometry())
    mse, bias = ev.mse(ev.z_of(truth)[None])
    excess = math.sqrt(max(mse[0] - np.mean(noise_floor(cs).var_bin), 0.0)) / G
    assert excess < 0.005  # g: within the prediction's resampling error
    assert abs(bias[0]) < 0.01


def test_a_waveform_common_to_every_cycle_is_profiled_out_of_the_nominal_fit():
    """Cycles with one waveform added to every cycle: at the true soil the common-waveform objective sees only
    the noise, where the constant-bias objective sees the waveform, and the profiled waveform is the one added
    (up to a constant). An effect's fit cannot take it."""
    from dataclasses import replace

    soil = StickSlipParams()
    cs = _cycles(_log(np.repeat([0.1, 0.25, 0.4], 3), noise=0.005))
    phase = GRID.bin_centres
    wave = 2.0 * np.sin(7.0 * phase) * np.exp(-3.0 * (phase + 0.8))  # [m/s^2], locked to the leg phase
    moved = replace(cs, y=cs.y + wave)
    idx = np.arange(len(cs.slip))
    truth = {"kS": soil.kS, "phiS": soil.phiS, "dphi": soil.phiS - soil.phiD, "kappa": soil.kappa}
    plain, common = Evaluator(moved, idx, None, Geometry()), Evaluator(moved, idx, None, Geometry(), common=True)
    clean, clean_common = Evaluator(cs, idx, None, Geometry()), Evaluator(cs, idx, None, Geometry(), common=True)
    z = clean.z_of(truth)[None]
    mse_common, bias = common.mse(z)
    assert mse_common[0] == pytest.approx(clean_common.mse(z)[0][0], rel=1e-9)  # the waveform costs nothing
    assert clean_common.mse(z)[0][0] <= clean.mse(z)[0][0]  # a constant is one common waveform
    assert plain.mse(z)[0][0] > clean.mse(z)[0][0] + 0.5 * np.var(wave)
    pred, _ = common.predict(z)
    found = common.common_waveform(pred)[0]
    base = clean_common.common_waveform(pred)[0]  # what the clean cycles leave: noise and the model's own bias
    assert np.sqrt(np.mean((found - base - wave) ** 2)) < 1e-9
    assert bias[0] == pytest.approx(np.mean(found))
    with pytest.raises(ValueError, match="nominal"):
        Evaluator(moved, idx, "imu_lowpass", Geometry(), common=True)


def test_effects_at_their_fit_starts_predict_the_nominal_model():
    """Where an effect's fit starts (FitParam.start) it is off: the nominal model's prediction, for every effect
    that has such a value (Stribeck has none; the low-pass starts at its highest cut-off, not off)."""
    from slipest.model.effects import EFFECTS

    s = _log([0.2, 0.2, 0.45, 0.45], noise=0.0)
    cs = _cycles(s)
    soil = {"kS": 1000.0, "phiS": 0.52, "dphi": 0.17, "kappa": 0.3}
    nominal = Evaluator(cs, np.arange(len(cs)), None, Geometry())
    ref, _ = nominal.predict(nominal.z_of(soil)[None])
    for name in ("contact_damping", "speed_ripple", "touchdown_impact", "imu_saturation", "angle_offset", "time_skew"):
        ev = Evaluator(cs, np.arange(len(cs)), name, Geometry())
        start = {fp.name: fp.start for fp in EFFECTS[name].fit_params}
        pred, ok = ev.predict(ev.z_of({**soil, **start})[None])
        assert ok[0]
        # groups: effects with memory also split the cycles by their previous slip
        np.testing.assert_allclose(pred[0][ev.group_of], ref[0][nominal.group_of], atol=1e-9, err_msg=name)


def test_the_fitted_bias_is_the_data_bias_whatever_bias0():
    """Evaluator.mse's bias is the log's whole accelerometer bias, not that plus the bias assumed before clipping."""
    soil = {"kS": 1100.0, "phiS": 0.6, "phiD": 0.42, "kappa": 0.33}
    s = _log([0.15, 0.15, 0.4, 0.4], soil=soil, effects=({"name": "angle_offset", "offset": 0.1},), noise=0.005)
    cs = _cycles(s)
    cs.y += 0.25  # a 0.25 m/s^2 accelerometer bias
    truth = {"kS": soil["kS"], "phiS": soil["phiS"], "dphi": soil["phiS"] - soil["phiD"], "kappa": soil["kappa"]}
    for bias0 in (0.0, 0.25):
        ev = Evaluator(cs, np.arange(len(cs)), "angle_offset", Geometry(), bias0=bias0)
        _, bias = ev.mse(ev.z_of({**truth, "offset": 0.1})[None])
        assert bias[0] == pytest.approx(0.25, abs=0.01), bias0


# --- CLI and end to end ------------------------------------------------------------------------


def _write_log(path, s, meta):
    from slipest.io.log_csv import LogWriter

    with open(path, "w", newline="") as fh:
        w = LogWriter(fh, metadata=meta, columns=("t", "az", "theta", "slip"))
        w.write(t=s.t, az=s.az, theta=s.theta, slip=s.slip)
        w.flush()


def test_cli_writes_the_json_keys(tmp_path, capsys):
    from slipest.cli.main import main

    s = _log(np.repeat([0.1, 0.25, 0.4], 2), effects=({"name": "imu_saturation", "full_scale": 12.0},))
    log = tmp_path / "real.csv"
    _write_log(log, s, {"nL": "4", "MH": "1", "mF": "0.2", "lS": "0.1763", "kS": "999"})
    out = tmp_path / "report.json"
    tiny = ["--quick", "--effects", "imu_saturation", "--rank-all", "--no-progress"]
    rc = main(["diagnose", str(log), "--json", str(out), "--plots", str(tmp_path / "png")] + tiny)
    assert rc == 0
    doc = json.loads(out.read_text())
    for key in ("verdict", "gap_nominal", "where", "ranking"):
        assert key in doc
    assert set(doc["where"]) >= {"angle_windows", "features", "slip_levels"}
    assert doc["ranking"] and set(doc["ranking"][0]) >= {"effect", "params", "gap_heldout", "shrink"}
    assert doc["ranking"][0]["effect"] == "imu_saturation" and "full_scale" in doc["ranking"][0]["params"]
    assert doc["verdict"] in ("imu_saturation", "none", "unexplained")
    printed = capsys.readouterr().out
    assert "verdict:" in printed and "gap of the nominal model" in printed
    # the leg swaps, read model-free beside the fits: a clean timing
    assert [sw["log"] for sw in doc["swaps"]] == [str(log)]
    assert doc["swaps"][0]["looked"] > 0 and doc["swaps"][0]["off"] is False
    assert f"{log}: the IMU's step at the leg swaps is" in printed or f"{log}: no step found" in printed
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == ["gap_by_angle.png", "ranking.png", "waveforms.png"]
    # a log without the slip column is refused with a clear message
    bare = tmp_path / "bare.csv"
    from slipest.io.log_csv import LogWriter

    with open(bare, "w", newline="") as fh:
        LogWriter(fh, columns=("t", "az", "theta")).write(t=s.t, az=s.az, theta=s.theta)
    with pytest.raises(SystemExit, match="slip"):
        main(["diagnose", str(bare), "--no-progress"])


def test_a_recording_without_reference_slip_is_named_as_such(tmp_path, capsys):
    """A live recording's `slip` column is NaN unless the device sent references: say so, not 'no cycle'."""
    from slipest.cli.main import main
    from slipest.io.log_csv import LogWriter

    s = _log(np.repeat([0.2, 0.3], 3))
    live = tmp_path / "live.csv"
    with LogWriter(live, ("t", "az", "theta", "slip"), metadata={"nL": 4}) as w:  # as slipest.live.Recorder writes
        w.write(s.t, s.az, s.theta, np.full(s.t.size, np.nan))
    with pytest.raises(SystemExit) as exc:
        main(["diagnose", str(live), "--no-progress"])
    msg = str(exc.value)
    assert f"{live}: the reference slip is missing" in msg and "'slip' column" in msg and "all NaN" in msg
    assert "--send-reference" in msg and "slipest replay" in msg
    assert "no complete leg cycle" not in msg
    # a reference only before the first midstance: every complete cycle lacks it
    early = np.where(s.t < 0.5, 0.2, np.nan)
    with pytest.raises(ValueError, match=r"reference slip is missing: no complete leg cycle has a value in the "
                       r"'slip' column at its midstance \(6 no reference slip of 6 cycles\)"):
        cut_cycles(s.t, s.az, s.theta, early, 4)
    # the other failure still points at the angle convention, with the counts
    with pytest.raises(ValueError, match=r"no complete leg cycle in the log \(.*incomplete.* check nL=4"):
        cut_cycles(s.t[:200], s.az[:200], s.theta[:200], s.slip[:200], 4)


def test_end_to_end_names_a_strong_effect():
    soil = {"kS": 900.0, "phiS": 0.58, "phiD": 0.40, "kappa": 0.32}
    slips = np.repeat([0.1, 0.2, 0.3, 0.4, 0.5], 2)
    s = _log(slips, soil=soil, effects=({"name": "angle_offset", "offset": 0.15},), seed=11)
    cs = _cycles(s)
    d = diagnose(cs, Geometry(), effects=["angle_offset", "imu_saturation"], budget=FitBudget().scaled(0.5))
    assert d.verdict == "angle_offset"
    assert d.ranking[0].effect == "angle_offset"
    assert d.ranking[0].params["offset"] == pytest.approx(0.15, abs=0.01)
    assert d.shrink >= 0.7


# --- building blocks of the prediction ---------------------------------------------------------


def test_butterworth_sections_match_scipy_and_start_steady():
    from scipy import signal

    from slipest.model.effects.imu_lowpass import butter_sections, lowpass_batch

    grid = Grid(4)
    fs = 0.63 / grid.dpsi
    rng = np.random.default_rng(2)
    x = 9.81 + rng.normal(0, 1, (3, 1, 800))
    for order in (1, 2, 3, 4):
        y = lowpass_batch(x, grid, 0.63, np.full(3, 7.0), np.full(3, order))
        b, a = signal.butter(order, 7.0, fs=fs)
        for r in range(3):
            ref, _ = signal.lfilter(b, a, x[r, 0], zi=signal.lfilter_zi(b, a) * x[r, 0, 0])
            np.testing.assert_allclose(y[r, 0], ref, atol=1e-9)
        assert len(butter_sections(order, 7.0, fs)) == (order + 1) // 2


def test_expected_clip_is_the_mean_of_noisy_clipped_samples():
    from slipest.model.effects.imu_saturation import expected_clip

    rng = np.random.default_rng(3)
    noise = rng.normal(0.0, 0.2, 400_000)
    for u in (11.0, 11.8, 12.0, 12.3, 13.0, -12.1):
        assert float(expected_clip(np.array(u), 12.0, 0.2)) == pytest.approx(np.mean(np.clip(u + noise, -12, 12)),
                                                                             abs=2e-3)
    np.testing.assert_array_equal(expected_clip(np.array([11.0, 13.0]), 12.0, 0.0), [11.0, 12.0])


def test_impact_train_is_the_sum_over_past_touchdowns():
    from slipest.model.effects import impact_response
    from slipest.model.effects.touchdown_impact import impact_batch

    grid = Grid(4)
    omega, A, tau, f = 0.63, -9.0, 0.8, 13.0
    train = impact_batch(grid, omega, [A], [tau], [f])[0]
    t = grid.time(omega)
    period = 2 * math.pi / (4 * omega)
    explicit = sum(impact_response(t - j * period, A, tau, f) for j in range(-40, 2))
    np.testing.assert_allclose(train, explicit, atol=1e-9)


def test_cycles_binning_wrapped_angles_and_first_cycle():
    s = _log([0.2, 0.3, 0.3, 0.4], noise=0.0)
    cs = _cycles(s)
    assert list(cs.k) == [1, 2, 3] and cs.dropped == 1  # the run's first cycle has no history: dropped
    np.testing.assert_allclose(cs.slip, [0.3, 0.3, 0.4])
    np.testing.assert_allclose(cs.prev_slip, [0.2, 0.3, 0.3])
    assert cs.y.shape == (3, GRID.nb) and np.all(cs.count >= 8)
    np.testing.assert_allclose(cs.omega, 0.63, rtol=1e-3)
    np.testing.assert_allclose(np.nanmean(cs.speed), 0.63, rtol=1e-6)
    wrapped = np.mod(s.theta + math.pi, 2 * math.pi) - math.pi
    cw = cut_cycles(s.t, s.az, wrapped, s.slip, 4)
    np.testing.assert_allclose(cw.y, cs.y, atol=1e-9)
    # the rigid half of a noise-free cycle: 1 g minus the small kinematic l w^2 cos(phi) (~0.007 g)
    rigid = cs.y[:, : GRID.nb_half] / G
    assert np.all(np.abs(rigid - 1.0) < 0.01)


# --- widened parametrisations: ripple harmonic, impact shape, time skew ---------------------------------


def _speed_log(slips, omega, soil=None, effects=(), noise=0.01, seed=3):
    sc = Scenario.per_cycle(StickSlipParams(**(soil or {})), imu={"rate": 1000.0, "noise_g": noise, "seed": seed},
                            slip=slips, omega=omega)
    return simulate_stream(Scenario(cycles=sc.cycles, rate=1000.0, noise_g=noise, seed=seed, effects=tuple(effects)))


def test_a_second_harmonic_ripple_is_named_with_its_harmonic():
    soil = {"kS": 900.0, "phiS": 0.58, "phiD": 0.40, "kappa": 0.32}
    s = _log(np.repeat([0.1, 0.25, 0.4, 0.5], 2), soil=soil,
             effects=({"name": "speed_ripple", "amplitude": 0.2, "phase": 0.5, "harmonic": 2},), seed=5)
    d = diagnose(_cycles(s), Geometry(), effects=["speed_ripple"], budget=FitBudget().scaled(0.5))
    assert d.verdict == "speed_ripple"
    p = d.ranking[0].params
    assert p["harmonic"] == 2
    assert p["amplitude"] == pytest.approx(0.2, abs=0.04)


def test_a_long_ringing_impact_of_another_shape_is_fitted_inside_the_range():
    """tau = 3 s and a 1 rad onset (the catalog draws tau 0.8-1.2 s, onset 0): not pinned at a bound."""
    from slipest.diagnosis.fit import catalog_params, fit, fit_effect
    from slipest.model.effects import EFFECTS

    soil = {"kS": 900.0, "phiS": 0.58, "phiD": 0.40, "kappa": 0.32}
    truth = {"name": "touchdown_impact", "amplitude": 12.0, "tau": 3.0, "freq": 9.0, "onset": 1.0}
    s = _log(np.r_[[0.3] * 4, np.repeat([0.1, 0.3, 0.5], 2)], soil=soil, effects=(truth,), seed=4)
    cs = _cycles(s)
    idx = np.arange(4, len(cs))  # after the train of transients has built up
    budget = FitBudget().scaled(0.5)
    nominal = fit(cs, idx, None, Geometry(), budget=budget)
    r = fit_effect(cs, idx, "touchdown_impact", Geometry(), nominal, budget=budget)
    tau_range = next(p for p in EFFECTS["touchdown_impact"].fit_params if p.name == "tau")
    got = catalog_params("touchdown_impact", r.values, Geometry())
    assert tau_range.lo * 1.5 < got["tau"] < tau_range.hi / 1.5  # well inside the range, not at a bound
    assert 2.0 < got["tau"] < 4.5  # tau is the least determined: one cycle lasts 2.5 s
    assert got["freq"] == pytest.approx(9.0, rel=0.02)
    assert got["onset"] == pytest.approx(1.0, abs=0.1)
    assert got["amplitude"] == pytest.approx(12.0, rel=0.1)
    assert r.mse_train < 0.05 * nominal.mse_train


def test_a_time_skew_at_changing_leg_speed_is_named_and_at_one_speed_left_to_the_angle_offset():
    from slipest.diagnosis.run import equivalent_effects

    soil = {"kS": 900.0, "phiS": 0.58, "phiD": 0.40, "kappa": 0.32}
    omega = np.repeat([0.5, 0.9, 0.6, 1.1, 0.7], 2)
    s = _speed_log(np.repeat([0.1, 0.2, 0.3, 0.4, 0.5], 2), omega, soil=soil,
                   effects=({"name": "time_skew", "skew": 0.2},))
    cs = _cycles(s)
    # each cycle has its speed level's speed, and its previous cycle's
    np.testing.assert_allclose(cs.omega, omega[1:], rtol=2e-3)
    np.testing.assert_allclose(cs.prev_omega, omega[:-1], rtol=2e-3)
    d = diagnose(cs, Geometry(), effects=["time_skew", "angle_offset"], budget=FitBudget().scaled(0.25))
    assert d.verdict == "time_skew" and not d.skipped
    assert d.ranking[0].params["skew"] == pytest.approx(0.2, abs=0.02)
    # at one leg speed the two are the same model: only the angle offset is fitted, and the report says why
    one = equivalent_effects(["angle_offset", "time_skew"], np.full(10, 0.63))
    assert list(one) == ["time_skew"] and "angle_offset" in one["time_skew"]
    assert equivalent_effects(["time_skew"], np.full(10, 0.63)) == {}  # asked for alone: fitted


def test_a_long_ringing_impact_builds_up_from_the_log_start_as_predicted():
    """The train of touchdown transients at tau = 3 s is not steady in the log's first cycles: predicted so."""
    soil = {"kS": 1000.0, "phiS": 0.55, "phiD": 0.40, "kappa": 0.3}
    eff = {"name": "touchdown_impact", "amplitude": 15.0, "tau": 3.0, "freq": 9.0, "onset": 1.0}
    cs = _cycles(_log(np.repeat([0.1, 0.3, 0.5], 3), soil=soil, effects=(eff,)))
    assert list(cs.touchdowns) == list(range(2, 10))  # the stream's first sample is the first touchdown
    ev = Evaluator(cs, np.arange(len(cs)), "touchdown_impact", Geometry())
    truth = {"kS": 1000.0, "phiS": 0.55, "dphi": 0.15, "kappa": 0.3, "a_sin": 15 * math.cos(1.0),
             "a_cos": 15 * math.sin(1.0), "tau": 3.0, "freq": 9.0}
    pred, _ = ev.predict(ev.z_of(truth)[None])
    resid = cs.y - pred[0][ev.group_of]
    excess = np.sqrt(np.maximum(np.mean(resid**2, axis=1) - np.mean(noise_floor(cs).var_bin), 0.0)) / G
    assert np.all(excess < 0.005)  # g, every cycle (a steady train would be 0.09 g off in the first)
    steady = cs.subset(np.arange(len(cs)))
    steady.touchdowns = np.full(len(cs), np.inf)
    ev_s = Evaluator(steady, np.arange(len(cs)), "touchdown_impact", Geometry())
    first = steady.y[0] - ev_s.predict(ev_s.z_of(truth)[None])[0][0][ev_s.group_of][0]
    assert np.sqrt(np.mean(first**2)) / G > 0.03


def test_speed_levels_group_jittered_speeds_and_split_ramps():
    from slipest.diagnosis.cycles import speed_levels

    rng = np.random.default_rng(0)
    steady = 0.63 * (1 + 1e-3 * rng.normal(size=30))
    assert len(set(speed_levels(steady))) == 1
    lab = speed_levels(np.r_[steady, 0.9 * (1 + 1e-3 * rng.normal(size=5))])
    assert len(set(lab)) == 2 and len(set(lab[:30])) == 1
    ramp = np.linspace(0.5, 1.0, 40)
    lab = speed_levels(ramp)
    for v in set(lab):  # no level wider than twice the tolerance
        member = ramp[lab == v]
        assert np.log(member.max() / member.min()) <= 0.04 + 1e-12


def test_solve_amplitudes_recovers_two_columns_and_the_bias():
    s = _log([0.2, 0.2, 0.4, 0.4], noise=0.0)
    cs = _cycles(s)
    ev = Evaluator(cs, np.arange(len(cs)), None, Geometry())
    rng = np.random.default_rng(1)
    P, G, nb = 3, ev.n_groups, GRID.nb
    m0 = rng.normal(size=(P, G, nb))
    h1, h2 = rng.normal(size=(P, G, nb)), rng.normal(size=(P, G, nb))
    ev.g_mean = m0[1] + 0.7 + 2.0 * h1[1] - 1.5 * h2[1]  # candidate 1 is exact
    from slipest.model.effects import FitParam

    a1, a2 = ev.solve_amplitudes((FitParam("a1", "-", -5, 5), FitParam("a2", "-", -5, 5)), m0, (h1, h2))
    assert a1[1] == pytest.approx(2.0) and a2[1] == pytest.approx(-1.5)
    assert ev.last_linear["a1"][1] == pytest.approx(2.0)
    one = ev.solve_amplitude(FitParam("a1", "-", -1, 1), m0, h1)  # one column: clipped to its range
    assert np.all(np.abs(one) <= 1.0)


def test_per_edge_offsets_equal_a_constant_offset_when_constant():
    from slipest.diagnosis.predict import bin_average_batch

    x = np.random.default_rng(2).normal(size=(2, 3, GRID.n_ext))
    off = np.array([0.1, -0.05])
    np.testing.assert_allclose(bin_average_batch(GRID, x, np.repeat(off[:, None], GRID.nb + 1, axis=1)),
                               bin_average_batch(GRID, x, off), atol=1e-12)


def test_a_coarse_encoder_is_interpolated_between_its_count_changes():
    from slipest.dequantize import dequantize_log

    s = _log([0.2, 0.3, 0.3, 0.4], noise=0.005)
    step = 2 * math.pi / 200  # 200 counts per revolution: the count changes every ~10 samples at 1 kHz
    coarse = np.round(s.theta / step) * step
    fine = dequantize_log(s.t, coarse)
    assert np.max(np.abs(coarse - s.theta)) > 0.4 * step
    assert np.max(np.abs(fine - s.theta)) < 0.02 * step
    np.testing.assert_array_equal(dequantize_log(s.t, s.theta), s.theta)  # a fine encoder: unchanged
    # the cycles of the coarse log are nearly those of the fine one (the diagnosis found 15-40 mg gaps before)
    cq, cs = cut_cycles(s.t, s.az, coarse, s.slip, 4), _cycles(s)
    assert np.sqrt(np.mean((cq.y - cs.y) ** 2)) / G < 0.003


def test_the_per_log_row_reads_an_encoder_offset_and_leaves_its_settling_out(tmp_path):
    from dataclasses import replace

    from slipest.offline.diagnose import DiagnoseOptions, diagnose_rows
    from slipest.swap_timing import swap_summary

    s = _log(np.repeat([0.1, 0.25, 0.4], 4))
    ahead = replace(s, theta=s.theta + 0.05)  # an encoder zero 0.05 rad off: its swaps come early
    sw = swap_summary(ahead.t, ahead.az, ahead.theta, 4)
    assert sw.off and sw.settled >= 5 and math.isfinite(sw.settling)  # a settling is read, at the wrong time
    log = tmp_path / "ahead.csv"
    _write_log(log, ahead, {"nL": "4"})
    row = diagnose_rows(log, DiagnoseOptions(effects=("imu_saturation",), quick=True))[0]
    assert row["error"] == "" and row["swap_steps"] >= 5
    assert row["swap_offset_ms"] == pytest.approx(1000 * sw.offset_s) and row["swap_offset_ms"] > 12.0
    assert math.isnan(row["settling"])  # read at the encoder's swap, which is off: not reported
