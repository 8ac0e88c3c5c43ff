"""The calibration's report for people: what was found, the gap before and after, what is left (pure computation).

:func:`report_lines` words a :attr:`slipest.rover.calibrate.Calibration.report`
(the dict the rover file keeps) as lines of text; ``slipest calibrate``
prints them.
"""

from __future__ import annotations

import math


def _pct(x) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{100 * x:.0f}%"


def _num(x, fmt: str = ".3f") -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, fmt)


def _params(d: dict) -> str:
    return ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in d.items() if k != "name")


def _blind(fig: dict) -> str:
    line = f"slip RMSE {_num(fig['slip_rmse'])}, 95% intervals cover {_pct(fig['coverage'])}"
    share = fig.get("estimated", 1.0)  # files written before the share was reported estimated every cycle
    return line if share >= 1.0 else f"{line} of the {_pct(share)} of cycles estimated"


def report_lines(report: dict) -> list[str]:
    """The report as lines (see the module docstring)."""
    out = []
    runs = report["runs"]
    out.append(f"testbed: {len(runs)} log(s), calibrated in {report['seconds']:.0f} s")
    for r in runs:
        s = r["soil"]
        flagged = ", ".join(f"{k} {v}" for k, v in sorted(r["flagged"].items()))
        out.append(f"  {r['name']}: {r['estimated_with_reference']} of {r['cycles']} leg cycles used, "
                   f"{r['slip_levels']} slip levels, {r['omega']:.2f} rad/s; soil found kS {s['kS']:.0f} N/m, "
                   f"phiS {s['phiS']:.3f}, dphi {s['dphi']:.3f} rad" + (f" (not estimated: {flagged})" if flagged else ""))
    imu = report["imu"]
    out.append(f"IMU: noise {imu['noise_g']:.4f} g at {imu['rate_hz']:.0f} Hz")
    out.append("diagnosis (each log on its own soil):")
    for d in report["diagnosis"]:
        if "kappa" not in d:
            out.append(f"  {d['run']}: {d['verdict']}")
            continue
        line = f"  {d['run']}: kappa {d['kappa']:.2f}, verdict {d['verdict']}"
        if d["ranking"]:
            top = d["ranking"][0]
            line += (f"; best effect {top['effect']} ({_params(top['params'])}), held-out gap "
                     f"{1000 * d['gap_nominal_g']:.1f} -> {1000 * top['gap_heldout_g']:.1f} mg")
        else:
            line += f"; held-out gap {1000 * d['gap_nominal_g']:.1f} mg (the nominal model explains the log)"
        out.append(line)
    corr = report["correction"]
    eff = corr["effect"]
    if eff is None:
        tried = ", ".join(f"{c['label']} ({_blind(c['blind'])})" for c in report["candidates"]) or "none"
        out.append(f"correction: no catalog effect used (tried: {tried})")
    elif eff.get("angle_offset"):
        what = "; ".join(f"{e['name']} ({_params(e)})" for e in eff["effects"])
        out.append(f"correction: {what} removed from the samples: {eff['angle_offset']:+.4f} rad (encoder angle minus "
                   f"true angle at the testbed's leg speed) subtracted from every theta sample ({eff['origin']})")
    elif eff.get("disturbance") and eff["effects"]:
        what = "; ".join(f"{e['name']} ({_params(e)})" for e in eff["effects"])
        out.append(f"correction: {what} removed from the samples before their features are computed, as its "
                   f"waveform over the leg phase at the testbed's leg speed ({eff['origin']})")
    elif eff.get("disturbance"):
        out.append("correction: a disturbance locked to the leg phase, removed from the samples before their "
                   f"features are computed ({eff['origin']}; no catalog effect explained the logs as well)")
    else:
        what = "; ".join(f"{e['name']} ({_params(e)})" for e in eff["effects"]) or eff["label"]
        out.append(f"correction: the simulator with {what}, kappa {eff['kappa']:.2f} ({eff['origin']}), as a "
                   "feature discrepancy over slip and soil")
    tb = corr["testbed"]
    out.append(f"  testbed correction in slip: {'used' if tb['used'] else 'not used'} ({tb['how']}: blind slip RMSE "
               f"{_num(tb['heldout_without']['slip_rmse'])} without, {_num(tb['heldout_with']['slip_rmse'])} with)")
    b, a = report["before"], report["after"]
    out.append(f"blind estimates of the testbed logs (soil unknown, reference ignored): before {_blind(b['blind'])}; "
               f"after {_blind(a['blind'])}")
    out.append(f"held-out slip levels, feature misfit (1: within the model's scatter): {_num(b['feature_misfit'], '.2f')} "
               f"before, {_num(a['feature_misfit'], '.2f')} after")
    scale = corr.get("interval_scale")
    if scale and scale["scale"] > 1.0:
        out.append(f"intervals widened {scale['scale']:.2f}x: the blind estimates of held-out testbed logs covered "
                   f"{_pct(scale['coverage_before'])} of their slips at 95% ({scale['n']} cycles); the rover "
                   "departs from the model in a way the correction does not capture")
    un = report["unexplained"]
    biases = ", ".join(f"{x['feature']} {x['bias_sd']:+.2f} sd" for x in un["largest_feature_bias"])
    out.append(f"left unexplained: covariance widened {un['covariance_factor']:.2f}x for the held-out scatter; "
               f"largest remaining mean residuals: {biases}")
    e = report.get("eq515")
    if e:
        out.append(f"Eq. 5.15 refitted ({e['how']}): slip RMSE {_num(e['rmse_end_to_end'])} over the testbed cycles")
    return out


__all__ = ["report_lines"]
