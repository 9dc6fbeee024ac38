"""What the ROS 2 topics ([ros2] enabled) cost a service per sample, on loopback.

    .venv/bin/python scripts/ros2_publish_cost.py [--samples 2000]

A Zenoh router on a free loopback port stands in for rmw_zenohd, with one
subscriber on every ROS 2 key (so each put really travels). For each kind of
output that has a ROS 2 topic, the time the service's publishing thread
spends on the ROS 2 side of one output (:class:`nwr.common.ros2.Mirror`'s
tee, the pipeline's own put excluded): building the message, rosbags' CDR,
the attachment and the put; then the CDR alone. Medians and 99th
percentiles over ``--samples`` outputs, after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.rmw_zenoh import Ros2Section
from nwr.common.robot import load_description
from nwr.common.ros2 import Ros2Link, mirror
from nwr.common.ros2_msgs import ARRAY_TYPE, JOINT_STATE_TYPE, Ros2Builder


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def timed(call: Callable[[], Any], n: int) -> tuple[float, float]:
    """Median and 99th percentile of ``call``'s time, microseconds."""
    for _ in range(50):
        call()
    times = np.empty(n)
    for i in range(n):
        t = time.perf_counter_ns()
        call()
        times[i] = time.perf_counter_ns() - t
    return float(np.median(times)) / 1e3, float(np.percentile(times, 99)) / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2000)
    args = parser.parse_args()
    desc = load_description()
    n = len(desc.pads)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    received = [0]
    with zenoh.open(conf) as router:
        sub = router.declare_subscriber("0/**", lambda s: received.__setitem__(0, received[0] + 1))
        profile = Profile()
        profile.ros2 = Ros2Section(enabled=True, router=[endpoint])
        link = Ros2Link(profile.ros2, "bench", lambda *a, **k: print(*a))
        mir = mirror(link, profile)
        time.sleep(0.5)
        state = m.RobotState(seq=1, stamp_ns=time.monotonic_ns(), q=list(desc.home), dq=[0.0] * len(desc.joints),
                             status="ok", owner="cartesian", backend="sim")
        skin = m.SkinPressure(seq=1, stamp_ns=time.monotonic_ns(), absolute_hpa=[1013.0] * n,
                              baseline_hpa=[1013.0] * n, change_hpa=[0.0] * n, contact=[False] * n, valid=[True] * n)
        status = m.PlannerStatus(seq=1, stamp_ns=1, name="cartesian", strategy="cartesian", mode="TASK",
                                 task_time_s=0.0)
        nothing: Callable[[Any], None] = lambda message: None  # noqa: E731 (the pipeline's own put, left out)
        tees = {"robot/state -> joint_states": (mir.tee(keys.ROBOT_STATE, nothing), state),
                "skin/pressure -> nwr/skin/absolute_hpa + change_hpa": (mir.tee(keys.SKIN_PRESSURE, nothing), skin),
                "reflex/<name>/status, no change -> nothing": (mir.tee(keys.planner_status("cartesian"), nothing),
                                                               status)}
        build = Ros2Builder(link.types, desc.joints)
        print(f"ROS 2 side of one output, {args.samples} samples each (median / p99, microseconds):")
        for name, (tee, message) in tees.items():
            median, p99 = timed(lambda tee=tee, message=message: tee(message), args.samples)
            print(f"  {name:55s} {median:7.1f} / {p99:7.1f}")
        js, (arr, _) = build.joint_state(state), build.skin(skin)
        for name, msg, msgtype in (("CDR of a JointState (rosbags)", js, JOINT_STATE_TYPE),
                                   ("CDR of a Float64MultiArray (rosbags)", arr, ARRAY_TYPE)):
            median, p99 = timed(lambda msg=msg, msgtype=msgtype: link.types.serialize_cdr(msg, msgtype), args.samples)
            print(f"  {name:55s} {median:7.1f} / {p99:7.1f}")
        time.sleep(0.3)
        link.close()
        sub.undeclare()
    print(f"samples the router's subscriber received: {received[0]}")


if __name__ == "__main__":
    main()
