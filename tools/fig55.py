#!/usr/bin/env python
"""Reproduce thesis Fig. 5.5: hub vertical acceleration vs leg angle, three panels.

(a) slip 0.5 / 0.25 / 0.125; (b) kS 1.5 / 1.0 / 0.5 kN/m; (c) phiS 0.70 /
0.52 / 0.35 rad with phiD = 0.30 rad. Everything not varied is the project's
default model (``docs/model.md`` section 3: i = 0.25,
kS = 1000 N/m, phiS = 0.52, phiD = 0.35, kappa = 0.3). x: leg angle theta
[rad] over [0, pi/4]; y: gravity-free hub vertical acceleration [g] within
+-1 g like the thesis (curves that leave that band are clipped by the axes;
the legend gives each curve's full ``Da``).

Prints each case's ``Da`` [g] and first break-away angle [rad] beside the
reference values of docs/model.md (section 4, dt = 1e-4 s) with the relative error.

    python tools/fig55.py -o out/fig55.png
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from slipest.model.params import StickSlipParams  # noqa: E402
from slipest.model.stance import DEFAULT_DT, simulate_stance  # noqa: E402
from slipest.plotting import pyplot  # noqa: E402  (matplotlib: pip install 'slipest[plot]')

plt = pyplot()

#: (panel title, [(legend label, parameter changes, reference Da [g], reference break-away theta [rad])])
#: Reference values: docs/model.md section 4.
PANELS = [
    (
        "(a) Slip influence",
        [
            ("i = 0.50", dict(slip=0.5), 1.505, 0.167),
            ("i = 0.25", dict(slip=0.25), 1.179, 0.273),
            ("i = 0.125", dict(slip=0.125), 0.684, 0.399),
        ],
    ),
    (
        "(b) Spring stiffness influence",
        [
            ("kS = 1.50 kN/m", dict(kS=1500.0), 1.567, 0.207),
            ("kS = 1.00 kN/m", dict(kS=1000.0), 1.179, 0.273),
            ("kS = 0.50 kN/m", dict(kS=500.0), 0.738, 0.399),
        ],
    ),
    (
        "(c) Friction angle influence (phiD = 0.30 rad)",
        [
            ("phiS = 0.70 rad", dict(phiS=0.70, phiD=0.30), 1.518, 0.392),
            ("phiS = 0.52 rad", dict(phiS=0.52, phiD=0.30), 1.109, 0.273),
            ("phiS = 0.35 rad", dict(phiS=0.35, phiD=0.30), 0.738, 0.175),
        ],
    ),
]


def _rel(value: float, ref: float) -> float:
    """Relative error [-] (NaN when either is NaN)."""
    return (value - ref) / ref if math.isfinite(value) and math.isfinite(ref) else math.nan


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-o", "--output", default="out/fig55.png", help="PNG to write (default: out/fig55.png)")
    ap.add_argument("--dt", type=float, default=DEFAULT_DT, help=f"integration step [s] (default {DEFAULT_DT:g})")
    args = ap.parse_args(argv)

    base = StickSlipParams()
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2), sharey=True)
    print(f"Fig. 5.5 cases (dt = {args.dt:g} s); reference: docs/model.md section 4 (dt = 1e-4 s)")
    header = f"{'case':<34} {'Da [g]':>8} {'ref':>7} {'rel.err':>8}   {'theta_b [rad]':>13} {'ref':>6} {'rel.err':>8}"
    print(header)
    print("-" * len(header))
    worst = 0.0
    for ax, (title, cases) in zip(axes, PANELS):
        panel = title.split()[0]
        for label, change, ref_da, ref_th in cases:
            p = base.with_(**change)
            r = simulate_stance(p, dt=args.dt)
            da, thb = r.delta_a_g, r.breakaway_theta
            e_da, e_th = _rel(da, ref_da), _rel(thb, ref_th)
            worst = max(worst, abs(e_da))
            print(
                f"{panel + ' ' + label:<34} {da:8.3f} {ref_da:7.3f} {100 * e_da:+7.2f}%"
                f"   {thb:13.3f} {ref_th:6.3f} {100 * e_th:+7.2f}%"
            )
            (line,) = ax.plot(r.theta, r.az / p.g, lw=0.9, label=f"{label}  (Da = {da:.3f} g)")
            if math.isfinite(thb):  # first break-away, on the curve
                k = min(int(np.searchsorted(r.theta, thb)), r.theta.size - 1)
                ax.plot(r.theta[k], r.az[k] / p.g, "v", color=line.get_color(), ms=6)
        ax.set_title(title)
        ax.set_xlabel(r"leg angle $\theta$ [rad]")
        ax.set_xlim(0.0, math.pi / base.nL)
        ax.set_ylim(-1.0, 1.0)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="lower left", fontsize=8)
    axes[0].set_ylabel(r"hub vertical acceleration $a_{z,H}$ [g] (gravity-free)")
    fig.suptitle(
        "Thesis Fig. 5.5 reproduced (stick-slip model, kappa = 0.3; unless varied i = 0.25, kS = 1 kN/m, "
        "phiS = 0.52, phiD = 0.35 rad); Da = max - min over the stance; triangles: first break-away",
        fontsize=10,
    )
    fig.tight_layout()
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    print(f"worst |relative error| of Da vs the reference: {100 * worst:.2f}%  (tests/test_model_stance.py: 0.1%)")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
