"""The suite's one set-up: slipest's compiled kernels are on disk before any test starts.

Many tests run the virtual device and the estimator as subprocesses (real
ptys, real buses).  On a cold numba cache (a fresh clone: CI, a new user)
each of those subprocesses compiled the kernels itself: about 55 s for the
device and 25 s for the estimator on an idle 2-core machine, and 135 s before
a device streamed with four CPU-bound processes on the 2 cores.  A live run's ``--duration``
guard then ran out before its device had streamed a frame, and the device
waited for a reader that was gone.  Compiling once here, before pytest-xdist
starts its workers, puts every subprocess on the cache (the device then
streams after about 8 s under the same load).
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: Two commands that compile what the suite's subprocesses run: the device generating a two-wheel feed (onto
#: an in-process virtual CAN bus, so it needs no reader), and a live run's warm-up, which pushes synthetic leg
#: cycles through the estimator before it reads the (silent) bus.  Run side by side, one per core.
WARM_COMMANDS = (
    [sys.executable, "-m", "firmware_sim", "can", "-i", "virtual", "-c", "slipest-warm-up", "--cycles", "2",
     "--wheels", "2", "--speed", "0", "--quiet"],
    [sys.executable, "-m", "slipest", "can", "-i", "virtual", "-c", "slipest-warm-up", "--duration", "0.3",
     "--format", "none", "--log-level", "WARNING"],
)
WARM_TIMEOUT = 900.0


def pytest_sessionstart(session) -> None:
    """Compile the kernels once, in the main process only (pytest-xdist workers find them on disk).

    A warm-up that fails is reported on the terminal, and the session goes on: the tests of what failed
    fail on their own, with their own messages."""
    if hasattr(session.config, "workerinput"):
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    say = reporter.write_line if reporter is not None else (lambda text, **_: print(text, file=sys.stderr))
    say("conftest: compiling slipest's kernels before the tests (a minute or two on a fresh clone, seconds when "
        "they are on disk)")
    t0 = time.monotonic()
    procs = [subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for cmd in WARM_COMMANDS]
    failures = []
    for cmd, proc in zip(WARM_COMMANDS, procs):
        try:
            _, err = proc.communicate(timeout=max(1.0, WARM_TIMEOUT - (time.monotonic() - t0)))
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
            failures.append(f"{' '.join(cmd[1:4])}: still running after {WARM_TIMEOUT:.0f} s, killed")
            continue
        if proc.returncode != 0:
            failures.append(f"{' '.join(cmd[1:4])}: exit status {proc.returncode}: {err.strip()[-2000:]}")
    for text in failures:
        say(f"conftest: compiling the kernels before the tests failed: {text}", red=True)
    if not failures:
        say(f"conftest: kernels ready in {time.monotonic() - t0:.0f} s")
