"""Where numba caches the compiled kernels (slipest.numba_cache), down to a real read-only copy of the package."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from slipest import numba_cache

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import bench_startup  # noqa: E402  (tools/bench_startup.py: the read-only copy)


@pytest.fixture
def unwritable(tmp_path) -> Path:
    """A path no one can create a directory under: its parent is a regular file (holds for root too)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    return blocker / "below"


def test_the_package_keeps_its_own_cache_when_it_can(tmp_path):
    assert numba_cache.choose({"HOME": str(tmp_path)}, package_dir=tmp_path / "pkg") is None
    assert (tmp_path / "pkg" / "__pycache__").is_dir()


def test_a_read_only_package_caches_in_the_first_writable_place(tmp_path, unwritable, monkeypatch):
    choose = lambda **env: numba_cache.choose(env, package_dir=unwritable)  # noqa: E731
    assert choose(NUMBA_CACHE_DIR=str(tmp_path / "mine")) is None  # the user's choice: left to numba
    home = tmp_path / "home"
    assert choose(HOME=str(home)) == str(home / ".cache" / "slipest" / "numba")
    assert choose(HOME=str(home), XDG_CACHE_HOME=str(tmp_path / "xdg")) == str(tmp_path / "xdg" / "slipest" / "numba")
    assert choose(HOME=str(home), XDG_CACHE_HOME="relative/xdg") == str(home / ".cache" / "slipest" / "numba")
    service = tmp_path / "var-cache-slipest"
    assert choose(HOME=str(home), CACHE_DIRECTORY=f"{service}:/elsewhere") == str(service / "numba")
    # a service user with no writable home: the temporary directory (until the next boot)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    got = choose(HOME=str(unwritable), CACHE_DIRECTORY=str(unwritable))
    assert got == str(tmp_path / "tmp" / f"slipest-{os.getuid()}" / "numba")
    assert os.path.isdir(got)


def test_configure_sets_the_environment_and_a_loaded_numba(monkeypatch, tmp_path, unwritable):
    import numba.core.config as config

    # set, then deleted, through monkeypatch: the variable's state before the test is recorded and comes back after
    # it, whatever configure() writes into os.environ (delenv of an unset variable records nothing, and the cache
    # directory configure() sets here leaked into every later test's subprocesses: each compiled the kernels again)
    monkeypatch.setenv("NUMBA_CACHE_DIR", "unset-after-the-test")
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(numba_cache, "PACKAGE_DIR", unwritable)
    monkeypatch.setattr(config, "CACHE_DIR", config.CACHE_DIR)
    want = str(tmp_path / "xdg" / "slipest" / "numba")
    assert numba_cache.configure() == want
    assert os.environ["NUMBA_CACHE_DIR"] == want and config.CACHE_DIR == want
    assert numba_cache.configure() is None  # now set: left alone


def test_the_cache_directory_a_test_configured_is_not_left_to_the_next_ones():
    # runs after test_configure_sets_the_environment_and_a_loaded_numba (file order): its NUMBA_CACHE_DIR is gone
    assert "slipest/numba" not in os.environ.get("NUMBA_CACHE_DIR", "")


PROBE = '''
import numba

@numba.njit(cache=True)
def probe(x):
    return x + 1
'''

RUN = ("import os, slipest, slipest.segmentation, slipest.inverse.grid_kernels; "
       "from slipest._cache_probe import probe; assert probe(1) == 2; print(os.environ.get('NUMBA_CACHE_DIR'))")


def _run(prefix, site, env):
    proc = subprocess.run(prefix + [sys.executable, "-c", RUN], env={**env, "NUMBA_DEBUG_CACHE": "1"}, cwd=site.parent,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def test_a_read_only_install_compiles_once_into_the_user_cache(tmp_path):
    """A read-only copy of the package, imported as a service user would: nothing is written into it,
    the kernel is cached in $XDG_CACHE_HOME/slipest/numba on the first run and loaded on the second; with no
    writable home either (numba alone then fails at import), the temporary directory is used."""
    site = bench_startup.copy_package(tmp_path / "site", compiled=True)
    (site / "slipest" / "_cache_probe.py").write_text(PROBE)
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(site / "slipest" / "_cache_probe.py")], check=True)
    prefix, how = bench_startup.read_only_wrapper(site)
    try:
        if prefix is None:
            pytest.skip(f"no read-only copy possible here: {how}")
        env = bench_startup.environment(site, tmp_path / "work")
        before = bench_startup.files(site)
        xdg_cache = tmp_path / "work" / "xdg" / "slipest" / "numba"

        first = _run(prefix, site, env)
        assert first.splitlines()[-1] == str(xdg_cache)
        assert "data saved" in first and "_cache_probe" in first
        cached = bench_startup.files(xdg_cache, bench_startup.NUMBA_FILES)
        assert any("_cache_probe.probe" in p for p in cached), sorted(cached)

        second = _run(prefix, site, env)
        assert "data loaded" in second and "data saved" not in second, second[-2000:]
        assert bench_startup.files(xdg_cache, bench_startup.NUMBA_FILES) == cached  # nothing recompiled

        blocker = tmp_path / "not-a-dir"
        blocker.write_text("")
        homeless = {**env, "HOME": str(blocker), "XDG_CACHE_HOME": str(blocker), "TMPDIR": str(tmp_path / "tmp")}
        (tmp_path / "tmp").mkdir()
        third = _run(prefix, site, homeless)
        assert third.splitlines()[-1] == str(tmp_path / "tmp" / f"slipest-{os.getuid()}" / "numba")
        assert bench_startup.files(site) == before  # the read-only copy was never written to
    finally:
        if os.geteuid() != 0:
            bench_startup.make_writable(site)
