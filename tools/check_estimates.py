#!/usr/bin/env python3
"""Numerical equality check of the online estimates against a saved reference.

Runs :class:`slipest.online.SlipEstimator` over a log (default: the 10-minute
log of ``tools/bench_replay.py``, written to a temporary directory) three
ways: ``push_many`` on the whole log, ``push`` one sample at a time (both
soil unknown, no reference), and ``push_many`` with ``use_reference=True``
(the soil learnt from the log's slip column). ``push`` and ``push_many``
must agree exactly. With ``--save`` the estimates are written to an
``.npz``; with ``--against`` they are compared with one written before (by
another version of the code): every cycle's quality must match, and the
largest differences of ``slip`` [-] and ``dphi`` [rad] (and, printed, of
every other numeric field) must be within ``--tol`` (default 1e-4: float32
rounding of the compiled kernels).

    python tools/check_estimates.py --save /tmp/ref.npz        # on the old code
    python tools/check_estimates.py --against /tmp/ref.npz     # on the new code
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from slipest.io.log_csv import LogReader
from slipest.online import ESTIMATE_FIELDS, SlipEstimator

CHECKED = ("slip", "dphi")  # fields held to --tol


def _arrays(estimates) -> dict:
    out = {}
    for name in ESTIMATE_FIELDS:
        vals = [getattr(e, name) for e in estimates]
        out[name] = np.array(vals, dtype=str if name == "quality" else float)
    return out


def run(log: Path) -> dict:
    """Estimates of the three runs, ``{run/field: array}``; checks push == push_many."""
    with LogReader(log) as r:
        d = r.read_all()
    n_legs = d.metadata.n_legs or 4
    many = SlipEstimator(n_legs=n_legs).push_many(d.t, d.az, d.theta)
    est = SlipEstimator(n_legs=n_legs)
    push = est.push
    one = []
    for a, b, c in zip(d.t.tolist(), d.az.tolist(), d.theta.tolist()):
        r_ = push(a, b, c)
        if r_:
            one.extend(r_)
    if one != many:
        bad = next(i for i, (x, y) in enumerate(zip(one, many)) if x != y) if len(one) == len(many) else -1
        raise SystemExit(f"FAIL: push and push_many differ ({len(one)} vs {len(many)} estimates, first at {bad})")
    ref = SlipEstimator(n_legs=n_legs, use_reference=True).push_many(d.t, d.az, d.theta, d.slip)
    res = {f"default/{k}": v for k, v in _arrays(many).items()}
    res.update({f"reference/{k}": v for k, v in _arrays(ref).items()})
    return res


def compare(new: dict, old: dict, tol: float) -> bool:
    ok = True
    for run_ in ("default", "reference"):
        qn, qo = new[f"{run_}/quality"], old[f"{run_}/quality"]
        if qn.shape != qo.shape or not np.array_equal(qn, qo):
            print(f"{run_}: FAIL: cycles or qualities differ ({qn.size} vs {qo.size} estimates)")
            ok = False
            continue
        parts = []
        for name in ESTIMATE_FIELDS:
            if name == "quality":
                continue
            a, b = new[f"{run_}/{name}"], old[f"{run_}/{name}"]
            if not np.array_equal(np.isnan(a), np.isnan(b)):
                print(f"{run_}: FAIL: {name} is NaN on different cycles")
                ok = False
                continue
            fin = ~np.isnan(a)
            diff = float(np.max(np.abs(a[fin] - b[fin]))) if fin.any() else 0.0
            parts.append(f"{name} {diff:.2e}")
            if name in CHECKED and not diff <= tol:
                print(f"{run_}: FAIL: {name} differs by {diff:.3e} > {tol:g}")
                ok = False
        print(f"{run_} ({qn.size} estimates, {int((qn == 'ok').sum())} ok), max |new - old|: " + ", ".join(parts))
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", help="log to run on (default: write the 10-minute benchmark log)")
    ap.add_argument("--save", help="write the estimates to this .npz")
    ap.add_argument("--against", help="compare with the estimates in this .npz")
    ap.add_argument("--tol", type=float, default=1e-4, help="largest allowed difference of slip and dphi (default 1e-4)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="slipest-check-") as tmp:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_replay import log_or_default

        log = log_or_default(args.log, tmp)
        res = run(log)
    print(f"push and push_many identical ({res['default/cycle'].size} estimates)")
    if args.save:
        np.savez_compressed(args.save, **res)
        print(f"saved {args.save}")
    if args.against:
        with np.load(args.against) as z:
            old = {k: z[k] for k in z.files}
        ok = compare(res, old, args.tol)
        print("equality check:", "PASS" if ok else "FAIL", f"(tolerance {args.tol:g} on {', '.join(CHECKED)})")
        return 0 if ok else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
