#!/usr/bin/env python
"""Smoke test of an installed slipest, run from outside the source tree (packaging mistakes show here).

The test suite imports ``slipest`` from the source tree, so a module or a
data file missing from the wheel, a broken entry point or a missing
``py.typed`` goes unseen there.  This script checks the package as it is
installed in the environment of the Python that runs it, in processes
started from an empty temporary directory without ``PYTHONPATH``:

* ``slipest`` is imported from the environment, not from this source tree;
* the ``slipest`` and ``firmware-sim`` commands and ``python -m slipest``
  answer ``--version``; ``from slipest import SlipEstimator`` works;
* the data files (calibration, inverse model, DBC) and ``py.typed`` are
  installed and load; the licence is in the distribution's metadata;
* ``slipest simulate ... | slipest replay - --truth`` estimates every
  complete cycle (the first run after an install: kernels compiled).

    python tools/check_installed.py        # .ci/run does, after installing the wheel

Exits 1 naming the first check that failed.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

CHECK_PACKAGE = """
import importlib.metadata as md
from importlib import resources
import slipest
from slipest import SlipEstimator
from slipest.calibration import load_calibration
from slipest.inverse.surrogate import load_inverse_model
from slipest.io.can_messages import CanDecoder
files = resources.files("slipest")
for name in ("py.typed", "data/calibration.json", "data/inverse_model.npz", "io/data/slipest.dbc"):
    assert files.joinpath(name).is_file(), f"{name} is not installed"
load_calibration(); load_inverse_model(); CanDecoder()
meta = md.metadata("slipest")
assert meta["License-Expression"] == "MIT", meta["License-Expression"]
assert any(str(f).endswith("LICENSE") for f in md.files("slipest")), "LICENSE is not in the distribution"
assert SlipEstimator.__module__ == "slipest.online"
print(slipest.__file__)
"""


def fail(what: str, detail: str = "") -> None:
    print(f"check_installed: FAILED: {what}" + (f"\n{detail.rstrip()}" if detail else ""), file=sys.stderr)
    raise SystemExit(1)


def run(cmd: list[str], cwd: Path, env: dict, stdin=None) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, cwd=cwd, env=env, input=stdin, capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        fail(f"{' '.join(cmd)} exited {proc.returncode}", proc.stderr[-3000:])
    return proc


def main() -> int:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    with tempfile.TemporaryDirectory(prefix="slipest-installed-") as tmp:
        cwd = Path(tmp)
        where = run([sys.executable, "-c", CHECK_PACKAGE], cwd, env).stdout.strip()
        if Path(where).resolve().is_relative_to(ROOT):
            fail(f"slipest was imported from the source tree ({where}): install it (pip install .) and run this "
                 "outside an editable install")
        print(f"check_installed: slipest imported from {where}; data files, py.typed and the licence installed")
        for cmd, want in (([str(BIN / "slipest"), "--version"], "slipest "),
                          ([sys.executable, "-m", "slipest", "--version"], "slipest "),
                          ([str(BIN / "firmware-sim"), "--version"], "firmware-sim ")):
            out = run(cmd, cwd, env).stdout.strip()
            if not out.startswith(want):
                fail(f"{' '.join(cmd)} printed {out!r}")
        print("check_installed: slipest, python -m slipest and firmware-sim answer --version")
        log = run([str(BIN / "slipest"), "simulate", "--slip", "0.3", "--cycles", "6", "--noise", "0.01", "--seed",
                   "2"], cwd, env).stdout
        t0 = time.perf_counter()
        replay = run([str(BIN / "slipest"), "replay", "-", "--truth"], cwd, env, stdin=log)
        elapsed = time.perf_counter() - t0
        rows = [line.split(",") for line in replay.stdout.splitlines()[1:]]
        quality = replay.stdout.splitlines()[0].split(",").index("quality")
        ok = sum(1 for r in rows if r[quality] == "ok")
        if len(rows) != 6 or ok != 6 or "truth: slip RMSE" not in replay.stderr:  # 6 cycles driven: 6 estimates
            fail(f"slipest simulate | slipest replay -: {ok} cycles estimated of {len(rows)}", replay.stderr)
        print(f"check_installed: slipest simulate | slipest replay - --truth: {ok} of {len(rows)} cycles estimated "
              f"({elapsed:.1f} s, kernels compiled on this first run); "
              + replay.stderr.strip().splitlines()[-1])
    print("check_installed: ok")
    return 0


if __name__ == "__main__":
    sys.exit(main())
