"""PNG plots of a diagnosis (matplotlib, Agg backend; ``pip install 'slipest[plot]'``): data in, files out.

* ``waveforms.png``: held-out cycles (mean per slip level) vs the nominal
  model and the best effect, specific force minus 1 g [g] vs leg phase [rad];
* ``gap_by_angle.png``: the gap [g] per leg-angle window, nominal and best effect;
* ``ranking.png``: held-out gap per effect, with the nominal gap and the
  ``none`` level.
"""

from __future__ import annotations

import os

import numpy as np

from slipest.plotting import pyplot
from slipest.units import G

plt = pyplot()  # matplotlib is an extra: MissingExtra names it when it is not installed


def plot_waveforms(path, phase, panels, best_name: str | None) -> str:
    """``panels``: list of ``(title, data, nominal, best_or_None)`` arrays over ``phase`` [rad], in m/s^2."""
    n = max(1, len(panels))
    fig, axes = plt.subplots(n, 1, figsize=(10, 2.6 * n), sharex=True, squeeze=False)
    for ax, (title, data, nominal, best) in zip(axes[:, 0], panels):
        ax.plot(phase, data / G - 1, color="k", lw=1.0, label="log (held-out mean)")
        ax.plot(phase, nominal / G - 1, color="tab:blue", lw=1.0, ls="--", label="nominal model")
        if best is not None:
            ax.plot(phase, best / G - 1, color="tab:red", lw=1.0, ls=":", label=f"+ {best_name}")
        ax.axvline(0.0, color="0.7", lw=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_ylabel("az - 1 g [g]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="upper left")
    axes[-1, 0].set_xlabel("leg phase [rad] (rigid half < 0 < stick-slip half)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def plot_windows(path, windows_nominal, windows_after=None, best_name: str | None = None) -> str:
    """Gap per leg-angle window (lists of ``{"from", "to", "gap", "share"}``)."""
    fig, ax = plt.subplots(figsize=(9, 3.5))
    lo = np.array([w["from"] for w in windows_nominal])
    hi = np.array([w["to"] for w in windows_nominal])
    width = hi - lo
    ax.bar(lo, [w["gap"] * 1000 for w in windows_nominal], width=width * 0.45, align="edge", color="tab:blue",
           label="nominal model")
    if windows_after:
        ax.bar(lo + width * 0.5, [w["gap"] * 1000 for w in windows_after], width=width * 0.45, align="edge",
               color="tab:red", label=f"+ {best_name}")
    for w in windows_nominal:
        ax.text(w["from"] + 0.02 * (w["to"] - w["from"]), w["gap"] * 1000, f"{w['share'] * 100:.0f}%", fontsize=7,
                va="bottom")
    ax.set_xlabel("leg phase window [rad]")
    ax.set_ylabel("gap [mg]")
    ax.set_title("held-out gap by leg-angle window (labels: share of the nominal gap)", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def plot_ranking(path, ranking, gap_nominal: float, none_level: float, verdict: str) -> str:
    """Held-out gap per effect (``ranking``: dicts with ``effect``, ``gap_heldout``, ``shrink``, ``named``)."""
    fig, ax = plt.subplots(figsize=(11, 3.8))
    names = [r["effect"] for r in ranking]
    gaps = [r["gap_heldout"] * 1000 for r in ranking]
    colors = ["tab:red" if r.get("named") else "tab:gray" for r in ranking]
    y = np.arange(len(names))
    ax.barh(y, gaps, color=colors)
    for yi, r in zip(y, ranking):
        ax.text(r["gap_heldout"] * 1000, yi, f"  shrink {r['shrink'] * 100:.0f}%", va="center", fontsize=8)
    ax.axvline(gap_nominal * 1000, color="tab:blue", ls="--", label=f"nominal {gap_nominal * 1000:.1f} mg")
    ax.axvline(none_level * 1000, color="tab:green", ls=":", label=f"'none' level {none_level * 1000:.1f} mg")
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xlabel("held-out gap [mg]")
    ax.set_title(f"effects ranked by held-out gap - verdict: {verdict}", fontsize=9)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


#: The files :func:`write_all` writes into its directory.
PLOT_FILES = ("waveforms.png", "gap_by_angle.png", "ranking.png")


def write_all(diag, directory) -> list[str]:
    """Write the three PNGs of a :class:`slipest.diagnosis.run.Diagnosis` into ``directory``."""
    os.makedirs(directory, exist_ok=True)
    cs = diag.cycles
    test = diag.split.test
    best = diag.best.effect if diag.best else None
    phase = cs.grid.bin_centres
    slips = np.round(cs.slip[test], 6)
    levels = np.unique(slips)
    # up to four levels, held-out levels first, spread over the range
    held = [lv for lv in levels if round(float(lv), 6) in {round(h, 6) for h in diag.split.heldout_levels}]
    rest = [lv for lv in levels if lv not in held]
    chosen = sorted((held + rest)[:4]) if len(levels) > 4 else list(levels)
    panels = []
    for lv in chosen:
        sel = slips == lv
        data = cs.y[test][sel].mean(axis=0)
        nominal = diag.predictions["nominal"][sel].mean(axis=0)
        b = diag.predictions[best][sel].mean(axis=0) if best else None
        tag = "never fitted" if lv in held else "fitted level, held-out cycles"
        panels.append((f"slip {lv:g} ({sel.sum()} cycles, {tag})", data, nominal, b))
    paths = [plot_waveforms(os.path.join(directory, PLOT_FILES[0]), phase, panels, best)]
    after = diag.where.get("after", {}).get("angle_windows")
    paths.append(plot_windows(os.path.join(directory, PLOT_FILES[1]), diag.where["angle_windows"], after, best))
    if diag.ranking:
        paths.append(
            plot_ranking(
                os.path.join(directory, PLOT_FILES[2]),
                [c.as_dict() for c in diag.ranking],
                diag.gap_nominal,
                diag.thresholds.none_level(diag.noise.bin_g),
                diag.verdict,
            )
        )
    return paths
