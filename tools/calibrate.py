#!/usr/bin/env python
"""Calibration sweep: simulate a grid of slips and soils, fit Eq. 5.15 and the forward model.

Grid (defaults, all stated in the output): slip 0..0.5 in 11 levels x kS
500..1500 N/m in 5 levels x phiD in {0.1, 0.2, 0.3, 0.4} rad x
dphi = phiS - phiD in {0, 0.0875, 0.175, 0.2625, 0.35} rad (phiS kept below
pi/2 - 0.1 rad), on the project's default model (kappa = 0.3, dt = 1e-4 s).
Four phiD levels (not three) so that a cubic surface's coefficients are
determined by the grid; candidates the grid cannot determine are reported but
never shipped. An independent validation table of random off-grid stances
(uniform over the same ranges) measures how each fit generalises between grid
levels, which a leave-one-soil-out split of the grid cannot.

Stances are simulated with ``simulate_batch`` in chunks (tqdm progress bar),
``on_error="flag"``; failures are counted by cause and dropped. Writes, into
the output directory (default ``out``): ``calibration_table.txt`` (a
Table-5.2-style report, also printed), ``calibration.png`` and
``calibration.json``; ``--write-package-data`` writes the JSON to
``slipest/data/calibration.json`` instead (the shipped calibration).  A
calibration file that already holds the same calibration is left untouched:
a rerun differs only in its time of writing (``created_utc``), the command
line (``created_by``, e.g. another ``-o``) and in float noise (about 1e-11,
from the order of parallel sums), which would otherwise show as a change to
the tracked file.

    python tools/calibrate.py [-o out] [--write-package-data]
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

import forward_calibration as fwd  # noqa: E402  (tools/forward_calibration.py, beside this script)
from slipest import calibration as cal_mod  # noqa: E402
from slipest.json_files import json_number  # noqa: E402
from slipest.model import kernel as K  # noqa: E402
from slipest.model.params import StickSlipParams, param_grid, param_matrix  # noqa: E402
from slipest.model.stance import DEFAULT_DT, simulate_batch, status_text  # noqa: E402
from slipest.plotting import pyplot  # noqa: E402  (matplotlib: pip install 'slipest[plot]')

plt = pyplot()

PACKAGE_JSON = Path(__file__).resolve().parents[1] / "slipest" / "data" / "calibration.json"


#: Keys that say when and with which command line a file was written, not what it holds: left out when
#: comparing calibrations (a rerun with another ``-o`` gives the same calibration).
VOLATILE_KEYS = frozenset({"created_utc", "created_by"})
#: Numbers this close (relative, absolute) are the same.  A rerun's float noise, measured against the
#: shipped file: at most 6.5e-12 absolute, and 1.3e-10 relative on values above 1e-3.
SAME_RTOL = 1e-9
SAME_ATOL = 1e-10


def same_calibration(a, b) -> bool:
    """True when two calibration documents (parsed JSON) differ at most in :data:`VOLATILE_KEYS` and
    in numbers within :data:`SAME_RTOL` / :data:`SAME_ATOL`."""
    if isinstance(a, dict) and isinstance(b, dict):
        keys = (a.keys() | b.keys()) - VOLATILE_KEYS
        return all(k in a and k in b and same_calibration(a[k], b[k]) for k in keys)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_calibration(x, y) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=SAME_RTOL, abs_tol=SAME_ATOL)
    return a == b


def write_calibration(cal: dict, path: Path) -> bool:
    """Write ``cal`` to ``path`` (validated) unless the file there already holds the same calibration
    (:func:`same_calibration`); True when written."""
    cal_mod.validate_calibration(cal)
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        old = None  # missing or unreadable: written
    if old is not None and same_calibration(old, json.loads(json.dumps(cal))):
        return False
    cal_mod.save_calibration(cal, path)
    return True


def _floats(text: str) -> np.ndarray:
    return np.array([float(v) for v in text.split(",") if v.strip()])


def build_grid(args) -> dict:
    """The sweep's levels and the flattened table of parameter values (SI)."""
    slip = np.linspace(0.0, args.slip_max, args.slip_levels)
    ks = np.linspace(args.ks_min, args.ks_max, args.ks_levels)
    phid = _floats(args.phid)
    dphi = _floats(args.dphi)
    s, k, pd, dp = (a.ravel() for a in np.meshgrid(slip, ks, phid, dphi, indexing="ij"))
    ps = pd + dp
    keep = ps < math.pi / 2 - args.phis_margin
    return {
        "levels": {"slip": slip, "kS": ks, "phiD": phid, "dphi": dphi},
        "n_dropped_phiS": int((~keep).sum()),
        "table": {"slip": s[keep], "kS": k[keep], "phiS": ps[keep], "phiD": pd[keep]},
    }


def validation_table(args) -> dict:
    """Random stances uniform over the sweep's ranges (not on its levels), seeded."""
    rng = np.random.default_rng(args.seed)
    n = args.n_validation
    phid = _floats(args.phid)
    dphi = _floats(args.dphi)
    pd = rng.uniform(phid.min(), phid.max(), n)
    dp = rng.uniform(dphi.min(), dphi.max(), n)
    ps = np.minimum(pd + dp, math.pi / 2 - args.phis_margin)
    return {
        "slip": rng.uniform(0.0, args.slip_max, n),
        "kS": rng.uniform(args.ks_min, args.ks_max, n),
        "phiS": ps,
        "phiD": pd,
    }


def simulate_table(table: dict, base: StickSlipParams, dt: float, chunk: int, desc: str):
    """Simulate every row of ``table`` (chunks, progress bar); returns ``(Da [g], status, n_contact_losses)``."""
    n = table["slip"].size
    # every row validated by the dataclass (raises on an invalid combination)
    mat = param_matrix(param_grid(base, slip=table["slip"], kS=table["kS"], phiS=table["phiS"], phiD=table["phiD"]))
    da = np.full(n, np.nan)
    status = np.zeros(n, dtype=np.int64)
    losses = np.zeros(n, dtype=np.int64)
    with tqdm(total=n, desc=desc, unit="stance") as bar:
        for start in range(0, n, chunk):
            sl = slice(start, min(start + chunk, n))
            r = simulate_batch(mat[sl], dt=dt, on_error="flag")
            da[sl], status[sl], losses[sl] = r.delta_a_g, r.status, r.n_contact_losses
            bar.update(sl.stop - sl.start)
    return da, status, losses


def failure_report(status: np.ndarray) -> list[str]:
    """One line per failure cause."""
    lines = []
    for code in np.unique(status[status != K.STATUS_OK]):
        lines.append(f"  {int((status == code).sum())} x status {code}: {status_text(code)}")
    return lines


def fmt(v, spec=".3f") -> str:
    """Format a number, NaN/None as 'n/a'."""
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def report(args, grid, n_total, n_fail, fail_lines, table, eqfit, cands, chosen, val_info, eq_val) -> str:
    """The Table-5.2-style text report."""
    L = []
    lv = grid["levels"]
    L.append("slipest calibration sweep (thesis Eq. 5.15 and forward model)")
    L.append("=" * 78)
    L.append(f"model: project default (docs/model.md section 3), kappa = {args.kappa:g}, dt = {args.dt:g} s")
    L.append(
        f"grid : slip {np.array2string(lv['slip'], precision=3, separator=', ')}\n"
        f"       kS   {np.array2string(lv['kS'], precision=0, separator=', ')} N/m\n"
        f"       phiD {np.array2string(lv['phiD'], precision=3, separator=', ')} rad\n"
        f"       dphi {np.array2string(lv['dphi'], precision=4, separator=', ')} rad  (phiS = phiD + dphi "
        f"< pi/2 - {args.phis_margin:g}; {grid['n_dropped_phiS']} combinations dropped for that)"
    )
    L.append(f"stances: {n_total} simulated, {n_fail} failed and dropped, {n_total - n_fail} used, "
             f"{eqfit.soils.shape[0]} soils")
    L.extend(fail_lines)
    L.append(f"validation: {val_info['n']} random off-grid stances (seed {args.seed}), {val_info['n_fail']} failed "
             f"and dropped")
    L.extend(val_info["fail_lines"])
    L.append("")
    L.append("1. Per-soil lines  i = aIV + bIV * Da  (Eq. 5.15, left) and, forward, Da = alpha + beta * i")
    L.append("   (the thesis text swaps the names 'slope'/'intercept'; here aIV is the intercept, bIV the slope)")
    L.append(f"   {'kS':>6} {'phiS':>6} {'phiD':>5} {'dphi':>6} | {'aIV [-]':>8} {'bIV [1/g]':>9} {'R^2':>6} {'n':>3} |"
             f" {'alpha [g]':>9} {'beta [g]':>9}")
    soils, a_f, b_f, r2_f, _ = fwd.forward_lines(table["slip"], table["kS"], table["phiS"], table["phiD"], table["Da"])
    for s in range(eqfit.soils.shape[0]):
        k, ps, pd = eqfit.soils[s]
        L.append(
            f"   {k:6.0f} {ps:6.4f} {pd:5.2f} {ps - pd:6.4f} | {fmt(eqfit.aIV[s], '8.3f')} {fmt(eqfit.bIV[s], '9.3f')} "
            f"{fmt(eqfit.r2[s], '6.3f')} {eqfit.n[s]:3d} | {fmt(a_f[s], '9.3f')} {fmt(b_f[s], '9.3f')}"
        )
    r2 = eqfit.r2[np.isfinite(eqfit.r2)]
    L.append(f"   per-soil R^2: mean {r2.mean():.3f}, median {np.median(r2):.3f}, min {r2.min():.3f}, max {r2.max():.3f}"
             f"   [docs/model.md sec. 5: mean ~0.79, median 0.87; thesis: average GoF 0.84]")
    dps = eqfit.dphi
    by = "   mean R^2 by dphi: " + ", ".join(
        f"{d:.4f}: {np.nanmean(eqfit.r2[np.isclose(dps, d)]):.3f}" for d in np.unique(np.round(dps, 6))
    )
    L.append(by + "   [docs/model.md: ~0.98 at 0, 0.6-0.75 at 0.175-0.35]")
    mono = 0
    for s in range(soils.shape[0]):
        m = np.isclose(table["kS"], soils[s, 0]) & np.isclose(table["phiS"], soils[s, 1]) & np.isclose(table["phiD"], soils[s, 2])
        order = np.argsort(table["slip"][m])
        mono += bool(np.all(np.diff(table["Da"][m][order]) > 0))
    L.append(f"   Da strictly increasing in slip for {mono} of {soils.shape[0]} soils")
    L.append("")
    L.append("2. Eq. 5.15 second-level laws (one point per soil, unweighted)")
    L.append(f"   bIV = amu + bmu * dphi            amu = {eqfit.amu:+.4f} 1/g, bmu = {eqfit.bmu:+.4f} 1/(g rad)"
             f"        R^2 = {eqfit.r2_slope_law:.3f}   [docs/model.md: ~0.07]")
    L.append(f"   aIV = cI + cmu * dphi + cK * kS   cI = {eqfit.cI:+.4f}, cmu = {eqfit.cmu:+.4f} 1/rad, "
             f"cK = {eqfit.cK:+.3e} m/N   R^2 = {eqfit.r2_intercept_plane:.3f}   [docs/model.md: ~0.15]")
    L.append("   full Eq. 5.15 predicting slip from (Da, dphi, kS):")
    L.append(f"     over the sweep: R^2 = {eqfit.r2_end_to_end:.3f}, RMSE = {eqfit.rmse_end_to_end:.4f}   "
             f"[docs/model.md: 'barely better than the mean'; slip std over the sweep = {np.std(table['slip']):.4f}]")
    L.append(f"     on validation : R^2 = {eq_val['r2']:.3f}, RMSE = {eq_val['rmse']:.4f}")
    L.append(f"   per-soil lines with the soil's own aIV, bIV (soil known, in-sample): RMSE = "
             f"{eqfit.rmse_lines_soil_known:.4f}   [docs/model.md: 0.072]")
    L.append("")
    L.append("3. Forward calibration  Da = f(i, soil), inverted for slip with the soil known")
    first = next(c for c in cands if "alpha_plane" in c.info)
    L.append(f"   per-soil lines Da = alpha + beta * i: R^2 mean {first.info['lines_r2_mean']:.3f}, "
             f"median {first.info['lines_r2_median']:.3f} (same R^2 as the slip-on-Da lines)")
    for c in cands:
        if "alpha_plane" in c.info:
            ap, bp = c.info["alpha_plane"], c.info["beta_plane"]
            terms = lambda p: " ".join(f"{v:+.4g}*{k}" if k != "const" else f"{v:+.4f}" for k, v in p.items())
            spec = "   [docs/model.md: alpha plane ~0.73]" if "phiS" not in ap else "   [docs/model.md: alpha plane ~0.82 with phiS]"
            L.append(f"   {c.model.name}:")
            L.append(f"     alpha = {terms(ap)}   R^2 = {c.info['r2_alpha']:.3f}{spec}")
            L.append(f"     beta  = {terms(bp)}   R^2 = {c.info['r2_beta']:.3f}")
        elif "r2_alpha" in c.info:
            L.append(f"   {c.model.name}: alpha surface R^2 = {c.info['r2_alpha']:.3f}, beta surface R^2 = "
                     f"{c.info['r2_beta']:.3f}")
    L.append("")
    L.append("   candidates (Da in g; slip RMSE after inversion, soil known, clipped to "
             f"[{chosen.model.slip_clip[0]:g}, {chosen.model.slip_clip[1]:g}]):")
    L.append(f"   {'candidate':<46} {'coef':>4} {'ident':>5} {'mono':>5} | {'R2 Da':>6} {'cv':>6} {'val':>6} | {'RMSE Da':>7} "
             f"{'val':>6} | {'RMSE slip':>9} {'cv':>6} {'val':>6}")
    for c in cands:
        mark = " <= shipped" if c is chosen else ""
        L.append(
            f"   {c.model.name:<46} {c.n_coef:4d} {('yes' if c.identifiable else 'NO'):>5} "
            f"{c.monotone_fraction:5.3f} | {c.r2_da:6.3f} "
            f"{c.r2_da_cv:6.3f} {fmt(c.r2_da_val, '6.3f')} | {c.rmse_da:7.3f} {fmt(c.rmse_da_val, '6.3f')} | "
            f"{c.rmse_slip:9.4f} {c.rmse_slip_cv:6.4f} {fmt(c.rmse_slip_val, '6.4f')}{mark}"
        )
    L.append("   (cv: leave one soil out; val: the random off-grid validation table; ident: the grid determines "
             "every coefficient;\n    mono: share of soils of the calibrated box on which Da increases strictly with "
             "slip, i.e. the inverse is unique)")
    L.append(f"   selection rule: {fwd.selection_rule(cands, args.tolerance)}")
    L.append(f"   shipped: {chosen.model.name} ({chosen.n_coef} coefficients)")
    L.append(f"   for scale: predicting the mean slip gives RMSE {np.std(table['slip']):.4f} over the sweep; "
             f"Eq. 5.15 gives {eqfit.rmse_end_to_end:.4f} (val {eq_val['rmse']:.4f})")
    return "\n".join(L) + "\n"


def plot(path: Path, table, eqfit, chosen, val, eq_pred_val):
    """Four panels: Da vs slip per soil (colour: dphi); Eq. 5.15 and forward-inverted slip vs true; R^2 vs dphi."""
    fig, axes = plt.subplots(2, 2, figsize=(13, 10))
    ax = axes[0, 0]
    cmap = plt.get_cmap("viridis")
    dmax = max(float(np.max(eqfit.dphi)), 1e-9)
    idx, soils = cal_mod.soil_index(table["kS"], table["phiS"], table["phiD"])
    for s in range(soils.shape[0]):
        m = idx == s
        o = np.argsort(table["slip"][m])
        d = soils[s, 1] - soils[s, 2]
        ax.plot(table["slip"][m][o], table["Da"][m][o], "-", color=cmap(d / dmax), lw=0.8, alpha=0.7)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, dmax))
    fig.colorbar(sm, ax=ax, label="dphi = phiS - phiD [rad]")
    ax.set_xlabel("slip i [-]")
    ax.set_ylabel("Da [g]")
    ax.set_title(f"Da vs slip, one line per soil ({soils.shape[0]} soils)")
    ax.grid(True, alpha=0.3)

    ax = axes[0, 1]
    pred = cal_mod.eq515_slip(eqfit, table["Da"], table["phiS"] - table["phiD"], table["kS"])
    ax.plot(table["slip"], pred, ".", ms=3, alpha=0.5, label="sweep")
    ax.plot(val["slip"], eq_pred_val, ".", ms=2, alpha=0.4, color="tab:orange", label="validation (off-grid)")
    ax.plot([0, 0.5], [0, 0.5], "k--", lw=1)
    ax.set_xlabel("true slip [-]")
    ax.set_ylabel("Eq. 5.15 predicted slip [-]")
    ax.set_title(f"Eq. 5.15 as stated: R^2 = {eqfit.r2_end_to_end:.2f}, RMSE = {eqfit.rmse_end_to_end:.3f}\n"
                 "(y axis cut at the 0.5-99.5 percentiles)", fontsize=10)
    lo, hi = np.percentile(np.concatenate([pred, eq_pred_val]), [0.5, 99.5])
    ax.set_ylim(min(lo, -0.1), max(hi, 0.6))
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(True, alpha=0.3)

    ax = axes[1, 0]
    inv = fwd.invert_slip(chosen.model, table["Da"], table["kS"], table["phiS"], table["phiD"])
    inv_val = fwd.invert_slip(chosen.model, val["Da"], val["kS"], val["phiS"], val["phiD"])
    rng = np.random.default_rng(1)
    jitter = rng.uniform(-0.006, 0.006, table["slip"].size)  # the sweep's slips sit on 11 levels
    ax.plot(table["slip"] + jitter, inv, ".", ms=3, alpha=0.5, label=f"sweep (RMSE {chosen.rmse_slip:.3f})")
    ax.plot(val["slip"], inv_val, ".", ms=2, alpha=0.4, color="tab:orange",
            label=f"validation (RMSE {chosen.rmse_slip_val:.3f})")
    ax.plot([0, 0.5], [0, 0.5], "k--", lw=1)
    ax.set_xlabel("true slip [-] (sweep levels jittered by +-0.006 for visibility)")
    ax.set_ylabel("slip from inverted forward model [-]")
    ax.set_title(f"shipped forward model, soil known:\n{chosen.model.name}", fontsize=10)
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(True, alpha=0.3)

    ax = axes[1, 1]
    for k in np.unique(eqfit.soils[:, 0]):
        m = np.isclose(eqfit.soils[:, 0], k)
        ax.plot(eqfit.dphi[m] + (k - 1000) / 5e4, eqfit.r2[m], "o", ms=4, label=f"kS = {k:.0f} N/m")
    ax.set_xlabel("dphi [rad] (offset slightly by kS)")
    ax.set_ylabel("R^2 of the per-soil line i = aIV + bIV Da")
    ax.set_title("Eq. 5.15 per-soil goodness of fit")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-o", "--out-dir", default="out", help="output directory (default: out)")
    ap.add_argument("--write-package-data", action="store_true",
                    help=f"write the calibration JSON to {PACKAGE_JSON} (the shipped calibration)")
    ap.add_argument("--slip-max", type=float, default=0.5, help="largest slip [-] (default 0.5)")
    ap.add_argument("--slip-levels", type=int, default=11)
    ap.add_argument("--ks-min", type=float, default=500.0, help="[N/m]")
    ap.add_argument("--ks-max", type=float, default=1500.0, help="[N/m]")
    ap.add_argument("--ks-levels", type=int, default=5)
    ap.add_argument("--phid", default="0.1,0.2,0.3,0.4", help="dynamic friction angles [rad], comma-separated")
    ap.add_argument("--dphi", default="0,0.0875,0.175,0.2625,0.35", help="phiS - phiD levels [rad], comma-separated")
    ap.add_argument("--phis-margin", type=float, default=0.1, help="keep phiS < pi/2 - margin [rad]")
    ap.add_argument("--kappa", type=float, default=StickSlipParams().kappa, help="leg lateral stiffness ratio [-]")
    ap.add_argument("--dt", type=float, default=DEFAULT_DT, help="integration step [s]")
    ap.add_argument("--n-validation", type=int, default=1000, help="random off-grid validation stances")
    ap.add_argument("--seed", type=int, default=20240605, help="seed of the validation table")
    ap.add_argument("--chunk", type=int, default=256, help="stances per simulate_batch call")
    ap.add_argument("--tolerance", type=float, default=0.05, help="selection tolerance on slip RMSE (relative)")
    args = ap.parse_args(argv)
    command = "python tools/calibrate.py" + ("" if not (argv or sys.argv[1:]) else " " + shlex.join(argv or sys.argv[1:]))

    base = StickSlipParams(kappa=args.kappa)
    grid = build_grid(args)
    tab = grid["table"]
    n_total = tab["slip"].size
    t0 = time.perf_counter()
    da, status, losses = simulate_table(tab, base, args.dt, args.chunk, "calibration sweep")
    t_sweep = time.perf_counter() - t0
    ok = status == K.STATUS_OK
    n_fail = int((~ok).sum())
    table = {k: v[ok] for k, v in tab.items()}
    table["Da"] = da[ok]
    print(f"sweep: {n_total} stances in {t_sweep:.1f} s, {n_fail} failed, "
          f"{int((losses[ok] > 0).sum())} used stances had a contact loss (re-planting rule)")

    vtab = validation_table(args)
    vda, vstatus, _ = simulate_table(vtab, base, args.dt, args.chunk, "validation")
    vok = vstatus == K.STATUS_OK
    val = {k: v[vok] for k, v in vtab.items()}
    val["Da"] = vda[vok]
    val_info = {"n": vtab["slip"].size, "n_fail": int((~vok).sum()), "fail_lines": failure_report(vstatus)}

    cols = (table["slip"], table["kS"], table["phiS"], table["phiD"], table["Da"])
    eqfit = cal_mod.fit_eq515(*cols)
    eq_pred_val = cal_mod.eq515_slip(eqfit, val["Da"], val["phiS"] - val["phiD"], val["kS"])
    eq_val = {"r2": cal_mod.r2_score(val["slip"], eq_pred_val), "rmse": cal_mod.rmse(val["slip"], eq_pred_val)}
    with tqdm(total=len(fwd.DEFAULT_CANDIDATES), desc="forward fits (+ leave-one-soil-out)", unit="model") as bar:
        cands = fwd.compare_forward(
            *cols,
            validation=(val["slip"], val["kS"], val["phiS"], val["phiD"], val["Da"]),
            progress=bar.update,
        )
    chosen = fwd.select_forward(cands, args.tolerance)

    text = report(args, grid, n_total, n_fail, failure_report(status), table, eqfit, cands, chosen, val_info, eq_val)
    print()
    print(text)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "calibration_table.txt").write_text(text, encoding="utf-8")
    plot(out / "calibration.png", table, eqfit, chosen, val, eq_pred_val)

    lv = grid["levels"]
    params = asdict(base)
    model = {"params": params, "dt": args.dt, "kappa": args.kappa}
    grid_json = {
        "slip": np.round(lv["slip"], 12).tolist(),
        "kS": np.round(lv["kS"], 12).tolist(),
        "phiD": np.round(lv["phiD"], 12).tolist(),
        "dphi": np.round(lv["dphi"], 12).tolist(),
        "phiS": f"phiD + dphi, kept below pi/2 - {args.phis_margin:g} rad",
        "n_stances": int(n_total),
        "n_failed": n_fail,
        "n_used": int(n_total - n_fail),
        "n_soils": int(eqfit.soils.shape[0]),
        "validation": {
            "n_stances": val_info["n"],
            "n_failed": val_info["n_fail"],
            "seed": args.seed,
            "distribution": "uniform over the grid's slip, kS, phiD and dphi ranges",
        },
    }
    cal = fwd.build_calibration(eqfit, cands, chosen, model, grid_json, command, args.tolerance)
    cal["eq515"]["r2_end_to_end_val"] = json_number(eq_val["r2"])
    cal["eq515"]["rmse_end_to_end_val"] = json_number(eq_val["rmse"])
    json_path = PACKAGE_JSON if args.write_package_data else out / "calibration.json"
    written = write_calibration(cal, json_path)
    fwd.check_forward_section(cal_mod.load_calibration(json_path))  # round-trip check
    print(f"wrote {out / 'calibration_table.txt'}, {out / 'calibration.png'}"
          + (f", {json_path}" if written else f"; {json_path} left as it was (the same calibration: only the "
             f"time and command line of writing and float noise would have changed)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
