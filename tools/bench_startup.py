#!/usr/bin/env python
"""Start-up of ``slipest replay``: cold (kernels compiled) and warm (loaded from numba's cache).

Copies the package out of the source tree, byte-compiled as pip installs it
but without numba's cache, twice: one copy writable (numba caches beside the
source, as in a user's virtual environment), one read-only (as a system or
image install: the cache goes to ``$XDG_CACHE_HOME/slipest/numba``, chosen by
:mod:`slipest.numba_cache`).
For each, times ``python -m slipest replay LOG -o /dev/null`` on a small
simulated log: the first run (cold: empty cache) and ``--runs`` more
(warm), each in a fresh process with only the copy on ``PYTHONPATH``, run
from a temporary directory with its own ``HOME`` and ``XDG_CACHE_HOME``.
It checks that the read-only copy stays untouched and that warm runs write
nothing to the cache (nothing recompiled), and prints, as baselines timed
in the same session, an empty interpreter and the imports numba needs
anyway (numpy, scipy.linalg, numba).  Target (issue 14): warm under 2 s.

A read-only copy: ``chmod -R a-w`` for a normal user; root ignores
permissions, so as root the copy is bind-mounted read-only in a private
mount namespace (``unshare -m``, needs CAP_SYS_ADMIN; adds about 5 ms).

    python tools/bench_startup.py [--runs 5] [--cycles 10]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Run ``$@`` with ``$0`` bind-mounted read-only over itself (in a private mount namespace).
_RO_MOUNT = 'mount --bind "$0" "$0" && mount -o remount,ro,bind "$0" "$0" && exec "$@"'


def copy_package(dest: Path, compiled: bool = False) -> Path:
    """A copy of the source tree's ``slipest`` package (without caches) under ``dest``; returns ``dest``.
    ``compiled``: with its bytecode (``.pyc``), as pip installs a package."""
    shutil.copytree(ROOT / "slipest", dest / "slipest", ignore=shutil.ignore_patterns("__pycache__"))
    if compiled:
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(dest / "slipest")], check=True)
    return dest


def read_only_wrapper(path: Path) -> tuple[list[str] | None, str]:
    """How to run a command with ``path`` read-only: (prefix of the command line, how); prefix None
    (with the reason) when this machine offers no way.  A normal user's copy is made read-only here."""
    if os.geteuid() != 0:
        for p in [path, *path.rglob("*")]:
            p.chmod(p.stat().st_mode & ~0o222)
        return [], "chmod -R a-w"
    if shutil.which("unshare") is None:
        return None, "root ignores file permissions and unshare(1) is missing"
    probe = subprocess.run(["unshare", "-m", "sh", "-c", _RO_MOUNT + " 2>/dev/null", str(path), "sh", "-c",
                            f'! touch "{path}/.probe" 2>/dev/null'], capture_output=True)
    if probe.returncode != 0:
        return None, "root ignores file permissions and cannot bind-mount read-only here (unshare -m failed)"
    return ["unshare", "-m", "sh", "-c", _RO_MOUNT, str(path)], "read-only bind mount (unshare -m)"


def make_writable(path: Path) -> None:
    """Undo :func:`read_only_wrapper`'s chmod (so the copy can be deleted)."""
    for p in [path, *path.rglob("*")]:
        p.chmod(p.stat().st_mode | 0o200)


#: The files of numba's cache: an index per function and its compiled data.
NUMBA_FILES = (".nbi", ".nbc")


def files(path: Path, suffixes: tuple[str, ...] = ()) -> dict[str, int]:
    """Every file under ``path`` (ending in one of ``suffixes``, if given) -> its modification time [ns]."""
    if not path.exists():
        return {}
    return {str(p): p.stat().st_mtime_ns for p in path.rglob("*")
            if p.is_file() and (not suffixes or p.name.endswith(suffixes))}


def environment(site: Path, work: Path) -> dict:
    """A process environment that sees only the copy at ``site``, with its own home and cache under ``work``."""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CACHE_DIRECTORY", "PYTHONPATH")}
    env.update(PYTHONPATH=str(site), HOME=str(work / "home"), XDG_CACHE_HOME=str(work / "xdg"))
    (work / "home").mkdir(parents=True, exist_ok=True)
    return env


def timed(cmd: list[str], env: dict, cwd: Path) -> float:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"bench_startup: {' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return elapsed


def measure(name: str, prefix: list[str], site: Path, work: Path, log: Path, runs: int, cache: Path) -> dict:
    env = environment(site, work)
    where = subprocess.run(prefix + [sys.executable, "-c", "import slipest, os; print(slipest.__file__); "
                                     "print(os.environ.get('NUMBA_CACHE_DIR', ''))"],
                           env=env, cwd=work, capture_output=True, text=True, check=True).stdout.split("\n")
    if not where[0].startswith(str(site)):
        raise SystemExit(f"bench_startup: {name}: slipest imported from {where[0]}, not from the copy {site}")
    cmd = prefix + [sys.executable, "-m", "slipest", "replay", str(log), "-o", os.devnull]
    package_before = files(site)
    cold = timed(cmd, env, work)
    cache_after_cold = files(cache, NUMBA_FILES)
    warm = [timed(cmd, env, work) for _ in range(runs)]
    cache_after_warm = files(cache, NUMBA_FILES)
    return {
        "name": name, "cold": cold, "warm": warm, "numba_cache_dir": where[1] or "(numba's default: in-tree)",
        "cache_files": len(cache_after_cold),
        "written_warm": sum(1 for k, v in cache_after_warm.items() if cache_after_cold.get(k) != v),
        "package_written": sum(1 for k, v in files(site).items() if package_before.get(k) != v),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="warm runs per copy (default 5)")
    ap.add_argument("--cycles", type=int, default=10, help="leg cycles in the replayed log (default 10)")
    args = ap.parse_args(argv)
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    with tempfile.TemporaryDirectory(prefix="slipest-startup-") as tmp:
        tmp = Path(tmp)
        log = tmp / "run.csv"
        subprocess.run([sys.executable, "-m", "slipest", "simulate", "--slip", "0.3", "--cycles", str(args.cycles),
                        "--noise", "0.01", "--seed", "1", "-o", str(log)],
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True, capture_output=True)
        env = environment(tmp / "nothing", tmp / "base")
        base = {
            "python -c pass": [timed([sys.executable, "-c", "pass"], env, tmp) for _ in range(args.runs)],
            "import numpy, scipy.linalg, numba": [
                timed([sys.executable, "-c", "import numpy, scipy.linalg, numba"], env, tmp) for _ in range(args.runs)],
        }
        results = []
        writable = copy_package(tmp / "writable", compiled=True)
        results.append(measure("writable copy", [], writable, tmp / "w", log, args.runs, writable / "slipest"))
        ro = copy_package(tmp / "readonly", compiled=True)
        prefix, how = read_only_wrapper(ro)
        try:
            if prefix is None:
                print(f"read-only copy: not measured: {how}")
            else:
                results.append(measure(f"read-only copy ({how})", prefix, ro, tmp / "r", log, args.runs,
                                       tmp / "r" / "xdg" / "slipest" / "numba"))
        finally:
            if os.geteuid() != 0:
                make_writable(ro)
        samples = sum(1 for line in open(log) if line[:1] not in ("#", "t"))
        print(f"command: python -m slipest replay LOG -o /dev/null  (LOG: {args.cycles} leg cycles, "
              f"{samples} samples); {args.runs} warm runs; each a fresh process")
        for name, t in base.items():
            print(f"baseline {name:<36s} median {statistics.median(t):6.3f} s  (min {min(t):.3f})")
        floor = statistics.median(base["import numpy, scipy.linalg, numba"])
        print(f"{'':<52s} {'cold':>7s} {'warm':>7s} {'min':>7s} {'warm/cold':>9s} {'warm/imports':>12s}")
        for r in results:
            med = statistics.median(r["warm"])
            print(f"{r['name']:<52s} {r['cold']:6.2f}s {med:6.3f}s {min(r['warm']):6.3f}s {med / r['cold']:9.3f} "
                  f"{med / floor:12.2f}")
            print(f"    numba cache: {r['numba_cache_dir']}: {r['cache_files']} files after the cold run; "
                  f"{r['written_warm']} written by the warm runs; {r['package_written']} files written in the package "
                  "(bytecode and numba's files)")
        worst = max(statistics.median(r["warm"]) for r in results)
        print(f"target warm < 2 s: {'met' if worst < 2.0 else 'NOT met'} (worst median {worst:.3f} s); "
              f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        bad = [r["name"] for r in results
               if r["written_warm"] or (r["name"] != "writable copy" and r["package_written"])]
        if bad:
            print(f"bench_startup: the cache did not hold for: {', '.join(bad)}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
