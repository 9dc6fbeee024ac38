"""ROS 2 bags for the tests, written by ``rosbags``' own rosbag2 writer (no ROS 2 needed): the same touch session
as the ROS 1 bags of tests/ros_scripts/write_bag.py, in either storage (MCAP or SQLite)."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

AIRSKIN_TYPE = "airskin_msgs/msg/AirskinStatus"
AIRSKIN_DEFINITION = "float32[] pressures"
TOPIC = "/bullet_ros/airskin_status"
T0_NS = 1_700_000_000 * 10**9
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


def typestore() -> Any:
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(AIRSKIN_DEFINITION, AIRSKIN_TYPE))
    return store


def joint_state(store: Any, stamp_ns: int, names: list[str], q: list[float], dq: list[float]) -> Any:
    t = store.types
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                             nanosec=stamp_ns % 10**9), frame_id="")
    return t["sensor_msgs/msg/JointState"](header=header, name=names, position=np.array(q, dtype=np.float64),
                                           velocity=np.array(dq, dtype=np.float64),
                                           effort=np.array([], dtype=np.float64))


def write_ros2_bag(path: Path, joints: list[str], *, storage: str = "mcap", n: int = 11, index: int = 4,
                   seconds: float = 6.0, bad: float | None = None,
                   spoil: Callable[[str, int, bytes], bytes] | None = None) -> Path:
    """A rosbag2 directory ``path``: AirskinStatus on TOPIC at 30 Hz for ``seconds``, ``n`` values at rest near
    1013 hPa with a press of 15 hPa on value ``index`` from 3.0 s to 3.8 s, one message of n - 2 values at 2.0 s
    and one with a NaN on value 0 at 2.5 s; sensor_msgs/msg/JointState on /joint_states at 100 Hz, its joints in
    reverse order. With ``bad``, joint state 50 puts the third joint at ``bad`` rad, 51 the fourth at NaN, 52 the
    second's velocity at ``bad`` rad/s. ``spoil(topic, k, cdr)`` may replace the k-th message's bytes."""
    store = typestore()
    with Writer(path, version=9, storage_plugin=STORAGES[storage]) as writer:
        skin = writer.add_connection(TOPIC, AIRSKIN_TYPE, typestore=store)
        states = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=store)
        records: list[tuple[int, Any, str, int, bytes]] = []
        k = 0
        while k / 30.0 < seconds:
            t = k / 30.0
            values = [1013.0 + 0.5 * i + 0.02 * math.sin(t + i) for i in range(n)]
            if 3.0 <= t < 3.8:
                values[index] += 15.0
            if k == 60:
                values = values[:n - 2]
            if k == 75:
                values[0] = float("nan")
            msg = store.types[AIRSKIN_TYPE](pressures=np.array(values, dtype=np.float32))
            records.append((T0_NS + round(t * 1e9), skin, TOPIC, k, store.serialize_cdr(msg, AIRSKIN_TYPE)))
            k += 1
        k = 0
        while k / 100.0 < seconds:
            t = k / 100.0
            q = [0.1 * i + 0.01 * math.sin(t) for i in range(len(joints))]
            dq = [0.0] * len(joints)
            if bad is not None and k == 50:
                q[2] = bad
            if bad is not None and k == 51:
                q[3] = float("nan")
            if bad is not None and k == 52:
                dq[1] = bad
            stamp = T0_NS + round(t * 1e9)
            msg = joint_state(store, stamp, list(reversed(joints)), list(reversed(q)), list(reversed(dq)))
            records.append((stamp, states, "/joint_states", k,
                            store.serialize_cdr(msg, "sensor_msgs/msg/JointState")))
            k += 1
        for stamp, connection, topic, k, data in sorted(records, key=lambda r: r[0]):
            writer.write(connection, stamp, spoil(topic, k, data) if spoil else data)
    return path


def storage_file(bag: Path) -> Path:
    """The one storage file of a rosbag2 directory."""
    (file,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return file
