"""ROS 2 bags (rosbag2, sqlite3 or MCAP) as the estimator's samples.

Reads with ``rosbags`` (pure Python, an optional extra:
``pip install 'slipest[ros]'``; without it :class:`RosBag` raises
:class:`~slipest.extras.MissingExtra` naming the extra).  A bag is a rosbag2 directory (with
its ``metadata.yaml``), or one ``.mcap`` or ``.db3`` file.

What is read (:class:`BagTopics` names the topics and the joint):

* ``sensor_msgs/msg/Imu`` on the IMU topic: ``az = linear_acceleration.z``
  [m/s^2], as the estimator takes it (gravity included, +9.81 at rest: the
  IMU's frame must have z up), at ``t = header.stamp`` [s];
* ``sensor_msgs/msg/JointState`` on the joint-states topic: the wheel-leg
  joint's ``position`` [rad] (by name; the joint may sit anywhere in the
  message's lists), at its ``header.stamp``; the positions are sorted by
  time, unwrapped (a continuous joint may report them wrapped) and
  interpolated linearly onto each IMU time;
* optionally a reference slip, ``std_msgs/msg/Float64`` (or ``Float32``)
  ``data`` [-], held from its arrival until the next one (arrival: the bag's
  receive time, on both sides, as such a message has no stamp).

``bag_time=True`` takes the bag's receive times instead of the header stamps
(drivers that leave stamps at zero: a bag whose IMU stamps are all zero is
refused with that hint).  Nothing is estimated from invented data: IMU
samples before the first or after the last joint state are left out
(``outside_joint_states``), and samples that fall in a gap of the joint
states longer than ``max_joint_gap`` get ``theta = NaN``
(``in_joint_gap``), which makes the segmenter flag their leg cycle.
Counters: :meth:`RosBag.counters`.

Memory: the joint states (two floats each) plus one chunk of IMU samples.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from slipest.extras import import_extra
from slipest.io.log_csv import LogChunk, LogFormatError

__all__ = ["BAG_SUFFIXES", "BagTopics", "RosBag", "is_bag"]

#: Single-file rosbag2 storages (a directory with a ``metadata.yaml`` is a bag too).
BAG_SUFFIXES = (".mcap", ".db3")
IMU_TYPE = "sensor_msgs/msg/Imu"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
SLIP_TYPES = ("std_msgs/msg/Float64", "std_msgs/msg/Float32")


def is_bag(path) -> bool:
    """Whether ``path`` is a rosbag2 bag: a directory with ``metadata.yaml``, or a ``.mcap``/``.db3`` file."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in BAG_SUFFIXES


@dataclass(frozen=True)
class BagTopics:
    """Where the samples are in a bag.  ``joint``: the wheel-leg joint's name in the JointState
    messages (None: the only joint they carry).  ``slip``: a reference-slip topic (None: none).
    ``max_joint_gap`` [s]: longest joint-state step interpolated over (None: 5 times the median step)."""

    imu: str = "/imu"
    joint_states: str = "/joint_states"
    joint: str | None = None
    slip: str | None = None
    bag_time: bool = False
    max_joint_gap: float | None = None


def _rosbags():
    highlevel = import_extra("rosbags.highlevel", "ros", "reading ROS 2 bags")
    typesys = import_extra("rosbags.typesys", "ros", "reading ROS 2 bags")
    return highlevel.AnyReader, highlevel.AnyReaderError, typesys.Stores, typesys.get_typestore


def _stamp(msg) -> float:
    st = msg.header.stamp
    return st.sec + st.nanosec * 1e-9


class RosBag:
    """One bag's wheel-leg samples (see the module docstring); a context manager.

    Opening checks the topics and their types and reads the joint states;
    :meth:`iter_chunks` then streams the IMU samples.  Errors
    (:class:`~slipest.io.log_csv.LogFormatError`) name the bag and what is
    wrong: a topic missing (the bag's topics are listed), of another type,
    empty, the joint not found (the joints are listed), zero stamps.
    """

    def __init__(self, path, topics: BagTopics = BagTopics()):
        AnyReader, self._error, Stores, get_typestore = _rosbags()
        self.path = os.fspath(path)
        self.topics = topics
        if not os.path.exists(self.path):
            raise FileNotFoundError(2, "no such file or directory", self.path)
        self.c = {"imu_messages": 0, "joint_states": 0, "joint_missing": 0, "slip_messages": 0,
                         "outside_joint_states": 0, "in_joint_gap": 0, "samples": 0}
        try:
            self._reader = AnyReader([Path(self.path)], default_typestore=get_typestore(Stores.LATEST))
            self._reader.open()
        except (self._error, OSError, ValueError, KeyError) as exc:
            raise LogFormatError(f"not a readable rosbag2 bag ({type(exc).__name__}: {exc})", self.path) from None
        try:
            self._imu = self._connections(topics.imu, (IMU_TYPE,))
            self._joint = self._connections(topics.joint_states, (JOINT_STATE_TYPE,))
            self._slip = self._connections(topics.slip, SLIP_TYPES) if topics.slip else []
            self.joint_name = topics.joint
            self._read_joint_states()
        except BaseException:
            self.close()
            raise

    # -- set-up ---------------------------------------------------------------------------
    def _fail(self, reason: str):
        raise LogFormatError(reason, self.path)

    def _zero_stamps(self, topic: str, what: str):
        self._fail(f"the {what} messages on {topic} have zero header stamps: read with the bag's receive times "
                   "instead (bag_time; slipest replay --bag-time)")

    def _connections(self, topic: str, types: tuple):
        conns = [c for c in self._reader.connections if c.topic == topic]
        if not conns:
            have = ", ".join(f"{c.topic} ({c.msgtype})" for c in self._reader.connections) or "none"
            self._fail(f"no topic {topic!r} in the bag (its topics: {have})")
        bad = sorted({c.msgtype for c in conns if c.msgtype not in types})
        if bad:
            self._fail(f"topic {topic!r} carries {', '.join(bad)}, expected {' or '.join(types)}")
        return conns

    def _messages(self, conns):
        """(connection, bag time [ns], message) in bag order; a message that cannot be read names its topic."""
        reader = self._reader
        for conn, ns, raw in reader.messages(connections=conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except self._error as exc:
                self._fail(f"a {conn.msgtype} message on {conn.topic} at bag time {ns} ns cannot be read: {exc}")
            yield conn, ns, msg

    def _read_joint_states(self) -> None:
        name = self.joint_name
        t, pos = [], []
        index_of: dict[tuple, int | None] = {}
        short = 0  # messages that name the joint but hold no position for it
        for _conn, ns, msg in self._messages(self._joint):
            names = tuple(msg.name)
            if name is None:
                if len(names) != 1:
                    self._fail(f"the JointState messages on {self.topics.joint_states} carry the joints "
                               f"{', '.join(names) or '(none)'}: name the wheel-leg joint")
                name = self.joint_name = names[0]
            k = index_of.get(names, -1)
            if k == -1:
                k = index_of[names] = names.index(name) if name in names else None
            if k is None or k >= len(msg.position):
                self.c["joint_missing"] += 1
                short += k is not None
                continue
            t.append(ns * 1e-9 if self.topics.bag_time else _stamp(msg))
            pos.append(float(msg.position[k]))
        self.c["joint_states"] = len(t)
        if not t:
            if short:
                self._fail(f"the JointState messages on {self.topics.joint_states} name the joint {name!r} but "
                           f"carry no position for it ({short} message(s) with too few positions)")
            if self.c["joint_missing"]:
                known = sorted({n for names in index_of for n in names})
                self._fail(f"no JointState message on {self.topics.joint_states} carries the joint {name!r} "
                           f"(joints: {', '.join(known)})")
            self._fail(f"no JointState message on {self.topics.joint_states}")
        tj = np.asarray(t)
        if not self.topics.bag_time and not np.any(tj):
            self._zero_stamps(self.topics.joint_states, "JointState")
        order = np.argsort(tj, kind="stable")
        tj, pj = tj[order], np.asarray(pos)[order]
        keep = np.concatenate(([True], np.diff(tj) > 0))  # one position per instant: the first
        tj, pj = tj[keep], pj[keep]
        finite = np.isfinite(pj)
        tj, pj = tj[finite], np.unwrap(pj[finite])
        if tj.size < 2:
            self._fail(f"fewer than two usable joint states for {name!r} on {self.topics.joint_states}")
        gap = self.topics.max_joint_gap
        self.max_joint_gap = float(gap) if gap is not None else 5.0 * float(np.median(np.diff(tj)))
        self._tj, self._pj = tj, pj

    # -- samples --------------------------------------------------------------------------
    def _theta(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mask of the IMU times inside the joint states' span, theta [rad] at those; NaN inside a gap)."""
        tj, pj = self._tj, self._pj
        inside = (t >= tj[0]) & (t <= tj[-1])
        ti = t[inside]
        theta = np.interp(ti, tj, pj)
        k = np.clip(np.searchsorted(tj, ti, side="right"), 1, tj.size - 1)
        in_gap = (tj[k] - tj[k - 1]) > self.max_joint_gap
        theta[in_gap] = np.nan
        self.c["outside_joint_states"] += int(t.size - ti.size)
        self.c["in_joint_gap"] += int(np.count_nonzero(in_gap))
        return inside, theta

    def _chunk(self, t, az, slip) -> LogChunk | None:
        t = np.asarray(t, np.float64)
        if self.c["samples"] == 0 and not self.topics.bag_time and t.size and not np.any(t):
            self._zero_stamps(self.topics.imu, "Imu")
        inside, theta = self._theta(t)
        chunk = LogChunk(t[inside], np.asarray(az, np.float64)[inside], theta,
                         np.asarray(slip, np.float64)[inside] if self._slip else None, {})
        self.c["samples"] += len(chunk)
        return chunk if len(chunk) else None

    def iter_chunks(self, chunk_rows: int = 65536) -> Iterator[LogChunk]:
        """:class:`~slipest.io.log_csv.LogChunk` s of at most ``chunk_rows`` samples (``slip`` None
        without a slip topic), in the bag's order.  Iterate once."""
        slip_ids = {c.id for c in self._slip}
        bag_time = self.topics.bag_time
        c = self.c
        t, az, slip = [], [], []
        current = np.nan
        for conn, ns, msg in self._messages(self._imu + self._slip):
            if conn.id in slip_ids:
                current = float(msg.data)
                c["slip_messages"] += 1
                continue
            c["imu_messages"] += 1
            t.append(ns * 1e-9 if bag_time else _stamp(msg))
            az.append(msg.linear_acceleration.z)
            slip.append(current)
            if len(t) >= chunk_rows:
                chunk = self._chunk(t, az, slip)
                t, az, slip = [], [], []
                if chunk is not None:
                    yield chunk
        if t:
            chunk = self._chunk(t, az, slip)
            if chunk is not None:
                yield chunk
        if not c["imu_messages"]:
            self._fail(f"no Imu message on {self.topics.imu}")

    def counters(self) -> dict:
        """``imu_messages``, ``joint_states`` (usable), ``joint_missing`` (JointState messages without
        the joint), ``slip_messages``, ``outside_joint_states``, ``in_joint_gap``, ``samples`` (handed on)."""
        return dict(self.c)

    @property
    def has_slip(self) -> bool:
        return bool(self._slip)

    def close(self) -> None:
        reader = getattr(self, "_reader", None)
        if reader is not None and reader.stack is not None:
            reader.close()

    def __enter__(self) -> "RosBag":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
