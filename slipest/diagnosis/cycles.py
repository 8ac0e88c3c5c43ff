"""Logged leg cycles on the diagnosis's phase grid (pure computation).

A log (arrays ``t`` [s], ``az`` [m/s^2] specific force with gravity,
``theta`` [rad] with 0 at every midstance, unwrapped or wrapped (then
unwrapped here), ``slip`` [-]) is cut
into leg cycles by phase: cycle ``k`` holds the samples whose phase
``phi = theta - 2 pi k/nL`` lies in ``[-pi/nL, pi/nL)`` (the project's log
convention, :mod:`slipest.model.stream`). A cycle is kept when it is
complete (every analysis bin holds a sample, no NaN) and its slip is
known. Each kept cycle's ``az`` is averaged over the analysis bins of the
:class:`~slipest.diagnosis.predict.Grid` (equal bins of logged phase), and
each bin mean is referred to the bin centre to first order (minus the local
slope times the offset of the samples' centroid from the centre).

The cycle's slip is the logged slip at its midstance sample (logged phase
nearest 0); ``prev_slip`` is the previous cycle's, which the model needs for
the transients that cross the boundary (filter memory, an encoder offset).
A cycle with no samples of the previous one in the log (the run's first
cycle) is dropped: its history is not the steady sequence the prediction
assumes. Bins without samples (a coarse encoder repeats angles) are
interpolated from their neighbours, if at least :data:`MIN_FILLED` of the
bins hold samples. A cycle whose phase goes backwards (the rover reversing)
or holds a non-finite ``az`` is dropped; so is a cycle holding samples of a
cycle replay's segmenter flags (``gap``, ``reverse``, ``time``, ``nan``...:
:func:`segmenter_flags`, counted by flag), and a log whose leg angle goes
back (two drives in one file) is cut into runs at each reversal. Isolated
outliers of ``az`` (a glitch of any size) are left out of a kept cycle's
samples with the estimator's rule (:func:`slipest.despike.outliers`). A
coarse encoder's angle (whole counts, repeated over several samples) is
interpolated between its count changes first (:func:`slipest.dequantize.dequantize_log`, the stream's
interpolation over the whole log).

Each cycle's leg speed ``omega`` is the mean speed of its *speed level*:
cycles whose speeds (least-squares slope of ``theta`` over the cycle)
agree within :data:`SPEED_TOLERANCE` form one level (so a drive that holds
its speed gives one level, and the prediction simulates one stance per
level and slip), whose speed is the leg-cycle angle over the median
duration of its cycles (boundary to boundary; the median leaves out a
cycle that straddles a change of speed, e.g. with an encoder offset; a ripple within the cycle
averages out). A log at one speed level has the speed of the whole log, as
before. ``prev_omega`` is the previous cycle's.

``touchdowns`` counts the cycle boundaries (touchdowns of a leg) from the
log's start up to and including the cycle's own start: the log's first
boundary, or its first sample when that sits on one, is the first
touchdown (a log that starts with the motion, as the simulator's do), so
transients that build up over many cycles (a long-ringing touchdown
impact) can be predicted from the log's start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slipest.dequantize import dequantize_log
from slipest.despike import outliers
from slipest.diagnosis.predict import Grid

#: Fewest share of the analysis bins a cycle's samples must fill (the rest are interpolated).
MIN_FILLED = 0.1

#: Relative spread of leg speeds [-] within which cycles share one speed level (see the module docstring).
SPEED_TOLERANCE = 0.02

#: Why a leg cycle of a log is not used (counted, and named when no cycle is left).
DROP_REASONS = ("incomplete", "no reference slip", "first of the log", "backwards or non-finite az", "flagged")

#: What a log without reference slip needs (the end of that error message).
NEEDS_SLIP = ("The diagnosis compares each leg cycle with the model at the slip the wheel really had, so it "
              "needs that slip logged: a testbed's log, or a live recording of a device that sends the reference "
              "slip (serial SLIP_REFERENCE frames, CAN SlipReference messages; firmware-sim --send-reference). "
              "To estimate the slip of this log instead, use 'slipest replay'.")


@dataclass
class CycleSet:
    """Binned cycles of one or more logs.

    y: ``(C, nb)`` bin averages of ``az`` [m/s^2]; count: samples per bin;
    slip, prev_slip: ``(C,)`` [-]; omega, prev_omega: ``(C,)`` leg speed
    of the cycle's speed level and of the previous cycle's [rad/s] (see the
    module docstring; ``prev_omega`` defaults to ``omega``); touchdowns:
    ``(C,)`` cycle boundaries since the log's start (see the module
    docstring; default infinity: a long history); log: ``(C,)``
    log index; k: cycle number in its log;
    t0: ``(C,)`` start time [s]; speed: ``(C, nb)`` leg speed per bin from
    the encoder [rad/s]; noise: white-noise standard deviation of
    one sample [m/s^2] per log (median absolute second difference);
    samples: per cycle, the raw ``(phase, az)`` arrays (for plots and features).
    """

    grid: Grid
    y: np.ndarray
    count: np.ndarray
    slip: np.ndarray
    prev_slip: np.ndarray
    omega: np.ndarray
    log: np.ndarray
    k: np.ndarray
    t0: np.ndarray
    speed: np.ndarray
    noise: np.ndarray
    samples: list = field(default_factory=list, repr=False)
    dropped: int = 0
    prev_omega: np.ndarray | None = None
    touchdowns: np.ndarray | None = None
    repaired: int = 0
    left_out: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.prev_omega is None:
            self.prev_omega = np.array(self.omega, dtype=float, copy=True)
        if self.touchdowns is None:
            self.touchdowns = np.full(len(self.slip), np.inf)

    def __len__(self) -> int:
        return len(self.slip)

    def subset(self, idx) -> "CycleSet":
        idx = np.asarray(idx)
        return CycleSet(
            grid=self.grid,
            y=self.y[idx],
            count=self.count[idx],
            slip=self.slip[idx],
            prev_slip=self.prev_slip[idx],
            omega=self.omega[idx],
            log=self.log[idx],
            k=self.k[idx],
            t0=self.t0[idx],
            speed=self.speed[idx],
            noise=self.noise,
            samples=[self.samples[i] for i in np.atleast_1d(idx)] if self.samples else [],
            prev_omega=self.prev_omega[idx],
            touchdowns=self.touchdowns[idx],
        )

    @property
    def noise_bin(self) -> np.ndarray:
        """Expected white-noise variance of each bin average, ``(C, nb)`` [(m/s^2)^2]."""
        return (self.noise[self.log][:, None] ** 2) / np.maximum(self.count, 1)

    @property
    def n_legs(self) -> int:
        return self.grid.n_legs


def sample_noise(az: np.ndarray) -> float:
    """Standard deviation [same unit as az] of white noise on a smooth signal: 1.4826 median|d2| / sqrt(6)."""
    a = np.asarray(az, dtype=float)
    a = a[np.isfinite(a)]
    if a.size < 3:
        return float("nan")
    d2 = np.abs(a[2:] - 2 * a[1:-1] + a[:-2])
    return float(1.4826 * np.median(d2) / math.sqrt(6.0))


def cut_cycles(t, az, theta, slip, n_legs: int, grid: Grid | None = None, log_index: int = 0,
               keep_samples: bool = True, flags=None) -> CycleSet:
    """The complete cycles of one log, binned (see the module docstring).

    ``ValueError`` when no cycle is usable, saying why: the reference slip
    missing (``slip`` all NaN, or NaN at every complete cycle's midstance),
    else the count of cycles dropped by reason (:data:`DROP_REASONS`).

    ``flags``: ``(code, names)`` from :func:`segmenter_flags` (None: not checked): a cycle holding a
    sample of a cycle the segmenter flags is left out (counted by flag in ``left_out``, as ``"flagged"`` in
    ``dropped``). Isolated outliers of ``az`` (:func:`slipest.despike.outliers`, a glitch of any size) are left
    out of the kept cycles' samples, as the estimator leaves them out (counted in ``repaired``).
    """
    t = np.asarray(t, dtype=float)
    az = np.asarray(az, dtype=float)
    theta = np.asarray(theta, dtype=float)
    if slip is None:
        raise ValueError("the diagnosis needs the logged slip (column 'slip')")
    slip = np.asarray(slip, dtype=float)
    if not (t.shape == az.shape == theta.shape == slip.shape):
        raise ValueError("t, az, theta and slip must have the same length")
    grid = grid or Grid(n_legs)
    if flags is not None and len(flags) > 2 and len(flags[2]):
        return _cut_runs(t, az, theta, slip, n_legs, grid, log_index, keep_samples, flags)
    half = math.pi / n_legs
    ok = np.isfinite(t) & np.isfinite(theta)
    t, az, theta, slip = t[ok], az[ok], theta[ok], slip[ok]
    if t.size < 10:
        raise ValueError("the log has fewer than 10 usable samples")
    if not np.isfinite(slip).any():
        raise ValueError(f"the reference slip is missing: the 'slip' column holds no value ({slip.size} rows, all "
                         f"NaN). {NEEDS_SLIP}")
    theta = dequantize_log(t, theta)  # unwrapped (0 stays at a midstance) and interpolated between whole counts
    k = np.floor((theta + half) / (2 * half)).astype(np.int64)
    phase = theta - 2 * half * k
    noise = sample_noise(az)
    edges = grid.bin_edges
    centres = grid.bin_centres
    starts = np.flatnonzero(np.r_[True, np.diff(k) != 0])
    ends = np.r_[starts[1:], k.size]
    ys, counts, slips, ks, t0s, samples, speeds = [], [], [], [], [], [], []
    slip_of_k = {}
    why = dict.fromkeys(DROP_REASONS, 0)  # cycles dropped, by reason
    left_out = {}  # cycles the segmenter flags, by flag (counted in why["flagged"])
    repaired = 0  # glitch samples left out of kept cycles
    flagged, flag_names = (None, None) if flags is None else flags[:2]
    if flagged is not None:
        flagged = np.asarray(flagged)[ok]
    for s0, s1 in zip(starts, ends):
        ph = phase[s0:s1]
        sl = slip[s0:s1]
        j0 = int(np.argmin(np.abs(ph)))
        slip_of_k[int(k[s0])] = float(sl[j0]) if np.isfinite(sl[j0]) else np.nan
    for s0, s1 in zip(starts, ends):
        kk = int(k[s0])
        ph = phase[s0:s1]
        a = az[s0:s1]
        if np.any(np.diff(ph) < 0) or not np.all(np.isfinite(a)):
            why["backwards or non-finite az"] += 1
            continue
        tt = t[s0:s1]
        spikes = outliers(a)  # isolated glitches (any size) left out, as the estimator does (slipest.despike)
        n_spikes = int(np.count_nonzero(spikes))
        if n_spikes:
            keep = ~spikes
            ph, a, tt = ph[keep], a[keep], tt[keep]
        b = np.clip(np.searchsorted(edges, ph, side="right") - 1, 0, grid.nb - 1)
        cnt = np.bincount(b, minlength=grid.nb).astype(float)
        filled = cnt > 0
        complete = ph[0] - edges[0] < 4 * (edges[1] - edges[0]) and edges[-1] - ph[-1] < 4 * (edges[1] - edges[0])
        # incomplete, slip unknown, or no history: the first cycle of a run has no previous stance
        # (filter state, earlier transients), which the prediction assumes
        reason = ("incomplete" if not complete or filled.mean() < MIN_FILLED
                  else "no reference slip" if not np.isfinite(slip_of_k[kk])
                  else "first of the log" if (kk - 1) not in slip_of_k else None)
        if reason is not None:
            why[reason] += 1
            continue
        if flagged is not None and flagged[s0:s1].any():  # the segmenter flags it: replay does not estimate it
            flag = str(flag_names[int(flagged[s0:s1].max())])
            left_out[flag] = left_out.get(flag, 0) + 1
            continue
        repaired += n_spikes
        safe = np.maximum(cnt, 1)
        mean = np.bincount(b, weights=a, minlength=grid.nb) / safe
        # refer every bin mean to its bin centre: the samples' centroid sits up to half a sample period
        # off the centre (and differently in every cycle), which on a 0.5 g, 6 Hz oscillation is ~0.01 g
        centroid = np.bincount(b, weights=ph, minlength=grid.nb) / safe
        if filled.all():
            slope = np.gradient(mean, centres)
            ys.append(mean - slope * (centroid - centres))
        else:
            # a coarse encoder leaves bins empty: interpolate the bin means at the bin centres
            ys.append(np.interp(centres, centroid[filled], mean[filled]))
        counts.append(cnt)
        slips.append(slip_of_k[kk])
        ks.append(kk)
        t0s.append(t[s0])
        # leg speed per bin from the encoder: mean of d theta / d t between consecutive samples [rad/s]
        mid = 0.5 * (ph[1:] + ph[:-1])
        rate = np.diff(ph) / np.maximum(np.diff(tt), 1e-12)
        bm = np.clip(np.searchsorted(edges, mid, side="right") - 1, 0, grid.nb - 1)
        cm = np.bincount(bm, minlength=grid.nb).astype(float)
        sp = np.bincount(bm, weights=rate, minlength=grid.nb) / np.maximum(cm, 1)
        speeds.append(np.where(cm > 0, sp, np.nan))
        if keep_samples:
            samples.append((ph.copy(), a.copy()))
    why["flagged"] = sum(left_out.values())
    if not ys:
        raise ValueError(_no_cycle_message(why, n_legs, left_out))
    ks = np.array(ks)
    slips = np.array(slips)
    prev = np.array([slip_of_k[kk - 1] for kk in ks])
    prev = np.where(np.isfinite(prev), prev, slips)
    # mean leg speed over whole cycles (a drive ripple within the cycle averages out), per speed level
    t0a = np.array(t0s)
    if len(ks) >= 2 and ks[-1] > ks[0]:
        omega = 2 * half * (ks[-1] - ks[0]) / (t0a[-1] - t0a[0])
    else:
        omega = (theta[-1] - theta[0]) / (t[-1] - t[0])
    level_speed = _level_speeds(t, theta, starts, ends, k, half)
    if len(set(level_speed.values())) <= 1:
        omegas = np.full(len(ks), omega)  # one speed level: the whole log's mean speed
        prev_omegas = omegas.copy()
    else:
        omegas = np.array([level_speed.get(int(kk), omega) for kk in ks])
        prev_omegas = np.array([level_speed.get(int(kk) - 1, om) for kk, om in zip(ks, omegas)])
    return CycleSet(
        grid=grid,
        y=np.array(ys),
        count=np.array(counts),
        slip=slips,
        prev_slip=prev,
        omega=omegas,
        log=np.full(len(ks), log_index),
        k=ks,
        t0=np.array(t0s),
        speed=np.array(speeds),
        noise=np.array([noise]),
        samples=samples,
        dropped=sum(why.values()),
        prev_omega=prev_omegas,
        repaired=repaired,
        left_out=left_out,
        touchdowns=_touchdowns(ks, k, phase, half),
    )



def segmenter_flags(t, az, theta, n_legs: int):
    """Which samples lie in a leg cycle that replay's segmenter flags: ``(code, names, restarts)``, ``code``
    an ``(n,)`` int array (0: an ``"ok"`` cycle's, else ``names[code]``: the flagged cycle's quality, e.g.
    ``"gap"``, ``"reverse"``, ``"time"``, ``"nan"``; not ``"partial"``: a cycle not observed from its start is
    the diagnosis's own ``"incomplete"``), ``restarts``: the indices of the samples that revealed a
    ``"reverse"`` (the leg angle going back: a reversing rover, or two logs appended in one file), where
    :func:`cut_cycles` cuts the log into runs numbered on their own. The segmenter
    (:class:`slipest.segmentation.CycleSegmenter`) runs with the live estimator's options (whole cycle,
    :mod:`slipest.online`), over the samples in log order; a flagged cycle's samples run from the sample that
    opened it (the one that closed the cycle before) to the one that closed or ended it."""
    from slipest.segmentation import QUALITIES, CycleSegmenter

    half = math.pi / n_legs
    seg = CycleSegmenter(n_legs, window=(-half, half), complete_from=0.0, max_dtheta=half / 10.0)
    t = np.asarray(t, dtype=float)
    az = np.asarray(az, dtype=float)
    theta = np.asarray(theta, dtype=float)
    code = np.zeros(t.size, dtype=np.int64)
    names = np.array(QUALITIES)
    opened = 0
    restarts = []
    for i in range(t.size):
        for cyc in seg.push(t[i], az[i], theta[i]):
            if cyc.quality == "reverse":
                restarts.append(i)
            if cyc.quality not in ("ok", "partial"):
                code[opened:i] = QUALITIES.index(cyc.quality)
            opened = i
    for cyc in seg.finish():
        if cyc.quality not in ("ok", "partial"):
            code[opened:] = QUALITIES.index(cyc.quality)
    return code, names, restarts


def _cut_runs(t, az, theta, slip, n_legs, grid, log_index, keep_samples, flags) -> CycleSet:
    """:func:`cut_cycles` of a log whose leg angle goes back (``flags[2]``: where): each run between the
    reversals cut on its own (its cycles numbered from its own start), the cycles of all runs in one set of
    the log (``log_index``, one noise level: the whole log's); ValueError when no run has a usable cycle."""
    code, names, restarts = flags
    bounds = [0, *restarts, t.size]
    sets, errors = [], []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < 10:
            continue
        try:
            sets.append(cut_cycles(t[a:b], az[a:b], theta[a:b], slip[a:b], n_legs, grid=grid, log_index=log_index,
                                   keep_samples=keep_samples, flags=(code[a:b], names)))
        except ValueError as exc:
            errors.append(str(exc))
    if not sets:
        raise ValueError(errors[0] if errors else "no complete leg cycle in the log")
    out = concat(sets)
    out.log = np.full(len(out), log_index)
    out.noise = np.array([sample_noise(az[np.isfinite(t) & np.isfinite(theta)])])
    return out


def _touchdowns(ks, k, phase, half) -> np.ndarray:
    """Cycle boundaries from the log's start up to each kept cycle's start (see the module docstring)."""
    step = float(np.median(np.diff(phase[k == k[0]]))) if np.count_nonzero(k == k[0]) > 1 else 0.0
    on_boundary = abs(phase[0] + half) <= 1.5 * abs(step)
    return (np.asarray(ks) - k[0] + (1 if on_boundary else 0)).astype(float)


def speed_levels(speeds, tol: float = SPEED_TOLERANCE) -> np.ndarray:
    """Level label ``(n,)`` of each speed (> 0): sorted speeds split where they jump by more than ``tol``
    (relative), and a level wider than ``2 tol`` split evenly in log speed (a ramp)."""
    speeds = np.asarray(speeds, dtype=float)
    labels = np.zeros(len(speeds), dtype=np.int64)
    if len(speeds) == 0:
        return labels
    order = np.argsort(speeds)
    ls = np.log(speeds[order])
    cut = np.flatnonzero(np.diff(ls) > tol) + 1
    next_label = 0
    for seg in np.split(np.arange(len(ls)), cut):
        width = ls[seg[-1]] - ls[seg[0]]
        n_sub = max(1, int(math.ceil(width / (2 * tol) - 1e-12)))
        sub = np.minimum(((ls[seg] - ls[seg[0]]) / (width / n_sub) if width > 0 else 0 * seg).astype(np.int64),
                         n_sub - 1)
        labels[order[seg]] = next_label + sub
        next_label += n_sub
    return labels


def _level_speeds(t, theta, starts, ends, k, half) -> dict:
    """Cycle number -> its speed level's speed [rad/s] (see the module docstring), for every cut segment
    with at least 3 samples and a positive speed."""
    rough, ks = [], []
    for s0, s1 in zip(starts, ends):
        if s1 - s0 < 3:
            continue
        tt, th = t[s0:s1], theta[s0:s1]
        slope = np.polyfit(tt - tt[0], th, 1)[0]
        if slope > 0 and np.isfinite(slope):
            rough.append(slope)
            ks.append(int(k[s0]))
    if not ks:
        return {}
    labels = speed_levels(np.array(rough))
    start_of = {int(k[s0]): t[s0] for s0 in starts[1:]}  # the log's first segment may start mid-cycle
    out = {}
    for lab in np.unique(labels):
        members = [kk for kk, lb in zip(ks, labels) if lb == lab]
        durations = [start_of[kk + 1] - start_of[kk] for kk in members if kk + 1 in start_of and kk in start_of]
        durations = [d for d in durations if d > 0]
        speed = 2 * half / float(np.median(durations)) if durations else float(np.mean(
            [r for r, lb in zip(rough, labels) if lb == lab]))
        out.update({kk: speed for kk in members})
    return out


def _no_cycle_message(why: dict, n_legs: int, left_out: dict | None = None) -> str:
    """Why a log gave no usable cycle, from the counts of dropped cycles by reason (``left_out``: the flagged
    ones by flag)."""
    cut = sum(why.values())
    counts = ", ".join(f"{n} {reason}" + (f" ({', '.join(f'{f} {m}' for f, m in left_out.items())})"
                                          if reason == "flagged" and left_out else "")
                       for reason, n in why.items() if n)
    if why["no reference slip"] and why["no reference slip"] + why["first of the log"] == cut:
        return (f"the reference slip is missing: no complete leg cycle has a value in the 'slip' column at its "
                f"midstance ({counts} of {cut} cycles). {NEEDS_SLIP}")
    return (f"no complete leg cycle in the log ({counts} of {cut} cycles; check nL={n_legs} and that theta "
            "is 0 at midstances)")


def concat(sets) -> CycleSet:
    """Cycles of several logs in one set (log indices renumbered in order)."""
    sets = list(sets)
    if not sets:
        raise ValueError("no logs")
    grid = sets[0].grid
    if any(s.grid != grid for s in sets):
        raise ValueError("the logs have different leg counts or grids")
    logs, noise, off = [], [], 0
    for s in sets:
        logs.append(s.log - s.log.min() + off if len(s) else s.log)
        noise.extend(s.noise.tolist())
        off += len(s.noise)
    return CycleSet(
        grid=grid,
        y=np.concatenate([s.y for s in sets]),
        count=np.concatenate([s.count for s in sets]),
        slip=np.concatenate([s.slip for s in sets]),
        prev_slip=np.concatenate([s.prev_slip for s in sets]),
        omega=np.concatenate([s.omega for s in sets]),
        log=np.concatenate(logs),
        k=np.concatenate([s.k for s in sets]),
        t0=np.concatenate([s.t0 for s in sets]),
        speed=np.concatenate([s.speed for s in sets]),
        noise=np.array(noise),
        samples=sum((s.samples for s in sets), []),
        dropped=sum(s.dropped for s in sets),
        prev_omega=np.concatenate([s.prev_omega for s in sets]),
        repaired=sum(s.repaired for s in sets),
        left_out={f: sum(s.left_out.get(f, 0) for s in sets) for f in sorted({f for s in sets for f in s.left_out})},
        touchdowns=np.concatenate([s.touchdowns for s in sets]),
    )
