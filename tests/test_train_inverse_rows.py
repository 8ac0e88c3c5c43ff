"""tools/train_inverse.py --rows: simulated rows kept with their features' names and simulation time, reused to
the bit, and refused when slipest.features computes other features than the file holds."""

import sys
from pathlib import Path

import numpy as np
import pytest

from slipest.features import FEATURE_NAMES
from slipest.inverse.surrogate import load_inverse_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import train_inverse  # noqa: E402

TINY = ["--nodes", "2", "--span", "0.57", "0.69", "--n-node", "1500", "--schedule", "tiny", "--n-val", "60",
        "--n-check", "5"]


def test_rows_are_kept_reused_and_refused_when_the_features_differ(tmp_path, capsys):
    rows = tmp_path / "rows.npz"
    assert train_inverse.main(TINY + ["--rows", str(rows), "--out", str(tmp_path / "a.npz")]) == 0
    kept = np.load(rows)
    assert tuple(str(n) for n in kept["features"]) == FEATURE_NAMES
    assert kept["f0"].shape[1] == len(FEATURE_NAMES) and float(kept["simulate_s"]) > 0.0

    assert train_inverse.main(TINY + ["--rows", str(rows), "--out", str(tmp_path / "b.npz")]) == 0
    a, b = load_inverse_model(tmp_path / "a.npz"), load_inverse_model(tmp_path / "b.npz")
    # the estimator's settings are written into the model: the slip tempering, and the gross misfit that keeps
    # the threshold's squared distance whatever the model's misfit level
    from slipest.estimator import GROSS_DISTANCE

    stated = a.meta["estimator"]
    assert stated["slip_temper"] == train_inverse.SLIP_TEMPER
    assert abs(stated["gross_misfit"] * a.meta["fit_level"] - GROSS_DISTANCE) <= 0.05 * a.meta["fit_level"]
    np.testing.assert_array_equal(a.coef, b.coef)
    np.testing.assert_array_equal(a.cov_coef, b.cov_coef)
    # the reused file's simulation time is the one it was simulated in, not the time it took to read it
    assert b.meta["training"]["simulate_s"] == round(float(kept["simulate_s"]))
    capsys.readouterr()

    # rows of an older feature set (one column fewer, no names) are refused by name, not misread
    old = tmp_path / "old.npz"
    data = {k: kept[k] for k in kept.files if k not in ("features", "simulate_s")}
    data = {k: (v[:, :-1] if k.startswith("f") else v) for k, v in data.items()}
    np.savez(old, **data)
    with pytest.raises(SystemExit) as e:
        train_inverse.main(TINY + ["--rows", str(old), "--out", str(tmp_path / "c.npz")])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "old.npz holds other features" in err and "simulate again" in err
    assert not (tmp_path / "c.npz").exists()


def test_added_features_and_the_slip_tempering_go_into_the_model_and_bad_ones_are_refused(tmp_path, capsys):
    from slipest.inverse.surrogate import MODEL_FEATURES

    out = tmp_path / "m.npz"
    rows = ["--rows", str(tmp_path / "r.npz"), "--add-features", "delta_a,stick_mean"]
    assert train_inverse.main(TINY + rows + ["--out", str(out)]) == 0
    m = load_inverse_model(out)
    assert m.features == tuple(MODEL_FEATURES) + ("delta_a", "stick_mean")
    assert m.coef.shape[-1] == len(m.features) and m.cov_coef.shape[-1] == len(m.features)
    assert train_inverse.main(TINY + rows + ["--slip-temper", "0.5", "--out", str(out)]) == 0
    # the same path written again is read again (load_inverse_model's cache is keyed by the file's state)
    assert load_inverse_model(out).meta["estimator"]["slip_temper"] == 0.5
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        train_inverse.main(TINY + ["--slip-temper", "0", "--out", str(tmp_path / "x.npz")])
    assert e.value.code == 2 and "--slip-temper" in capsys.readouterr().err
    for bad in ("bogus", "onset", "spec_skew", "delta_a,delta_a"):
        with pytest.raises(SystemExit) as e:
            train_inverse.main(TINY + ["--add-features", bad, "--out", str(tmp_path / "x.npz")])
        assert e.value.code == 2 and "--add-features" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()
