"""A known soil (`--kS --phiS --phiD`, `SlipEstimator(soil=...)`) is checked as the learnt one is: a soil
outside the soils the model covers is refused (the surrogate would extrapolate, or the prior pin a
partial soil to the grid's edge), and each cycle's features are tested against the model on the soil
given, so a wrong soil gives wider intervals or no estimate, not confident wrong slips."""

from __future__ import annotations

import math

import pytest

from slipest import SlipEstimator
from slipest.cli.main import main
from slipest.io.log_csv import read_log
from tests.log_makers import stream, write_csv


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """12 clean cycles at slip 0.25 on kS 1000 N/m, phiS 0.52, phiD 0.35 rad (1 kHz, 0.01 g)."""
    s, sc = stream(12, seed=2)
    return write_csv(tmp_path_factory.mktemp("known") / "drive.csv", s, sc)


@pytest.mark.parametrize("soil, named", [({"kS": 1e6, "phiS": 0.52, "phiD": 0.35}, "kS=1e+06 N/m (covered: 500-1500)"),
                                         ({"kS": 3000.0}, "kS=3000 N/m (covered: 500-1500)"),
                                         ({"kS": 1000.0, "phiS": 1.2, "phiD": 0.35}, "phiS=1.2 rad"),
                                         ({"kS": 1000.0, "dphi": 0.5}, "dphi=0.5 rad")])
def test_a_known_soil_outside_what_the_model_covers_is_refused_naming_it(soil, named, drive, capsys):
    with pytest.raises(ValueError, match="outside the soils the model covers") as err:
        SlipEstimator(soil=soil)
    assert named in str(err.value)
    args = [a for k, v in soil.items() for a in (f"--{k}", str(v))]
    if set(soil) == {"kS"}:
        args += ["--use-reference"]  # a partial soil needs the reference to learn the rest
    assert main(["replay", str(drive), *args]) == 2
    assert named in capsys.readouterr().err


def test_a_wrong_known_soil_is_said_to_be_off_the_model_not_estimated_confidently(drive, capsys):
    log = read_log(drive)
    est = SlipEstimator(soil={"kS": 1400.0, "phiS": 0.3, "phiD": 0.25})
    got = est.push_many(log.t, log.az, log.theta) + est.finish()
    assert len(got) == 12
    assert all(e.misfit > 1.0 for e in got)  # every cycle tested against the model, and off it
    assert main(["replay", str(drive), "--kS", "1400", "--phiS", "0.3", "--phiD", "0.25"]) == 0
    assert "the data do not fit the estimator's model (12 of 12 cycles off it)" in capsys.readouterr().err
    far = SlipEstimator(soil={"kS": 600.0, "phiS": 0.8, "phiD": 0.5})  # so far that nothing explains it
    rows = far.push_many(log.t, log.az, log.theta) + far.finish()
    assert all(e.quality == "misfit" and math.isnan(e.slip) for e in rows)


def test_the_right_known_soil_explains_clean_cycles(drive):
    log = read_log(drive)
    est = SlipEstimator(soil={"kS": 1000.0, "phiS": 0.52, "phiD": 0.35})
    got = est.push_many(log.t, log.az, log.theta) + est.finish()
    assert len(got) == 12 and sum(e.misfit == 1.0 for e in got) >= 11
    assert all(abs(e.slip - 0.25) < 3 * e.slip_std + 0.02 for e in got)
