"""Optional dependencies (pip extras): import one, or fail with the ``pip install`` that brings it.

The core install runs a rover's estimator; what only some users need comes
with an extra of the ``slipest`` package: ``plot`` (matplotlib: ``slipest
replay --plot``, ``slipest diagnose --plots``, the scripts in ``tools/``),
``ros`` (rosbags: ROS 2 bags), ``dask`` (dask.distributed: many logs on a
cluster), ``view`` (foxglove-sdk: the live view, ``--view``), ``mf4``
(asammdf: ``.mf4`` CAN logs, recorded and replayed through python-can).
:func:`import_extra` imports a module of one of them, and raises
:class:`MissingExtra` (an ``ImportError``) saying which extra to install
when it is not there.
"""

from __future__ import annotations

import importlib

__all__ = ["MissingExtra", "import_extra"]


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message names the ``pip install`` that brings it."""


def import_extra(module: str, extra: str, purpose: str):
    """``importlib.import_module(module)``, or :class:`MissingExtra` ("``purpose`` needs
    ``package``: pip install 'slipest[extra]'") when the module or its package is missing.
    An ``ImportError`` from inside an installed package (a broken install) is raised as it is."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        top = module.split(".")[0]
        if exc.name is not None and exc.name != module and exc.name.split(".")[0] != top:
            raise
        raise MissingExtra(f"{purpose} needs {top}, which is not installed: pip install 'slipest[{extra}]'") from exc
