"""A live view of a live run in Foxglove: estimates, raw ``az`` and leg angle over a WebSocket.

:class:`LiveView` starts a Foxglove WebSocket server (the ``foxglove-sdk``
package: ``pip install 'slipest[view]'``) and publishes, per wheel ``K``:

==================================  =======================  ==================================================
topic                               schema (encoding)        what
==================================  =======================  ==================================================
``/slipest/wheelK/estimate``        ``slipest.Estimate``     one message per leg cycle: every field of
                                    (JSON)                   :class:`slipest.online.Estimate`, plus ``wheel``,
                                                             the 95 % band ``slip_lo``/``slip_hi`` (slip -/+
                                                             1.96 slip_std) and ``latency_ms``
``/slipest/wheelK/imu``             ``slipest.ImuSample``    the estimator's input decimated to ``rate`` per
                                    (JSON)                   second of device time: ``t`` [s], ``az``
                                                             [m/s^2] and ``theta`` [rad, wrapped to
                                                             [-pi, pi)] of the first sample of each interval,
                                                             ``az_min``/``az_max`` over it, ``n`` samples,
                                                             ``lost`` of them lost (az NaN)
``/slipest/wheelK/joint_states``    ``foxglove.JointStates``  the same leg angle as joint ``wheelK_leg``
                                    (protobuf)               (``position`` [rad]), for a 3D panel
``/slipest/log``                    ``foxglove.Log``         the run's notices (start, stop, link trouble)
                                    (protobuf)
==================================  =======================  ==================================================

NaN (a cycle not estimated, a lost sample) is ``null`` in JSON.  Each
message's log time is the host's wall-clock time [ns] of its data's
arrival (an estimate: its closing sample's), so the topics line up in
Foxglove's timeline; the device time is in the message.  ``docs/live-view.md``
has the details and how to open the view.

The live run never waits for the view: :meth:`LiveView.attach` adds
listeners to a :class:`~slipest.live.LiveEstimation` that only append
references to a bounded queue (well under a microsecond, no thread woken);
a thread of the view's wakes every ``interval`` s (0.02), takes what came,
decimates, encodes and hands the messages to the server, which keeps at
most ``backlog`` messages per client (a viewer that stops reading loses
its oldest ones, or is disconnected: it never holds anything up).  A full
queue (the view's thread behind) drops what comes, counted
(``queue_dropped``).  Use::

    from slipest.live.view import LiveView
    view = LiveView("127.0.0.1", 8765).attach(live)   # before run_live(source, live, ...)
    ...
    view.close()
"""

from __future__ import annotations

import collections
import dataclasses
import json
import math
import threading
import time

import numpy as np

from slipest.extras import import_extra

__all__ = ["DEFAULT_PORT", "DEFAULT_RATE", "IMU_SCHEMA", "LiveView", "decimate", "estimate_schema"]

#: Foxglove's default WebSocket port.
DEFAULT_PORT = 8765
#: Decimated samples per second of device time.
DEFAULT_RATE = 100.0
#: [s] messages wait this long after their channel was created, for the viewers to subscribe.
NEW_CHANNEL_HOLD = 0.2

_JSON_TYPES = {"int": {"type": "integer"}, "float": {"type": ["number", "null"]}, "str": {"type": "string"},
               "bool": {"type": "boolean"}}


def estimate_schema() -> dict:
    """The JSON schema of ``/slipest/wheelK/estimate``: the fields of :class:`slipest.online.Estimate`
    (whatever they are) and ``wheel``, ``slip_lo``, ``slip_hi``, ``latency_ms``."""
    from slipest.online import Estimate

    props = {"wheel": {"type": "integer"}}
    for f in dataclasses.fields(Estimate):
        props[f.name] = dict(_JSON_TYPES.get(str(f.type), {}))
    props["slip_lo"] = {"type": ["number", "null"], "description": "slip - 1.96 slip_std [-]"}
    props["slip_hi"] = {"type": ["number", "null"], "description": "slip + 1.96 slip_std [-]"}
    props["latency_ms"] = {"type": ["number", "null"],
                           "description": "closing sample's arrival to the estimate being ready [ms]"}
    return {"title": "slipest.Estimate", "type": "object", "properties": props}


#: JSON schema of ``/slipest/wheelK/imu``.
IMU_SCHEMA = {"title": "slipest.ImuSample", "type": "object", "properties": {
    "wheel": {"type": "integer"},
    "t": {"type": "number", "description": "device time of the interval's first sample [s]"},
    "az": {"type": ["number", "null"], "description": "its vertical acceleration, gravity included [m/s^2]"},
    "az_min": {"type": ["number", "null"], "description": "lowest az over the interval [m/s^2]"},
    "az_max": {"type": ["number", "null"], "description": "highest az over the interval [m/s^2]"},
    "theta": {"type": "number", "description": "leg angle of the first sample, wrapped to [-pi, pi) [rad]"},
    "n": {"type": "integer", "description": "samples in the interval"},
    "lost": {"type": "integer", "description": "of them lost (az NaN)"},
}}


def _num(v):
    v = float(v)
    return v if math.isfinite(v) else None


def decimate(t, az, theta, intake, rate: float, carry=None):
    """Samples cut into intervals of ``1/rate`` s of device time ``t`` (interval ``floor(t * rate)``; a
    new one also where ``t`` goes back).  Returns ``(rows, carry)``: a dict per finished interval
    (``t``, ``az``, ``theta`` of its first sample (theta wrapped to [-pi, pi)), ``az_min``, ``az_max``
    (NaN-ignoring; None when every az is NaN), ``n``, ``lost``, ``intake``: its latest finite arrival time
    or NaN) and the unfinished last interval's samples, to pass back as ``carry`` with the next ones."""
    cols = [np.asarray(c, np.float64) for c in (t, az, theta, intake)]
    if carry is not None:
        cols = [np.concatenate((a, b)) for a, b in zip(carry, cols)]
    t, az, theta, intake = cols
    if not t.size:
        return [], None
    bucket = np.floor(t * rate)
    starts = np.flatnonzero(np.r_[True, bucket[1:] != bucket[:-1]])
    done = starts[-1]  # the last interval may go on in the next samples
    rows = []
    if done:
        s = starts[:-1]
        lo = np.fmin.reduceat(az[:done], s)
        hi = np.fmax.reduceat(az[:done], s)
        lost = np.add.reduceat(np.isnan(az[:done]).astype(np.int64), s)
        arrived = np.fmax.reduceat(intake[:done], s)
        n = np.diff(np.r_[s, done])
        wrapped = np.mod(theta[s] + math.pi, 2 * math.pi) - math.pi
        for i, k in enumerate(s):
            rows.append({"t": float(t[k]), "az": _num(az[k]), "az_min": _num(lo[i]), "az_max": _num(hi[i]),
                         "theta": float(wrapped[i]), "n": int(n[i]), "lost": int(lost[i]),
                         "intake": float(arrived[i])})
    return rows, [c[done:] for c in cols]


class _Wheel:
    """One wheel's channels and decimation state (the view's thread only)."""

    def __init__(self, fox, ctx, wheel: int):
        from foxglove.channels import JointStatesChannel

        self.estimate = fox.Channel(f"/slipest/wheel{wheel}/estimate", schema=estimate_schema(), context=ctx)
        self.imu = fox.Channel(f"/slipest/wheel{wheel}/imu", schema=IMU_SCHEMA, context=ctx)
        self.joints = JointStatesChannel(f"/slipest/wheel{wheel}/joint_states", context=ctx)
        self.joint = f"wheel{wheel}_leg"
        self.carry = None
        self.last_log_time = 0


class LiveView:
    """A Foxglove WebSocket server publishing a live run (see the module docstring).

    ``host``, ``port``: where it listens (``127.0.0.1``: this machine only;
    ``0.0.0.0``: every interface; port 0: any free one, see :attr:`port`).
    ``rate``: decimated samples per second of device time.  ``backlog``:
    messages the server keeps per client (the oldest of a slow client's are
    dropped).  ``queue_size``: items waiting for the view's thread;
    ``interval`` [s]: how often it publishes what came.  Raises
    :class:`~slipest.extras.MissingExtra` (names ``pip install
    'slipest[view]'``) without foxglove-sdk, ``OSError`` when it cannot
    listen there.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, rate: float = DEFAULT_RATE,
                 name: str = "slipest", backlog: int = 1024, queue_size: int = 10000, interval: float = 0.02):
        if not rate > 0:
            raise ValueError(f"the view's rate must be > 0 samples/s, got {rate!r}")
        fox = import_extra("foxglove", "view", "the live view")
        from foxglove.channels import LogChannel

        self._fox = fox
        self.rate = float(rate)
        self.host = host
        self._ctx = fox.Context()
        try:
            self.server = fox.start_server(name=name, host=host, port=port, context=self._ctx,
                                           message_backlog_size=backlog)
        except Exception as exc:  # foxglove raises its own error types for a busy port or a bad address
            raise OSError(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.port = int(self.server.port)
        self._log = LogChannel("/slipest/log", context=self._ctx)
        self._wall_offset_ns = time.time_ns() - time.monotonic_ns()  # host monotonic [s] -> wall clock [ns]
        self.interval = float(interval)
        self._queue: collections.deque = collections.deque()
        self._queue_size = int(queue_size)
        self._stop = threading.Event()
        self._wheels: dict[int, _Wheel] = {}
        self._topics: dict = {}  # the caller's topics (publish)
        self._held: list = []  # items waiting for their new channels' subscribers
        self._hold_until = 0.0
        self.c = {"estimates": 0, "imu": 0, "joint_states": 0, "log": 0, "other": 0, "queue_dropped": 0, "errors": 0}
        self.last_error: str | None = None
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="slipest live view", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The address a viewer opens (``ws://host:port``)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    # -- the live run's side: quick, never blocks ---------------------------------------------
    def attach(self, live) -> "LiveView":
        """Publish ``live``'s samples and estimates (a :class:`~slipest.live.LiveEstimation`); returns self."""
        live.add_listener(on_samples=self.on_samples, on_estimate=self.on_estimate)
        return self

    def _put(self, item) -> None:
        if len(self._queue) >= self._queue_size:  # (only the view's thread takes: the length cannot grow meanwhile)
            self.c["queue_dropped"] += 1
        else:
            self._queue.append(item)

    def on_samples(self, wheel: int, samples) -> None:
        """A wheel's samples (a :class:`~slipest.io.device_stream.WheelSamples`, not changed afterwards)."""
        self._put(("samples", wheel, samples))

    def on_estimate(self, wheel: int, estimate, info: dict) -> None:
        """A wheel's estimate of a leg cycle, with the ``info`` of :class:`~slipest.live.LiveEstimation`."""
        self._put(("estimate", wheel, estimate, info))

    def notice(self, text: str, level: str = "warning") -> None:
        """A line for ``/slipest/log``: ``level`` debug, info, warning, error or fatal."""
        self._put(("log", level, text, time.time_ns()))

    def publish(self, topic: str, message: dict, schema: dict | None = None) -> None:
        """A JSON message of the caller's on ``topic`` (NaN as null; log time: now), e.g. a testbed's
        truth beside the estimates; ``schema``: its JSON schema (an object with a ``title``), taken
        when the topic's first message comes."""
        self._put(("json", topic, message, schema, time.time_ns()))

    # -- the view's thread ---------------------------------------------------------------------
    def _log_time(self, intake: float, fallback: int) -> int:
        return int(intake * 1e9) + self._wall_offset_ns if intake == intake else fallback

    def _publish_samples(self, wheel: int, pushes: list) -> None:
        from foxglove.messages import JointState, JointStates, Timestamp

        w = self._wheels[wheel]
        cols = [np.concatenate([getattr(s, name) for s in pushes]) for name in ("t", "az", "theta", "intake")]
        rows, w.carry = decimate(*cols, self.rate, w.carry)
        for row in rows:
            log_time = w.last_log_time = self._log_time(row.pop("intake"), w.last_log_time or time.time_ns())
            row["wheel"] = wheel
            w.imu.log(json.dumps(row, allow_nan=False).encode(), log_time=log_time)
            stamp = Timestamp(sec=log_time // 1_000_000_000, nsec=log_time % 1_000_000_000)
            w.joints.log(JointStates(timestamp=stamp, joints=[JointState(name=w.joint, position=row["theta"])]),
                         log_time=log_time)
        self.c["imu"] += len(rows)
        self.c["joint_states"] += len(rows)

    def _publish_estimate(self, wheel: int, est, info: dict) -> None:
        from slipest.online import ESTIMATE_FIELDS

        msg = {"wheel": wheel}
        for name in ESTIMATE_FIELDS:
            v = getattr(est, name, None)
            msg[name] = _num(v) if isinstance(v, (float, np.floating)) else (v.item() if hasattr(v, "item") else v)
        slip, std = float(getattr(est, "slip", math.nan)), float(getattr(est, "slip_std", math.nan))
        msg["slip_lo"], msg["slip_hi"] = _num(slip - 1.96 * std), _num(slip + 1.96 * std)
        msg["latency_ms"] = _num(1e3 * float(info.get("latency", math.nan)))
        log_time = self._log_time(float(info.get("intake", math.nan)),
                                  self._log_time(float(info.get("ready", math.nan)), time.time_ns()))
        self._wheels[wheel].estimate.log(json.dumps(msg, allow_nan=False).encode(), log_time=log_time)
        self.c["estimates"] += 1

    def _publish_log(self, level: str, text: str, stamp_ns: int) -> None:
        from foxglove.messages import Log, LogLevel, Timestamp

        lvl = {"debug": LogLevel.Debug, "info": LogLevel.Info, "warning": LogLevel.Warning,
               "error": LogLevel.Error, "fatal": LogLevel.Fatal}.get(level.lower(), LogLevel.Info)
        stamp = Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)
        self._log.log(Log(timestamp=stamp, level=lvl, message=text, name="slipest"), log_time=stamp_ns)
        self.c["log"] += 1

    def _publish_json(self, topic: str, message: dict, schema: dict | None, stamp_ns: int) -> None:
        channel = self._topics[topic]
        clean = {k: (_num(v) if isinstance(v, (float, np.floating)) else v) for k, v in message.items()}
        channel.log(json.dumps(clean, allow_nan=False).encode(), log_time=stamp_ns)
        self.c["other"] += 1

    def _publish(self) -> None:
        """Everything queued: each wheel's samples in one go, then the estimates and notices.  Once
        a channel is created, what came waits :data:`NEW_CHANNEL_HOLD` s, so that the viewers connected
        can subscribe to it first (a message with no subscriber goes nowhere; foxglove-sdk takes a
        subscription a moment after the client sent it)."""
        items = self._held
        self._held = []
        while self._queue:
            items.append(self._queue.popleft())
        new = False
        for item in items:
            if item[0] in ("samples", "estimate") and item[1] not in self._wheels:
                self._wheels[item[1]] = _Wheel(self._fox, self._ctx, item[1])
                new = True
            elif item[0] == "json" and item[1] not in self._topics:
                self._topics[item[1]] = self._fox.Channel(item[1], schema=item[3], context=self._ctx)
                new = True
        if new:
            self._hold_until = time.monotonic() + NEW_CHANNEL_HOLD
        if time.monotonic() < self._hold_until and not self._stop.is_set():
            self._held = items
            return
        samples: dict[int, list] = {}
        rest = []
        for item in items:
            if item[0] == "samples":
                samples.setdefault(item[1], []).append(item[2])
            else:
                rest.append(item)
        jobs = [(self._publish_samples, (wheel, pushes)) for wheel, pushes in samples.items()]
        kinds = {"estimate": self._publish_estimate, "log": self._publish_log, "json": self._publish_json}
        jobs += [(kinds[item[0]], item[1:]) for item in rest]
        for publish, args in jobs:
            try:
                publish(*args)
            except Exception as exc:  # counted and kept (counters(), last_error): the view goes on
                self.c["errors"] += 1
                self.last_error = f"{type(exc).__name__}: {exc}"

    def _run(self) -> None:
        while True:
            stopping = self._stop.wait(self.interval)
            try:
                self._publish()
            except Exception as exc:  # (a channel foxglove would not create): counted and kept, the view goes on
                self.c["errors"] += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
            if stopping:
                return

    # -- the end -------------------------------------------------------------------------------
    def counters(self) -> dict:
        """Messages published per topic kind (``estimates``, ``imu``, ``joint_states``, ``log``, ``other``:
        :meth:`publish`),
        ``queue_dropped`` and ``errors`` (items the view failed to publish; the last: :attr:`last_error`)."""
        return dict(self.c)

    def close(self, timeout: float = 5.0, linger: float = 0.25) -> None:
        """Publish what is queued (up to ``timeout`` s), give the server ``linger`` s to send it to the
        viewers (foxglove-sdk has no flush: stopping it drops what it still holds for a client), then
        stop the server (idempotent).  What the view's thread did not publish within ``timeout`` is
        counted in ``errors`` (:attr:`last_error` says how many items)."""
        if self._stopped:
            return
        self._stopped = True
        self._stop.set()
        self._thread.join(timeout)
        if self._thread.is_alive():
            self.c["errors"] += 1
            self.last_error = f"the view's thread was still publishing after {timeout:g} s; stopped the server"
        elif linger > 0:
            time.sleep(linger)
        self.server.stop()

    def __enter__(self) -> "LiveView":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
