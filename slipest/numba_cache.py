"""Where numba keeps slipest's compiled kernels, chosen before any of them is compiled.

Every kernel is compiled with ``cache=True``: the first run after an install
compiles them (10-20 s on a 2-core machine), later runs load the machine
code from disk (about 0.5 s, once per process).  numba writes its cache in
the ``__pycache__`` directories beside the source when it can.  An install
in a read-only place (a system or image install, a service user who owns
neither the package nor a home directory) would otherwise fall back on
numba's ``~/.cache/numba``, and when that is not writable either, fail at
import (``RuntimeError: cannot cache function ...: no locator available``).

:func:`configure` (called by ``import slipest``) picks the first of:

1. ``$NUMBA_CACHE_DIR`` when set: the user's choice, left alone;
2. the package's own ``__pycache__`` directories when writable: numba's
   default, nothing is set;
3. ``$CACHE_DIRECTORY/numba``: the cache directory systemd gives a service
   with ``CacheDirectory=`` (the first one when several);
4. ``$XDG_CACHE_HOME/slipest/numba``, else ``~/.cache/slipest/numba``;
5. ``<temporary directory>/slipest-<uid>/numba`` (lasts until the next boot);

that it can write to, and sets ``NUMBA_CACHE_DIR`` to it, in ``os.environ``
(child processes inherit it) and, when numba is already imported, in
numba's configuration.  numba then caches every cached function of the
process there (its rule for ``NUMBA_CACHE_DIR``), keyed by source file, so
several installs and versions can share it.  It has to happen before numba
compiles or loads any of slipest's kernels: importing slipest does it first.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: The package directory whose ``__pycache__`` numba writes to by default.
PACKAGE_DIR = Path(__file__).resolve().parent


def writable(path: str | os.PathLike) -> bool:
    """True when a file can be created in ``path`` (created if missing), tested the way numba does: by writing one."""
    path = os.fspath(path)
    try:
        os.makedirs(path, exist_ok=True)
        probe = os.path.join(path, f".slipest-write-test-{os.getpid()}")
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
        os.unlink(probe)
        return True
    except OSError:
        return False


def user_cache_dir(environ=os.environ) -> Path:
    """The user's cache directory for slipest (XDG base directories): ``$XDG_CACHE_HOME/slipest``, else
    ``~/.cache/slipest`` (``%LOCALAPPDATA%\\slipest`` on Windows, ``~/Library/Caches/slipest`` on macOS)."""
    if sys.platform == "win32" and environ.get("LOCALAPPDATA"):
        return Path(environ["LOCALAPPDATA"]) / "slipest"
    home = Path(environ.get("HOME") or Path.home())
    if sys.platform == "darwin":
        return home / "Library" / "Caches" / "slipest"
    xdg = environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else home / ".cache"  # the spec ignores a relative value
    return base / "slipest"


def candidates(environ=os.environ) -> list[Path]:
    """The places tried when the package cannot hold its own cache, in order (items 3-5 of the module docstring)."""
    out = []
    systemd = environ.get("CACHE_DIRECTORY", "").split(":")[0]
    if systemd:
        out.append(Path(systemd) / "numba")
    try:
        out.append(user_cache_dir(environ) / "numba")
    except RuntimeError:  # no home directory to be found
        pass
    import tempfile

    uid = os.getuid() if hasattr(os, "getuid") else os.getpid()
    out.append(Path(tempfile.gettempdir()) / f"slipest-{uid}" / "numba")
    return out


def choose(environ=os.environ, package_dir: Path | None = None) -> str | None:
    """The directory :func:`configure` would set ``NUMBA_CACHE_DIR`` to, or None when it sets nothing
    (``NUMBA_CACHE_DIR`` already set, or the package's ``__pycache__`` writable, or nothing writable).
    ``package_dir``: default :data:`PACKAGE_DIR`."""
    if environ.get("NUMBA_CACHE_DIR"):
        return None
    if writable(Path(package_dir or PACKAGE_DIR) / "__pycache__"):
        return None
    for path in candidates(environ):
        if writable(path):
            return str(path)
    return None


def configure() -> str | None:
    """Point numba's cache at a writable place when the package's own is not (see the module docstring).

    Returns the directory set, or None when nothing was set.
    """
    path = choose()
    if path is None:
        return None
    os.environ["NUMBA_CACHE_DIR"] = path
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba read its environment when it was imported
        config.CACHE_DIR = path
    return path
