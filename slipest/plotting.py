"""matplotlib for the modules that draw (an optional extra: ``pip install 'slipest[plot]'``).

:func:`pyplot` gives ``matplotlib.pyplot`` on the file-only Agg backend, or
raises :class:`~slipest.extras.MissingExtra` naming the extra when
matplotlib is not installed.  Only the drawing modules call it
(:mod:`slipest.offline.replay_plot`, :mod:`slipest.diagnosis.plots`); the rest of
slipest never imports matplotlib, so a rover installs without it.
"""

from __future__ import annotations

from slipest.extras import import_extra

__all__ = ["pyplot"]


def pyplot():
    """``matplotlib.pyplot`` with the Agg backend (PNG files, no display)."""
    matplotlib = import_extra("matplotlib", "plot", "drawing plots")
    matplotlib.use("Agg")
    return import_extra("matplotlib.pyplot", "plot", "drawing plots")
