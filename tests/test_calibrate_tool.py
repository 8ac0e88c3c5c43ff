"""tools/calibrate.py leaves the tracked calibration file alone when a rerun changes nothing but its
time and command line of writing and float noise."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import calibrate  # noqa: E402  (tools/calibrate.py)

from slipest.calibration import load_calibration  # noqa: E402


def _nudge(node, by: float):
    """Every float of a JSON document times (1 + by)."""
    if isinstance(node, dict):
        return {k: _nudge(v, by) for k, v in node.items()}
    if isinstance(node, list):
        return [_nudge(v, by) for v in node]
    return node * (1 + by) if isinstance(node, float) else node


def test_a_rerun_with_only_noise_and_a_new_time_leaves_the_file_untouched(tmp_path):
    shipped = load_calibration()
    path = tmp_path / "calibration.json"
    assert calibrate.write_calibration(shipped, path)  # no file yet: written
    text = path.read_text()
    mtime = path.stat().st_mtime_ns
    rerun = _nudge(shipped, 1e-11)
    rerun["created_utc"] = "2031-01-01T00:00:00+00:00"
    assert rerun["eq515"]["amu"] != shipped["eq515"]["amu"]
    assert not calibrate.write_calibration(rerun, path)
    assert path.read_text() == text and path.stat().st_mtime_ns == mtime


def test_a_real_change_is_written(tmp_path):
    shipped = load_calibration()
    path = tmp_path / "calibration.json"
    calibrate.write_calibration(shipped, path)
    changed = _nudge(shipped, 1e-6)  # far above float noise
    assert calibrate.write_calibration(changed, path)
    assert json.loads(path.read_text())["eq515"]["amu"] == changed["eq515"]["amu"]
    other = copy.deepcopy(changed)
    other["created_by"] = "python tools/calibrate.py --write-package-data -o elsewhere"  # the same calibration
    assert not calibrate.write_calibration(other, path)
    other["grid"]["n_failed"] = 1
    assert calibrate.write_calibration(other, path)
    del other["grid"]["n_failed"]
    assert not calibrate.same_calibration(other, changed)  # a key missing is a change


def test_the_comparison():
    same = calibrate.same_calibration
    assert same({"a": [1.0, 2, "x"], "created_utc": "then"}, {"a": [1.0 + 1e-12, 2, "x"], "created_utc": "now"})
    assert not same({"a": [1.0, 2]}, {"a": [1.0, 2, 3]})
    assert not same({"a": 1.0}, {"a": 1.0 + 1e-8})
    assert not same({"a": True}, {"a": 1})
    assert not same({"a": None}, {"a": 0.0})
    assert same({"a": 0.0}, {"a": 1e-11}) and not same({"a": 0.0}, {"a": 1e-9})  # absolute floor near zero
