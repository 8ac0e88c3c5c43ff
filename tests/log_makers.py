"""Recordings made here with the libraries a rover team uses: python-can's writers and rosbags.

The samples come from the simulator (:func:`slipest.model.stream.simulate_stream`), so the estimates
of a recording can be compared with those of the same samples in a slipest log CSV.
"""

from __future__ import annotations

import math

import can
import numpy as np

from slipest.io.can_messages import encode_imu, encode_slip_reference
from slipest.io.log_csv import LogWriter
from slipest.model.params import StickSlipParams
from slipest.model.scenario import Scenario
from slipest.model.stream import simulate_stream


def stream(n_cycles: int = 5, seed: int = 11, slip=None):
    """A simulated wheel-leg stream (``t, az, theta, slip``) and its scenario."""
    if slip is None:
        sc = Scenario.constant(n_cycles, noise_g=0.01, seed=seed)
    else:
        sc = Scenario.per_cycle(StickSlipParams(kS=900.0, phiS=0.5, phiD=0.3), dict(noise_g=0.01, seed=seed),
                                slip=np.asarray(slip, float))
    return simulate_stream(sc), sc


def write_csv(path, s, sc):
    with LogWriter(path, ("t", "az", "theta", "slip"), metadata=sc.metadata()) as w:
        w.write(s.t, s.az, s.theta, s.slip)
    return path


def can_frames(streams: dict, *, time_scale: float = 1.0, t0: float = 1000.0, drop: dict | None = None,
               unknown_every: int = 0, references: bool = True) -> list[can.Message]:
    """The frames of wheel -> stream, interleaved in time order as a bus carries them: one ImuSample per
    sample, a SlipReference whenever the wheel's slip changes (``references``), an unknown-ID frame every
    ``unknown_every`` samples.  ``drop``: wheel -> sample indices not sent (lost frames).  Timestamps
    ``t0 + t / time_scale`` (a recording replayed faster than it was driven)."""
    drop = drop or {}
    out = []
    n = max(len(s.t) for s in streams.values())
    last_slip, n_refs = {}, {}
    for i in range(n):
        for wheel, s in streams.items():
            if i >= len(s.t):
                continue
            ts = t0 + float(s.t[i]) / time_scale
            if references and s.slip[i] != last_slip.get(wheel):
                last_slip[wheel] = s.slip[i]
                n_refs[wheel] = n_refs.get(wheel, -1) + 1
                m = encode_slip_reference(wheel, n_refs[wheel], float(s.slip[i]), float(s.t[i]))
                m.timestamp, m.channel = ts, "vcan0"
                out.append(m)
            if i in drop.get(wheel, ()):
                continue
            m = encode_imu(wheel, i, float(s.az[i]), float(s.theta[i]), float(s.t[i]))
            m.timestamp, m.channel = ts, "vcan0"
            out.append(m)
        if unknown_every and i % unknown_every == 0:
            out.append(can.Message(arbitration_id=0x7AB, data=b"\x01\x02", is_extended_id=False, timestamp=ts,
                                   channel="vcan0"))
    return out


def with_references(frames, replace: dict) -> list[can.Message]:
    """``frames`` with the k-th SlipReference frame's slip replaced by ``replace[k]`` (timestamp, channel,
    wheel, counter and time kept): e.g. a negative slip, which the DBC's signed field carries, or 1.5."""
    from slipest.io.can_messages import SlipReferenceMessage, decode

    out, k = [], 0
    for m in frames:
        rec = decode(m)
        if isinstance(rec, SlipReferenceMessage):
            if k in replace:
                bad = encode_slip_reference(rec.wheel, rec.counter, replace[k], rec.time_mod)
                bad.timestamp, bad.channel, m = m.timestamp, m.channel, bad
            k += 1
        out.append(m)
    return out


def write_can_log(path, frames) -> str:
    """The frames written with python-can's writer for the file's suffix (can.Logger)."""
    with can.Logger(str(path)) as writer:
        for m in frames:
            writer.on_message_received(m)
    return str(path)


def write_bag(path, s, *, storage: str = "sqlite3", t0: float = 1.7e9, joint_every: int = 5,
              joints=("steer", "wheel_leg"), slip_topic: str | None = "/slip", zero_stamps: bool = False,
              joint_hole=None, positions: bool = True) -> str:
    """A rosbag2 bag written with rosbags: sensor_msgs/Imu on /imu (az as linear_acceleration.z, every
    sample), sensor_msgs/JointState on /joint_states every ``joint_every`` samples (the wheel-leg
    angle wrapped to [-pi, pi) under the last of ``joints``, the others at fixed positions), and
    std_msgs/Float64 reference slips on ``slip_topic`` whenever the slip changes.  Header stamps
    ``t0 + t`` (zero with ``zero_stamps``); ``joint_hole``: (t_from, t_to) without joint states;
    ``positions`` False: the joint states name the joints but carry an empty position array."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Imu, JointState, Float64 = (T["sensor_msgs/msg/Imu"], T["sensor_msgs/msg/JointState"], T["std_msgs/msg/Float64"])
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    Vector3, Quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    cov = np.zeros(9)
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c_imu = w.add_connection("/imu", Imu.__msgtype__, typestore=ts)
        c_js = w.add_connection("/joint_states", JointState.__msgtype__, typestore=ts)
        c_slip = w.add_connection(slip_topic, Float64.__msgtype__, typestore=ts) if slip_topic else None
        last_slip = None
        for i in range(len(s.t)):
            ns_total = int(round((t0 + float(s.t[i])) * 1e9))
            stamp = Time(sec=0, nanosec=0) if zero_stamps else Time(sec=ns_total // 10**9, nanosec=ns_total % 10**9)
            header = Header(stamp=stamp, frame_id="hub")
            if c_slip is not None and s.slip[i] != last_slip:
                last_slip = s.slip[i]
                w.write(c_slip, ns_total, ts.serialize_cdr(Float64(data=float(last_slip)), Float64.__msgtype__))
            in_hole = joint_hole is not None and joint_hole[0] <= s.t[i] < joint_hole[1]
            if i % joint_every == 0 and not in_hole:
                angle = (float(s.theta[i]) + math.pi) % (2 * math.pi) - math.pi
                pos = np.array([0.1] * (len(joints) - 1) + [angle]) if positions else np.zeros(0)
                msg = JointState(header=header, name=list(joints), position=pos, velocity=np.zeros(0),
                                 effort=np.zeros(0))
                w.write(c_js, ns_total, ts.serialize_cdr(msg, JointState.__msgtype__))
            msg = Imu(header=header, orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
                      angular_velocity=Vector3(x=0.0, y=0.0, z=0.0), angular_velocity_covariance=cov,
                      linear_acceleration=Vector3(x=0.0, y=0.0, z=float(s.az[i])),
                      linear_acceleration_covariance=cov)
            w.write(c_imu, ns_total, ts.serialize_cdr(msg, Imu.__msgtype__))
    return str(path)
