"""Live estimation of every wheel: frames in, one estimate per leg cycle out.

:class:`LiveEstimation` takes the batches a :class:`~slipest.io.source.Source`
delivers (any wheel, in arrival order), turns each wheel's frames into
samples with that source's wire facts (a
:class:`~slipest.io.device_stream.WheelStream` per wheel: lost frames become
NaN samples so their cycles are flagged, stuck sensors are caught, wrapped
counters and times are unwrapped, device restarts and frames missed by a
late start are told apart from losses), runs one estimator per wheel,
records the samples and the raw CAN frames when asked
(:mod:`slipest.live.recording`), and reports every estimate to a callback
(print it, publish it on the bus...) and to the listeners added with
:meth:`LiveEstimation.add_listener` (a live view: :mod:`slipest.live.view`).  What
people should hear of (a restart, a late start) waits in :meth:`notices`.  It keeps
counters and two latencies: from a cycle's closing sample arriving to its
estimate being ready, and (for firmware-sim on this host, ``sim_speed``)
from each sample's instant on the device to its arrival.

A cycle is counted ``estimates`` when its quality is ``"ok"`` and its slip
finite, else ``cycles_flagged``; an estimator error on one push (a
``ValueError`` or ``FloatingPointError``) is counted
(``estimator_errors``, ``last_error``) and the stream goes on.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from slipest.io.device_stream import WheelSamples, WheelStream
from slipest.io.notice_limit import NoticeLimiter
from slipest.stuck import STUCK_TIME
from slipest.latency import latency_summary
from slipest.live.recording import Recording

__all__ = ["LiveEstimation", "WheelState"]

#: A push of up to this many samples goes sample by sample (cheaper than the array path for a few).
_PUSH_ONE_BY_ONE = 8


@dataclass
class WheelState:
    """One wheel's stream, estimator and tallies."""

    stream: WheelStream
    estimator: object
    estimates: int = 0
    cycles_seen: int = 0
    qualities: dict = field(default_factory=dict)
    hints_said: set = field(default_factory=set)


class LiveEstimation:
    """Frames of any wheel in, estimates out (see the module docstring).

    ``source``: the :class:`~slipest.io.source.Source` the frames come from
    (its ``seq_modulus``, ``time_modulus``, ``time_unit``, ``reorder_window`` and
    ``describe()`` are used; it need not be started yet).  The estimator
    options (``n_legs``, ``method``, ``soil``, ``use_reference``, ``model``)
    are those of :class:`~slipest.online.SlipEstimator`, or
    ``estimator_factory(wheel)`` makes each wheel's estimator.  ``wheels``:
    estimate only these (None: every wheel seen).  ``stuck_time`` [s] and
    ``stuck_samples``: the stuck-sensor rule of
    :class:`~slipest.io.device_stream.WheelStream` (a run of identical
    ``az`` lasting ``stuck_time``; or of ``stuck_samples`` samples when
    given; 0: off).  ``sim_speed``: the device is firmware-sim on this host at this speed (its timestamps are
    this host's monotonic clock times the speed): device-to-intake latency
    is measured and wrapped times are unwrapped knowing the speed-up.
    ``record``: a path or a list of paths to record to, each as its name
    says: the samples (a ``.csv``...) or the source's raw CAN frames (a
    python-can log: ``.asc``, ``.blf``...); ``record_frames``: paths
    recorded as CAN frames whatever their suffix (python-can's ``.csv``).
    See :class:`~slipest.live.recording.Recording` (``ValueError`` for a
    CAN log of a source without CAN frames, ``FileExistsError`` unless
    ``overwrite``).

    ``on_estimate(wheel, estimate, info)`` is called for every closed cycle,
    in order; ``info`` holds ``intake`` (arrival of the cycle's closing
    sample, host monotonic [s]), ``latency`` (from that arrival to the
    estimate being ready [s]; NaN when unknown) and ``ready`` [s].
    """

    def __init__(self, source, *, n_legs: int = 4, method: str | None = None, soil: dict | None = None,
                 use_reference: bool = False, model=None, wheels: list[int] | None = None,
                 stuck_samples: int | None = None, stuck_time: float = STUCK_TIME, sim_speed: float | None = None,
                 record=None, record_frames=(), overwrite: bool = False, on_estimate: Callable | None = None,
                 estimator_factory: Callable | None = None):
        self.seq_modulus = int(source.seq_modulus)
        self.time_modulus = source.time_modulus
        self.time_unit = float(source.time_unit)
        self.reorder_window = int(source.reorder_window)
        self.n_legs = n_legs
        self.method = method
        self.soil = soil or None
        self.use_reference = use_reference
        self.model = model  # the inverse model (FeatureSurrogate) of the default method; None: the shipped one
        self.only_wheels = set(wheels) if wheels else None
        self.stuck_samples = stuck_samples
        self.stuck_time = stuck_time
        self.sim_speed = sim_speed
        self.on_estimate = on_estimate or (lambda wheel, est, info: None)
        self._factory = estimator_factory or self._default_factory
        self._closed = False
        self.recorder = (Recording(record or (), source=source, n_legs=n_legs, frames=record_frames,
                                   overwrite=overwrite) if record or record_frames else None)
        self._sample_listeners: list[Callable] = []
        self.wheels: dict[int, WheelState] = {}
        self.c = {"frames_ignored_wheel": 0, "estimates": 0, "cycles_flagged": 0, "estimator_errors": 0}
        self._intake_latency: list[np.ndarray] = []
        self._estimate_latency: list[float] = []
        self._spare = None
        self.last_error: str | None = None
        self._notices: list[str] = []
        self._limiter = NoticeLimiter()

    def add_listener(self, *, on_samples: Callable | None = None, on_estimate: Callable | None = None) -> None:
        """Also call ``on_samples(wheel, samples)`` with each wheel's samples (a
        :class:`~slipest.io.device_stream.WheelSamples`, as the recording gets them, before the
        estimator does) and ``on_estimate(wheel, estimate, info)`` after the estimate callback (it
        becomes part of :attr:`on_estimate`).  Both run in the loop's thread: they must be quick (hand
        the work to a thread of their own, as :class:`~slipest.live.view.LiveView` does) and must not
        keep or change the arrays."""
        if on_samples is not None:
            self._sample_listeners.append(on_samples)
        if on_estimate is not None:
            first = self.on_estimate

            def both(wheel, est, info):
                first(wheel, est, info)
                on_estimate(wheel, est, info)

            self.on_estimate = both

    def warmup(self) -> float:
        """Get the estimator's one-time costs (loading the model, compiled
        code) out of the way before data comes: a throwaway estimator gets
        three synthetic leg cycles, pushed one sample at a time (and a chunk
        more), and a fresh one is kept for the first wheel.  Raises the
        estimator's ``ValueError``/``TypeError`` on bad options.  Returns the
        seconds it took."""
        t0 = time.monotonic()
        est = self._factory(-1)
        n_legs = self.n_legs
        omega = 0.63
        period = 2 * math.pi / (n_legs * omega)
        t = np.arange(0.0, 3 * period, 1e-3)
        theta = -math.pi / n_legs + omega * t
        phase = np.mod(theta + math.pi / n_legs, 2 * math.pi / n_legs) - math.pi / n_legs
        rng = np.random.default_rng(0)
        az = 9.81 + np.where(phase > 0.2, 3.0 * np.sin(2 * math.pi * 12 * t), 0.0) + rng.normal(0, 0.1, t.size)
        try:  # one sample at a time, as a live stream comes: push's own compiled paths (getting ready for the
            # next close among them) are then compiled here, not in the middle of the first wheel's stream
            for a, b, c in zip(t.tolist(), az.tolist(), theta.tolist()):
                est.push(a, b, c)
            more = np.arange(1, 17) * 1e-3  # and 16 more samples of the same stream as a chunk (push_many's paths)
            est.push_many(t[-1] + more, az[:16], theta[-1] + omega * more, warm=True)
        except ValueError:  # the synthetic cycles are only for warming up; what they give does not matter
            pass
        self._spare = self._factory(0)
        return time.monotonic() - t0

    # -- set-up -----------------------------------------------------------------
    def _default_factory(self, wheel: int):
        from slipest.online import SlipEstimator

        kwargs = {"n_legs": self.n_legs, "use_reference": self.use_reference, "soil": self.soil, "model": self.model,
                  "stuck_time": self.stuck_time, "stuck_samples": self.stuck_samples}
        if self.method is not None:
            kwargs["method"] = self.method
        return SlipEstimator(**kwargs)

    def _wheel(self, wheel: int) -> WheelState | None:
        st = self.wheels.get(wheel)
        if st is not None:
            return st
        if self.only_wheels is not None and wheel not in self.only_wheels:
            return None
        stream = WheelStream(wheel, seq_modulus=self.seq_modulus, time_modulus=self.time_modulus,
                             time_scale=self.sim_speed or 1.0, stuck_samples=self.stuck_samples,
                             stuck_time=self.stuck_time, reorder_window=self.reorder_window)
        estimator, self._spare = (self._spare, None) if self._spare is not None else (self._factory(wheel), None)
        if self.recorder is not None:
            self.recorder.open_wheel(wheel)
        st = self.wheels[wheel] = WheelState(stream, estimator)
        return st

    # -- input ------------------------------------------------------------------
    def feed(self, batches) -> None:
        """Source batches (:class:`~slipest.io.source.SourceBatch`) in arrival order.  Each wheel's
        IMU frames are merged into one push per run between reference frames (fewer, larger pushes
        when the consumer is behind); a reference holds from its place among the IMU frames it
        arrived with."""
        per_wheel: dict[int, tuple[list, list, list, list, list]] = {}
        unit = self.time_unit

        def push():
            for w, (seq, t, az, th, intake) in per_wheel.items():
                self.samples(w, seq, t, az, th, intake)
            per_wheel.clear()

        def add(frames, intake):
            for wheel, seq, t, az, th in frames:
                cols = per_wheel.get(wheel)
                if cols is None:
                    cols = per_wheel[wheel] = ([], [], [], [], [])
                cols[0].append(seq)
                cols[1].append(t * unit)
                cols[2].append(az)
                cols[3].append(th)
                cols[4].append(intake)

        for b in batches:
            done = 0
            for wheel, _seq, _t, slip, at in b.refs:
                add(b.imu[done:at], b.intake)
                done = max(done, at)
                push()
                self.reference(wheel, slip)
            add(b.imu[done:] if done else b.imu, b.intake)
        push()

    def reference(self, wheel: int, slip: float) -> None:
        """A reference slip [-] for the wheel's samples that follow."""
        st = self._wheel(wheel)
        if st is None:
            self.c["frames_ignored_wheel"] += 1
            return
        st.stream.set_reference(slip)

    def samples(self, wheel: int, seq, t, az, theta, intake) -> None:
        """Frames of one wheel, in arrival order (sequences of equal length): counters, ``t`` [s]
        device time (wrapped when the source's time is), ``az`` [m/s^2], ``theta`` [rad],
        ``intake`` [s] arrival times."""
        st = self._wheel(wheel)
        if st is None:
            self.c["frames_ignored_wheel"] += len(t)
            return
        if self.sim_speed:
            self._measure_intake(np.asarray(t, np.float64), np.asarray(intake, np.float64))
        self._push(wheel, st, st.stream.add(seq, t, az, theta, intake))
        if st.stream.events:
            for text in st.stream.events:  # rate-limited per wheel and kind: a device restarting again and again
                said = self._limiter.admit(f"wheel {wheel}: {text}", f"{wheel}:{text.split(' (')[0]}")
                if said is not None:
                    self._notices.append(said)
            st.stream.events.clear()

    def notices(self) -> list[str]:
        """Events for people since the last call (a device restart, frames a late start missed), three of a
        kind at once then one per ten seconds (:mod:`slipest.io.notice_limit`); once closed, the ones left
        out summed up."""
        out, self._notices = self._notices, []
        if self._closed:
            out += self._limiter.left_out()
        return out

    def _measure_intake(self, t, intake) -> None:
        s = self.sim_speed
        lag = np.asarray(s * intake - t, np.float64).reshape(-1)
        if self.time_modulus:
            lag = np.mod(lag, self.time_modulus)
        self._intake_latency.append(lag / s)

    def _push(self, wheel: int, st: WheelState, s: WheelSamples) -> None:
        if not len(s):
            return
        if self.recorder is not None:
            self.recorder.add(wheel, s)
        for listener in self._sample_listeners:
            listener(wheel, s)
        try:
            est = st.estimator
            if len(s) <= _PUSH_ONE_BY_ONE:
                estimates = []
                use_ref = self.use_reference
                for i in range(len(s)):
                    estimates += est.push(float(s.t[i]), float(s.az[i]), float(s.theta[i]),
                                          float(s.slip[i]) if use_ref else None)
            else:
                estimates = est.push_many(s.t, s.az, s.theta, s.slip if self.use_reference else None, warm=True)
        except (ValueError, FloatingPointError) as exc:  # never let one bad cycle stop the stream
            self._estimator_error(wheel, exc)
            return
        self._report(wheel, st, estimates, s)

    def _estimator_error(self, wheel: int, exc: Exception) -> None:
        self.c["estimator_errors"] += 1
        self.last_error = f"wheel {wheel}: {type(exc).__name__}: {exc}"

    def _report(self, wheel: int, st: WheelState, estimates: list, s: WheelSamples | None) -> None:
        """Count and hand on a wheel's estimates; ``s``: the samples that closed them (their intake times
        give the latency), None at the end of the stream."""
        now = time.monotonic()
        for est in estimates:
            st.cycles_seen += 1
            q = str(getattr(est, "quality", "ok"))
            st.qualities[q] = st.qualities.get(q, 0) + 1
            slip = getattr(est, "slip", math.nan)
            if not getattr(est, "ok", q == "ok") or slip != slip:
                self.c["cycles_flagged"] += 1
            else:
                st.estimates += 1
                self.c["estimates"] += 1
            intake = math.nan
            if s is not None:
                t_end = float(getattr(est, "t_end", math.nan))
                k = int(np.searchsorted(s.t, t_end)) if t_end == t_end else -1
                intake = float(s.intake[k]) if 0 <= k < len(s) and s.t[k] == t_end else math.nan
            latency = now - intake if intake == intake else math.nan
            if latency == latency:
                self._estimate_latency.append(latency)
            self.on_estimate(wheel, est, {"intake": intake, "latency": latency, "ready": now})
        hints = getattr(st.estimator, "hints", None)
        if estimates and hints and len(hints) > len(st.hints_said):
            for kind, text in hints.items():
                if kind not in st.hints_said:
                    st.hints_said.add(kind)
                    self._notices.append(f"wheel {wheel}: {text}")

    def flush(self, force: bool = False) -> None:
        """Write the recording's buffered samples (every 0.1 s at most unless ``force``)."""
        if self.recorder is not None:
            self.recorder.flush(force)

    def close(self) -> None:
        """Hand on the samples the streams still hold, end every wheel's stream (its last cycle, which no
        sample will close, is estimated: see :meth:`slipest.online.SlipEstimator.finish`), then write, flush
        and close the recording. Idempotent: a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        try:
            for wheel, st in self.wheels.items():
                self._push(wheel, st, st.stream.flush())
                finish = getattr(st.estimator, "finish", None)
                if finish is None:
                    continue
                try:
                    estimates = finish()
                except (ValueError, FloatingPointError) as exc:
                    self._estimator_error(wheel, exc)
                    continue
                self._report(wheel, st, estimates, None)
        finally:
            if self.recorder is not None:
                self.recorder.close()

    # -- reporting ---------------------------------------------------------------
    def min_cycles(self) -> int:
        """Fewest leg cycles closed by any wheel seen (0 before the first)."""
        return min((st.cycles_seen for st in self.wheels.values()), default=0)

    def counters(self) -> dict:
        """Estimation counters, and per wheel (``wheelK``) the stream's, the estimator's and the recording's."""
        c = dict(self.c)
        for wheel, st in sorted(self.wheels.items()):
            wc = st.stream.counters()
            wc["estimates"] = st.estimates
            wc["cycles"] = st.cycles_seen
            wc["qualities"] = dict(st.qualities)
            seg = getattr(st.estimator, "counters", None)
            if seg is not None:
                wc["estimator"] = seg() if callable(seg) else dict(seg)
            if self.recorder is not None and self.recorder.samples is not None:
                wc["rows_recorded"] = self.recorder.rows(wheel)
            c[f"wheel{wheel}"] = wc
        if self.recorder is not None and self.recorder.frame_logs:
            c["frame_logs"] = self.recorder.counters()
        return c

    def latency(self) -> dict:
        """``intake_to_estimate`` and (with ``sim_speed``) ``device_to_intake``: n, median, p99, max [ms]."""
        out = {"intake_to_estimate": latency_summary([np.array(self._estimate_latency, np.float64)])}
        if self.sim_speed:
            out["device_to_intake"] = latency_summary(self._intake_latency)
        return out
