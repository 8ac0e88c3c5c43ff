"""The honesty and calibration tools' ``--kappa``: the same draw with the rover's leg set to a given kappa."""

from __future__ import annotations

import numpy as np
import pytest

from tools import bench_calibration, check_uncalibrated


def test_check_uncalibrated_sets_every_cycles_kappa_after_the_same_draw():
    drawn = check_uncalibrated.draw_log("none", np.random.default_rng(5), 0.1, 0.45)
    fixed = check_uncalibrated.draw_log("none", np.random.default_rng(5), 0.1, 0.45, kappa=0.3)
    (sc0, soil0, *_), (sc1, soil1, *_) = drawn, fixed
    assert soil0["kappa"] != 0.3 and 0.25 <= soil0["kappa"] <= 0.40
    assert {c.kappa for c in sc0.cycles} == {soil0["kappa"]}
    assert {c.kappa for c in sc1.cycles} == {0.3} and soil1["kappa"] == 0.3
    # the same soil, slips and IMU draw otherwise
    assert [c.slip for c in sc0.cycles] == [c.slip for c in sc1.cycles]
    assert {k: v for k, v in soil0.items() if k != "kappa"} == {k: v for k, v in soil1.items() if k != "kappa"}
    assert (sc0.seed, sc0.rate, sc0.noise_g) == (sc1.seed, sc1.rate, sc1.noise_g)


def test_check_uncalibrated_help_names_kappa_and_a_kappa_out_of_range_is_refused(capsys):
    with pytest.raises(SystemExit):
        check_uncalibrated.main(["--help"])
    assert "--kappa" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        check_uncalibrated.main(["--kappa", "1.5", "--cases", "1"])
    assert "--kappa 1.5 must be in [0, 1]" in capsys.readouterr().err


def test_bench_calibration_leg_only_rover_and_its_kappa():
    effects, params, tb_soils, drive_soils, change = bench_calibration.draw_rover("none", np.random.default_rng(3))
    assert effects == () and params == {} and change == 0.0
    assert len(tb_soils) == 2 and len(drive_soils) == bench_calibration.DRIVES
    assert bench_calibration.stages_of("none", params) == []
    rng = np.random.default_rng(1)
    sc = bench_calibration.testbed_scenario(rng, tb_soils[0], 0.38)
    assert {c.kappa for c in sc.cycles} == {0.38}
    sc = bench_calibration.drive_scenario(rng, drive_soils[0])
    assert {c.kappa for c in sc.cycles} == {bench_calibration.KAPPA}


def test_bench_calibration_refuses_a_kappa_out_of_range_and_an_unknown_rover(capsys):
    with pytest.raises(SystemExit):
        bench_calibration.main(["--effects", "none", "--kappa", "-0.1"])
    assert "--kappa" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench_calibration.main(["--effects", "no_such_effect"])
    assert "none" in capsys.readouterr().err  # the leg-only rover is listed among the known ones
