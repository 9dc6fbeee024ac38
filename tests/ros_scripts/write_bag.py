"""Run by the system's Python 3 with the real rosbag: a ROS 1 bag of a touch session for the tests.

Writes OUT.bag: TYPE (generated from DEFINITION, a float array field "pressures") on TOPIC
at 30 Hz for SECONDS s, N values at rest near 1013 hPa with a press of 15 hPa on value INDEX
from 3.0 s to 3.8 s, one message of N - 2 values at 2.0 s and one with a NaN on value 0 at
2.5 s; sensor_msgs/JointState on /joint_states at 100 Hz, its joints in reverse order.
Arguments: OUT TOPIC TYPE DEFINITION N INDEX SECONDS JOINT,NAMES,... [BAD]
With BAD (a number), joint state 50 puts the third joint at BAD rad, joint state 51 the fourth at NaN and
joint state 52 the second joint's velocity at BAD rad/s.
"""

import math
import sys

import rosbag
import rospy
from genpy.dynamic import generate_dynamic
from sensor_msgs.msg import JointState


def main() -> None:
    out, topic, type_name, definition = sys.argv[1:5]
    n, index, seconds = int(sys.argv[5]), int(sys.argv[6]), float(sys.argv[7])
    joints = sys.argv[8].split(",")
    bad = float(sys.argv[9]) if len(sys.argv) > 9 else None
    cls = generate_dynamic(type_name, definition)[type_name]
    t0 = 1_700_000_000.0
    with rosbag.Bag(out, "w") as bag:
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
            bag.write(topic, cls(pressures=values), rospy.Time.from_sec(t0 + t))
            k += 1
        k = 0
        while k / 100.0 < seconds:
            t = k / 100.0
            msg = JointState()
            msg.header.stamp = rospy.Time.from_sec(t0 + t)
            msg.name = list(reversed(joints))
            q = [0.1 * i + 0.01 * math.sin(t) for i in range(len(joints))]
            dq = [0.0] * len(joints)
            if bad is not None and k == 50:
                q[2] = bad
            if bad is not None and k == 51:
                q[3] = float("nan")
            if bad is not None and k == 52:
                dq[1] = bad
            msg.position = list(reversed(q))
            msg.velocity = list(reversed(dq))
            bag.write("/joint_states", msg, rospy.Time.from_sec(t0 + t))
            k += 1


if __name__ == "__main__":
    main()
