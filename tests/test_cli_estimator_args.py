"""The estimator options shared by `slipest replay` and the live commands."""

import argparse
import re

import numpy as np
import pytest

from slipest.cli.estimator_args import add_estimator_arguments, model_from_args, soil_from_args
from slipest.cli.main import main
from slipest.inverse.surrogate import InverseModelError, load_inverse_model


def _parse(argv):
    p = argparse.ArgumentParser()
    add_estimator_arguments(p)
    return p.parse_args(argv)


def test_soil_and_model_from_the_options(tmp_path):
    args = _parse(["--kS", "900", "--dphi", "0.2"])
    assert soil_from_args(args) == {"kS": 900.0, "dphi": 0.2}
    assert model_from_args(args) is None  # the shipped one
    assert soil_from_args(_parse([])) == {}
    bad = tmp_path / "bad.npz"
    bad.write_text("[1, 2]")
    with pytest.raises(InverseModelError, match="bad.npz: not an inverse model file"):
        model_from_args(_parse(["--model", str(bad)]))
    shipped = tmp_path / "copy.npz"
    from slipest.inverse.surrogate import save_inverse_model

    save_inverse_model(load_inverse_model(), shipped)
    copy = model_from_args(_parse(["--model", str(shipped)]))
    assert np.array_equal(copy.coef, load_inverse_model().coef) and copy.meta == load_inverse_model().meta


def test_live_command_refuses_a_bad_model_before_listening(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["can", "--interface", "virtual", "--channel", "t", "--model", str(bad), "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert re.search(r"ERROR slipest\.can: .*bad\.json: not an inverse model file", err), err
    assert "listening" not in err


@pytest.mark.parametrize("soil, given", [([], "no soil option"), (["--kS", "1000"], "--kS"),
                                         (["--kS", "1000", "--phiS", "0.5"], "--kS, --phiS"),
                                         (["--dphi", "0.2"], "--dphi")])
def test_eq515_says_in_option_names_what_it_needs(soil, given):
    with pytest.raises(ValueError) as err:
        soil_from_args(_parse(["--method", "eq515", *soil]))
    assert str(err.value) == ("--method eq515 needs --kS, and --dphi (or --phiS with --phiD) or --use-reference to "
                              f"learn dphi from the reference slip (given: {given})")


def test_eq515_runs_with_what_its_help_says_is_enough(tmp_path, capsys):
    from slipest.inverse.base import Soil
    from slipest.inverse.eq515 import Eq515Tracker
    from tests.log_makers import stream, write_csv

    s, sc = stream(n_cycles=3)
    log = str(write_csv(tmp_path / "sim.csv", s, sc))
    enough = [["--kS", "1000", "--dphi", "0.17"], ["--kS", "1000", "--phiS", "0.52", "--phiD", "0.35"],
              ["--kS", "1000", "--phiD", "0.35", "--dphi", "0.17"], ["--kS", "1000", "--use-reference"]]
    for soil in enough:
        assert main(["replay", log, "--method", "eq515", *soil]) == 0, soil
        out, err = capsys.readouterr()
        assert ",ok," in out and "method eq515" in err, soil
        args = _parse(["--method", "eq515", *[a for a in soil if a != "--use-reference"]])
        args.use_reference = "--use-reference" in soil
        Eq515Tracker.from_calibration(Soil.from_args(**soil_from_args(args)), args.use_reference)  # agrees
    assert main(["replay", log, "--method", "eq515", "--kS", "1000"]) == 2
    assert "slipest replay: --method eq515 needs --kS, and --dphi" in capsys.readouterr().err
    # the help says it, with the one leg speed its calibration knows
    p = argparse.ArgumentParser()
    add_estimator_arguments(p)
    help_text = next(a.help for a in p._actions if a.dest == "method") % {}  # as argparse expands it
    assert "needs --kS, and --dphi (or --phiS with --phiD) or --use-reference" in help_text
    assert "one leg speed" in help_text and "0.63 rad/s" in help_text and "'speed'" in help_text
