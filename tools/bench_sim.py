#!/usr/bin/env python
"""Benchmark the stick-slip simulators against a plain ``scipy.integrate.solve_ivp`` version.

In one run:

1. accuracy: ``Da`` from (a) ``simulate_stance``, (b) ``simulate_batch`` and
   (c) the ``solve_ivp`` implementation below, on test cases (docs/model.md's
   Fig. 5.5 reference cases, random ones and two with a contact loss), against a converged
   reference, the kernel at dt = 2.5e-5 s; all must agree within 0.5%. The
   ``solve_ivp`` model at a very tight tolerance is also compared with the
   reference (two independent integrators of the same equations);
2. step convergence: ``Da`` at dt and dt/2 on the reference cases (max
   relative change must be < 0.5%);
3. speed, in simulated leg cycles (propulsive half-stances) per second:
   ``simulate_stance`` per call (after a warm-up call; the JIT compile time
   is measured separately, cold, in a subprocess with an empty numba cache),
   ``simulate_batch`` on a few thousand random parameter sets within the
   docs/model.md's ranges, and ``solve_ivp`` on a handful of cycles under a time
   budget; ratios batch/solve_ivp and single/solve_ivp (target: batch >= 100x).

The ``solve_ivp`` model is written the way a user would: state
``[zH, vzH, xH, xC, vC]``, one right-hand side per regime (stick, slip,
contact lost), an event function for each regime switch (stick->slip:
``|FE| - muS FN`` crossing zero upwards; slip->stick: ``vC`` crossing zero;
contact loss: ``FN`` crossing zero downwards; contact resumes: the re-planted
leg becoming loaded) and a restart of the integration at each event.

    python tools/bench_sim.py [--n-batch 4000] [--ivp-cycles 5] [--ivp-budget 120]
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from scipy.integrate import solve_ivp
from tqdm import tqdm

from slipest.model.params import StickSlipParams, param_grid
from slipest.model.stance import simulate_batch, simulate_stance

DT = 1e-4  # default step of the kernel [s]
DT_REF = 2.5e-5  # converged reference step [s]
TOL = 0.005  # agreement required (relative)

#: Fig. 5.5 reference cases (docs/model.md section 4): label, parameter changes.
REFERENCE_CASES = [
    ("i=0.50", dict(slip=0.5)),
    ("i=0.25", dict(slip=0.25)),
    ("i=0.125", dict(slip=0.125)),
    ("kS=1.5k", dict(kS=1500.0)),
    ("kS=0.5k", dict(kS=500.0)),
    ("phiS=.70,phiD=.30", dict(phiS=0.70, phiD=0.30)),
    ("phiS=.52,phiD=.30", dict(phiS=0.52, phiD=0.30)),
    ("phiS=.35,phiD=.30", dict(phiS=0.35, phiD=0.30)),
]


def random_params(n: int, seed: int) -> list[StickSlipParams]:
    """Random parameter sets within docs/model.md's ranges: slip 0-0.5, kS 500-1500 N/m,
    phiD 0.1-0.4 rad, dphi 0-0.35 rad."""
    rng = np.random.default_rng(seed)
    phid = rng.uniform(0.1, 0.4, n)
    return param_grid(
        slip=rng.uniform(0.0, 0.5, n),
        kS=rng.uniform(500.0, 1500.0, n),
        phiD=phid,
        phiS=phid + rng.uniform(0.0, 0.35, n),
    )


# --------------------------------------------------------------------------- solve_ivp version

STICK, SLIP, AIR = 0, 1, 2


class IvpFailure(RuntimeError):
    """The solve_ivp integration failed (hub below ground, solver error, too many events)."""


def solve_ivp_stance(p: StickSlipParams, rtol: float = 1e-7, atol: float = 1e-10, method: str = "RK45",
                     sample_dt: float = 1e-4, max_segments: int = 20000) -> dict:
    """One propulsive half-stance of the model (docs/model.md section 3) with ``solve_ivp`` and event functions.

    State ``y = [zH, vzH, xH, xC, vC]`` [m, m/s]; leg angle ``theta = omega t``.
    ``Da`` [g] is max - min of the hub's gravity-free vertical acceleration,
    sampled every ``sample_dt`` [s] on each segment's dense output plus the
    segment ends. Only the nominal model (no damping, Stribeck, ripple).
    Returns ``{"delta_a_g", "breakaway_theta", "n_segments", "nfev"}``.
    """
    if p.b_hc or p.stribeck_vs or p.viscous or p.ripple_amp:
        raise ValueError("the solve_ivp baseline implements the nominal model only")
    ks, ls, kappa, mh, mf, g = p.kS, p.lS, p.kappa, p.MH, p.mF, p.g
    mus, mud, omega = p.muS, p.muD, p.omega
    t_end = (math.pi / p.nL) / omega

    def forces(t, y):
        """Normal force FN and tangential force FE on the foot [N] (leg force on the hub: (-FE, FN))."""
        th = omega * t
        s, c = math.sin(th), math.cos(th)
        zh, xh, xc = y[0], y[2], y[3]
        dx = xh - xc
        fs = ks * (ls - math.sqrt(zh * zh + dx * dx))  # Eq. 5.13, positive in compression
        off = dx * c - zh * s  # hub offset from the commanded leg line
        fhx = fs * s - kappa * ks * off * c
        fhz = fs * c + kappa * ks * off * s
        return fhz, -fhx

    def vxh(t):
        return (1.0 - p.slip) * ls * omega * math.cos(omega * t)

    def rhs_stick(t, y):
        fn, _ = forces(t, y)
        return [y[1], (fn - mh * g) / mh, vxh(t), 0.0, 0.0]

    def make_rhs_slip(direction):
        def rhs(t, y):
            fn, fe = forces(t, y)
            return [y[1], (fn - mh * g) / mh, vxh(t), y[4], (fe - mud * fn * direction) / mf]
        return rhs

    def rhs_air(t, y):
        return [y[1], -g, vxh(t), 0.0, 0.0]

    def ev_breakaway(t, y):
        fn, fe = forces(t, y)
        return abs(fe) - mus * fn
    ev_breakaway.terminal, ev_breakaway.direction = True, 1

    def ev_contact_loss(t, y):
        return forces(t, y)[0]
    ev_contact_loss.terminal, ev_contact_loss.direction = True, -1

    def ev_foot_stops(t, y):
        return y[4]
    ev_foot_stops.terminal = True

    def ev_landing(t, y):  # re-planted leg (on its line) loaded again: zH < lS cos(theta)
        return y[0] - ls * math.cos(omega * t)
    ev_landing.terminal, ev_landing.direction = True, -1

    def ev_below_ground(t, y):
        return y[0]
    ev_below_ground.terminal, ev_below_ground.direction = True, -1

    def az_samples(ts, ys, mode):
        """Gravity-free hub vertical acceleration [m/s^2] at times ``ts`` (vectorised ``forces``)."""
        if mode == AIR:
            return np.full(ts.size, -g)
        th = omega * ts
        s, c = np.sin(th), np.cos(th)
        dx = ys[2] - ys[3]
        fs = ks * (ls - np.sqrt(ys[0] ** 2 + dx**2))
        fhz = fs * c + kappa * ks * (dx * c - ys[0] * s) * s
        return (fhz - mh * g) / mh

    t = 0.0
    y = np.array([ls - mh * g / ks, 0.0, 0.0, 0.0, 0.0])  # static equilibrium at midstance
    mode, direction, just_landed = STICK, 0.0, False
    az_max, az_min = 0.0, 0.0
    breakaway = math.nan
    nfev = 0
    for n_seg in range(max_segments):
        # regime checks at the segment start (as the fixed-step kernel does every step)
        while True:
            if mode == AIR:
                # the unloaded foot is re-planted on the leg line, at rest; contact resumes as soon
                # as that leg is loaded (zH < lS cos(theta)), possibly at once
                th = omega * t
                y[3], y[4] = y[2] - y[0] * math.tan(th), 0.0
                if y[0] < ls * math.cos(th):
                    mode, just_landed = STICK, True
                    continue
            elif mode == STICK:
                fn, fe = forces(t, y)
                if fn <= 0.0 and not just_landed:
                    mode = AIR
                    continue
                if fn > 0.0 and abs(fe) > mus * fn:
                    mode, direction = SLIP, (1.0 if fe > 0 else -1.0)
                    if math.isnan(breakaway):
                        breakaway = omega * t
            break
        just_landed = False
        if mode == STICK:
            rhs, events = rhs_stick, [ev_breakaway, ev_contact_loss, ev_below_ground]
        elif mode == SLIP:
            ev_foot_stops.direction = -direction  # vC returns to zero from the side it slid to
            rhs, events = make_rhs_slip(direction), [ev_foot_stops, ev_contact_loss, ev_below_ground]
        else:
            rhs, events = rhs_air, [ev_landing, ev_below_ground]
        sol = solve_ivp(rhs, (t, t_end), y, method=method, rtol=rtol, atol=atol, events=events, dense_output=True)
        nfev += sol.nfev
        if sol.status == -1:
            raise IvpFailure(f"solve_ivp failed at theta = {omega * t:.3f}: {sol.message}")
        t_stop = sol.t[-1]
        ts = np.append(np.arange(t, t_stop, sample_dt), t_stop)
        az = az_samples(ts, sol.sol(ts), mode)
        az_max, az_min = max(az_max, float(az.max())), min(az_min, float(az.min()))
        t, y = t_stop, sol.y[:, -1].copy()
        if sol.status == 0:  # reached the end of the stance
            return {"delta_a_g": (az_max - az_min) / g, "breakaway_theta": breakaway,
                    "n_segments": n_seg + 1, "nfev": nfev}
        fired = min((te[0], k) for k, te in enumerate(sol.t_events) if te.size)[1]
        event = events[fired]
        if event is ev_below_ground:
            raise IvpFailure(f"the hub fell below the ground at theta = {omega * t:.3f}")
        if event is ev_breakaway:
            mode, direction = SLIP, (1.0 if forces(t, y)[1] > 0 else -1.0)
            if math.isnan(breakaway):
                breakaway = omega * t
        elif event is ev_foot_stops:
            mode, y[4] = STICK, 0.0
        elif event is ev_contact_loss:
            mode = AIR
        elif event is ev_landing:  # foot re-planted on the leg line, at rest, in stick
            th = omega * t
            y[3], y[4] = y[2] - y[0] * math.tan(th), 0.0
            mode, just_landed = STICK, True
    raise IvpFailure(f"more than {max_segments} regime switches in one stance")


# --------------------------------------------------------------------------- benchmark


def cold_compile_time(which: str) -> float:
    """Seconds to import and JIT-compile the kernel from scratch (empty numba cache, subprocess)."""
    code = (
        "import time; t0 = time.perf_counter()\n"
        "from slipest.model.stance import simulate_stance, simulate_batch\n"
        "from slipest.model.params import StickSlipParams\n"
        f"{'simulate_stance(StickSlipParams())' if which == 'stance' else 'simulate_batch([StickSlipParams()])'}\n"
        "print(time.perf_counter() - t0)\n"
    )
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def rel(a: float, b: float) -> float:
    return abs(a - b) / abs(b)


def _timed(fn):
    """Run ``fn()``; returns ``(result, wall seconds, CPU seconds of this process, all threads)``."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-batch", type=int, default=4000, help="random parameter sets for the batch timing")
    ap.add_argument("--single-calls", type=int, default=30, help="simulate_stance calls timed")
    ap.add_argument("--ivp-cycles", type=int, default=5,
                    help="random cycles (from the batch's set) timed with solve_ivp; also in the accuracy check")
    ap.add_argument("--ivp-budget", type=float, default=120.0, help="time budget of the solve_ivp timing [s]")
    ap.add_argument("--ivp-rtol", type=float, default=None,
                    help="solve_ivp relative tolerance (default: the loosest of 1e-3..1e-8 meeting the 0.5%% check)")
    ap.add_argument("--ivp-ref-rtol", type=float, default=1e-10, help="solve_ivp tolerance of the cross-check")
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats (the best is kept)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    failures = []
    import numba

    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, numba {numba.__version__} "
          f"({numba.get_num_threads()} threads), {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")

    # ---- compile times
    print("\n== JIT compile (cold: empty numba cache, new process, including imports)")
    t_cold_stance = cold_compile_time("stance")
    t_cold_batch = cold_compile_time("batch")
    print(f"   simulate_stance first call: {t_cold_stance:.1f} s;  simulate_batch first call: {t_cold_batch:.1f} s")
    _, t_warm_stance, _ = _timed(lambda: simulate_stance(StickSlipParams()))
    _, t_warm_batch, _ = _timed(lambda: simulate_batch([StickSlipParams()]))
    print(f"   in this process, first calls (from numba's on-disk cache): stance {t_warm_stance:.2f} s, "
          f"batch {t_warm_batch:.2f} s; excluded from the timings below")

    # ---- accuracy
    base = StickSlipParams()
    rand = random_params(args.n_batch, args.seed)
    cases = [(label, base.with_(**ch)) for label, ch in REFERENCE_CASES]
    cases += [(f"random #{k}", p) for k, p in enumerate(rand[: args.ivp_cycles])]
    # cases where the foot loses contact (re-planting rule), so that every regime switch is checked
    pool = rand[args.ivp_cycles : args.ivp_cycles + 600]
    lost = np.flatnonzero(simulate_batch(pool, dt=DT, on_error="flag").n_contact_losses > 0)[:2]
    cases += [(f"contact loss #{k}", pool[j]) for k, j in enumerate(lost)]
    params = [p for _, p in cases]
    print(f"\n== Da agreement with the converged reference (kernel at dt = {DT_REF:g} s); tolerance {TOL:.1%}")
    ref = simulate_batch(params, dt=DT_REF).delta_a_g
    single = np.array([simulate_stance(p, dt=DT).delta_a_g for p in params])
    batch = simulate_batch(params, dt=DT).delta_a_g

    def ivp_all(rtol, atol=1e-10, desc=None):
        it = tqdm(params, desc=desc, unit="cycle", leave=False) if desc else params
        return [solve_ivp_stance(p, rtol=rtol, atol=atol) for p in it]

    ladder = [args.ivp_rtol] if args.ivp_rtol else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
    rtol = None
    for r in ladder:
        runs = ivp_all(r, desc=f"solve_ivp rtol {r:g}")
        ivp = np.array([x["delta_a_g"] for x in runs])
        worst_r = max(rel(a, b) for a, b in zip(ivp, ref))
        print(f"   solve_ivp rtol {r:g}: worst Da error vs reference {100 * worst_r:.3f}%")
        if worst_r < TOL:
            rtol = r
            break
    if rtol is None:
        rtol = ladder[-1]
        failures.append(f"no solve_ivp tolerance down to {rtol:g} meets {100 * TOL:.1f}%")
    ivp_seg = [x["n_segments"] for x in runs]
    ivp_ref = np.array([x["delta_a_g"] for x in ivp_all(args.ivp_ref_rtol, 1e-12, "solve_ivp tight cross-check")])
    print(f"   solve_ivp benchmarked at rtol = {rtol:g} (atol 1e-10; method RK45)")
    print(f"   {'case':<20} {'ref Da [g]':>10} | {'single':>8} {'batch':>8} {'ivp':>8} {'ivp-tight':>9} | relative error "
          f"vs ref (single, batch, ivp, ivp-tight) | ivp segments")
    for j, (label, p) in enumerate(cases):
        errs = [rel(single[j], ref[j]), rel(batch[j], ref[j]), rel(ivp[j], ref[j]), rel(ivp_ref[j], ref[j])]
        flag = "" if max(errs) < TOL else "  <-- EXCEEDS"
        print(f"   {label:<20} {ref[j]:10.4f} | {single[j]:8.4f} {batch[j]:8.4f} {ivp[j]:8.4f} {ivp_ref[j]:9.4f} | "
              + " ".join(f"{100 * e:6.3f}%" for e in errs) + f" | {ivp_seg[j]:4d}{flag}")
    worst = {
        "single": max(rel(a, b) for a, b in zip(single, ref)),
        "batch": max(rel(a, b) for a, b in zip(batch, ref)),
        "solve_ivp": max(rel(a, b) for a, b in zip(ivp, ref)),
        f"solve_ivp rtol {args.ivp_ref_rtol:g}": max(rel(a, b) for a, b in zip(ivp_ref, ref)),
    }
    print("   worst: " + ", ".join(f"{k} {100 * v:.3f}%" for k, v in worst.items()))
    for k, v in worst.items():
        if v >= TOL:
            failures.append(f"{k} Da differs from the reference by {100 * v:.2f}% (>= {100 * TOL:.1f}%)")
    print(f"   simulate_stance and simulate_batch identical to the last bit: {np.array_equal(single, batch)}")

    # ---- step convergence
    print(f"\n== step convergence on the reference cases: Da at dt = {DT:g} s and dt/2")
    ref_params = params[: len(REFERENCE_CASES)]
    d1 = simulate_batch(ref_params, dt=DT).delta_a_g
    d2 = simulate_batch(ref_params, dt=DT / 2).delta_a_g
    for (label, _), a, b in zip(REFERENCE_CASES, d1, d2):
        print(f"   {label:<20} {a:8.4f} {b:8.4f}  change {100 * rel(a, b):.3f}%")
    conv = max(rel(a, b) for a, b in zip(d1, d2))
    print(f"   max relative change: {100 * conv:.3f}% (must be < {100 * TOL:.1f}%)")
    if conv >= TOL:
        failures.append(f"step convergence: halving dt changes Da by {100 * conv:.2f}%")

    # ---- speed
    load0 = os.getloadavg()[0]
    print(f"\n== speed (simulated leg cycles per second; best of {args.repeats} repeats; wall clock, and per "
          "CPU-second of this process)")

    def singles():
        for _ in range(args.single_calls):
            simulate_stance(base, dt=DT)

    def best(fn, label):
        runs = []
        for _ in tqdm(range(args.repeats), desc=label, unit="repeat", leave=False):
            runs.append(_timed(fn))
        return min(runs, key=lambda r: r[1])

    _, w_single, c_single = best(singles, "simulate_stance timing")
    simulate_batch(rand[:16], dt=DT, on_error="flag")
    rb, w_batch, c_batch = best(lambda: simulate_batch(rand, dt=DT, on_error="flag"), "simulate_batch timing")
    n_bad = int((~rb.ok).sum())
    ivp_set = rand[: args.ivp_cycles]
    per_cycle = np.full((args.repeats, len(ivp_set), 2), np.inf)  # wall, CPU [s]
    t0 = time.perf_counter()
    with tqdm(total=args.repeats * len(ivp_set), desc=f"solve_ivp timing (budget {args.ivp_budget:g} s)",
              unit="cycle", leave=False) as bar:
        for rep in range(args.repeats):
            for k, p in enumerate(ivp_set):
                _, w, c = _timed(lambda: solve_ivp_stance(p, rtol=rtol))
                per_cycle[rep, k] = (w, c)
                bar.update(1)
                if time.perf_counter() - t0 > args.ivp_budget:
                    break
            if time.perf_counter() - t0 > args.ivp_budget:
                break
    done = np.isfinite(per_cycle[:, :, 0]).any(axis=0)
    n_ivp = int(done.sum())
    w_ivp = float(per_cycle[:, done, 0].min(axis=0).sum())
    c_ivp = float(per_cycle[:, done, 1].min(axis=0).sum())
    load1 = os.getloadavg()[0]
    rows = [
        (f"simulate_stance (dt {DT:g} s, every signal recorded; {args.single_calls} calls)", args.single_calls,
         w_single, c_single),
        (f"simulate_batch  ({args.n_batch} random sets, {numba.get_num_threads()} threads; {n_bad} failed)",
         args.n_batch, w_batch, c_batch),
        (f"solve_ivp       (RK45, rtol {rtol:g}; {n_ivp} random cycles of the same set)", n_ivp, w_ivp, c_ivp),
    ]
    rates = {}
    for (label, n, w, c), key in zip(rows, ("single", "batch", "ivp")):
        rates[key] = (n / w, n / c)
        print(f"   {label:<78} {1e3 * w / n:9.2f} ms/cycle  {n / w:9.1f} cycles/s wall  {n / c:9.1f} per CPU-s")
    rb_w, rb_c = rates["batch"][0] / rates["ivp"][0], rates["batch"][1] / rates["ivp"][1]
    rs_w, rs_c = rates["single"][0] / rates["ivp"][0], rates["single"][1] / rates["ivp"][1]
    print(f"   batch / solve_ivp : {rb_w:7.0f}x wall, {rb_c:7.0f}x per CPU-second   "
          f"(target >= 100x wall: {'met' if rb_w >= 100 else 'NOT met'})")
    print(f"   single / solve_ivp: {rs_w:7.0f}x wall, {rs_c:7.0f}x per CPU-second")
    # the baseline's cost depends on its tolerance: show it (the headline uses the loosest passing one)
    print("   solve_ivp cost vs tolerance (same cycles, one pass each; CPU time, less sensitive to load):")
    for r in (1e-4, 1e-5, 1e-6, 1e-7, 1e-8):
        if r > rtol:
            continue
        c = sum(_timed(lambda: solve_ivp_stance(p, rtol=r))[2] for p in ivp_set[:n_ivp])
        err = max(rel(solve_ivp_stance(p, rtol=r)["delta_a_g"], ref[len(REFERENCE_CASES) + k])
                  for k, p in enumerate(ivp_set[:n_ivp]))
        print(f"     rtol {r:7.0e}: {n_ivp / c:8.1f} cycles per CPU-s, batch/solve_ivp "
              f"{rates['batch'][1] * c / n_ivp:6.0f}x per CPU-second, worst Da error on these cycles {100 * err:.3f}%")
    busy = max(load0, load1) > 0.75 * (os.cpu_count() or 1)
    print(f"   load average during the timing: {load0:.1f} -> {load1:.1f} on {os.cpu_count()} CPUs"
          + ("  (machine busy: wall-clock figures, above all the 2-thread batch's, are depressed)" if busy else ""))
    target_note = None
    if rb_w < 100:  # a reported target, not a correctness check: it does not change the exit status
        target_note = (f"speed target NOT met: batch is {rb_w:.0f}x faster than solve_ivp in wall-clock time "
                       f"({rb_c:.0f}x per CPU-second; target 100x)" + (" on a busy machine" if busy else ""))

    print()
    if target_note:
        print(target_note)
    if failures:
        print("FAILED checks:\n  " + "\n  ".join(failures))
        return 1
    print("all accuracy and convergence checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
