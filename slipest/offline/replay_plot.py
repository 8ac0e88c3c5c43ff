"""A picture of a replay (PNG, matplotlib: ``pip install 'slipest[plot]'``): estimates in, a file out.

:func:`replay_figure` draws, over time, one column per wheel (:func:`plot_replay` writes it):

* the slip estimate with its 95 % band (``slip +- 1.96 slip_std``) and the
  reference slip where the log has one (``slip_ref``);
* ``dphi = phiS - phiD`` [rad] with its 95 % band;
* the soil the estimator holds: ``kS`` [N/m] with its band, and ``phiS``
  [rad] on the right axis;

and marks every flagged (not estimated) leg cycle with a red cross at its
end time, the legend counting them by reason.  Importing this module without
matplotlib raises :class:`~slipest.extras.MissingExtra`.
"""

from __future__ import annotations

import math

import numpy as np

from slipest.plotting import pyplot

plt = pyplot()

__all__ = ["plot_replay", "replay_figure"]

#: The half width of a 95 % band in standard deviations.
Z95 = 1.96


def _column(estimates, name: str) -> np.ndarray:
    return np.array([float(getattr(e, name, math.nan)) for e in estimates], dtype=np.float64)


def _band(ax, t, value, std, color: str, label: str) -> None:
    ax.plot(t, value, color=color, lw=1.2, marker=".", ms=3, label=label)
    ax.fill_between(t, value - Z95 * std, value + Z95 * std, color=color, alpha=0.2, lw=0, label="95% band")


def _flagged(ax, t, estimates, ok) -> None:
    bad = ~ok
    if not bad.any():
        return
    reasons: dict[str, int] = {}
    for e, b in zip(estimates, bad):
        if b:
            reasons[str(e.quality)] = reasons.get(str(e.quality), 0) + 1
    label = "flagged: " + ", ".join(f"{q} {n}" for q, n in sorted(reasons.items()))
    ax.plot(t[bad], np.zeros(int(bad.sum())), "x", color="tab:red", ms=6, transform=ax.get_xaxis_transform(),
            clip_on=False, label=label)


def replay_figure(series: dict, *, title: str = ""):
    """The figure (see the module docstring); ``series``: wheel (None for a one-stream log) -> its
    :class:`~slipest.online.Estimate` s in order.  ValueError when no wheel has a cycle.  The caller
    closes it (``matplotlib.pyplot.close``)."""
    wheels = [w for w in sorted(series, key=lambda w: -1 if w is None else w) if series[w]]
    if not wheels:
        raise ValueError("no leg cycle to plot")
    t0 = min(float(series[w][0].t_start) for w in wheels)
    fig, axes = plt.subplots(3, len(wheels), figsize=(max(8.0, 5.0 * len(wheels)), 8.5), sharex="col", squeeze=False)
    for j, wheel in enumerate(wheels):
        est = series[wheel]
        t = _column(est, "t_end") - t0
        ok = np.array([e.ok for e in est], dtype=bool) & np.isfinite(_column(est, "slip"))
        ax_slip, ax_dphi, ax_soil = axes[:, j]
        _band(ax_slip, t[ok], _column(est, "slip")[ok], _column(est, "slip_std")[ok], "tab:blue", "slip estimate")
        ref = _column(est, "slip_ref")
        if np.isfinite(ref).any():
            ax_slip.plot(t, ref, color="k", lw=1.0, ls="--", drawstyle="steps-pre", label="reference slip")
        _flagged(ax_slip, t, est, ok)
        ax_slip.set_ylabel("slip [-]")
        ax_slip.set_title(("wheel %s" % wheel) if wheel is not None else (title or "replay"), fontsize=10)
        _band(ax_dphi, t[ok], _column(est, "dphi")[ok], _column(est, "dphi_std")[ok], "tab:green", "dphi estimate")
        _flagged(ax_dphi, t, est, ok)
        ax_dphi.set_ylabel("dphi = phiS - phiD [rad]")
        _band(ax_soil, t[ok], _column(est, "kS")[ok], _column(est, "kS_std")[ok], "tab:purple", "kS")
        ax_soil.set_ylabel("kS [N/m]")
        ax_phi = ax_soil.twinx()
        ax_phi.plot(t[ok], _column(est, "phiS")[ok], color="tab:orange", lw=1.0, marker=".", ms=3, label="phiS")
        ax_phi.set_ylabel("phiS [rad]")
        ax_soil.set_xlabel(f"time [s] from t = {t0:.6g} s")
        for ax in (ax_slip, ax_dphi, ax_soil):
            ax.grid(alpha=0.3)
        for ax in (ax_slip, ax_dphi):
            ax.legend(fontsize=7, loc="upper left")
        handles = ax_soil.get_legend_handles_labels()
        more = ax_phi.get_legend_handles_labels()
        ax_soil.legend(handles[0] + more[0], handles[1] + more[1], fontsize=7, loc="upper left")
    if title and wheels != [None]:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_replay(path, series: dict, *, title: str = "") -> str:
    """Write :func:`replay_figure` as the PNG ``path`` (exactly there, whatever its extension); returns ``path``."""
    fig = replay_figure(series, title=title)
    try:
        fig.savefig(path, dpi=110, format="png")
    finally:
        plt.close(fig)
    return str(path)
