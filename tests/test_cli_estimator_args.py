"""The estimator options shared by `slipest replay` and the live commands."""

import argparse
import re

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
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(InverseModelError, match="bad.json: expected a JSON object"):
        model_from_args(_parse(["--model", str(bad)]))
    shipped = tmp_path / "copy.json"
    from slipest.inverse.surrogate import save_inverse_model

    save_inverse_model(load_inverse_model(), shipped)
    assert model_from_args(_parse(["--model", str(shipped)])).degree == load_inverse_model().degree


def test_live_command_refuses_a_bad_model_before_listening(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["can", "--interface", "virtual", "--channel", "t", "--model", str(bad), "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert re.search(r"ERROR slipest\.can: .*bad\.json: not valid JSON", err), err
    assert "listening" not in err
