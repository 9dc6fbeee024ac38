"""Run by the system's Python 3 with the real rospy: an AIRSKIN-like skin node for the tests.

Publishes TYPE (generated from DEFINITION, a float array field "pressures") on TOPIC at
RATE Hz: N values at rest near 1013 hPa, and while the file PRESS_FILE exists a press of
PEAK hPa on value INDEX. A hostile skin, while the file MODE_FILE exists, by its content:
"nan" every value NaN, "pa" every value in Pa instead of hPa, "short" only the first 3 values.
Arguments: TOPIC TYPE DEFINITION N INDEX PEAK PRESS_FILE [RATE [MODE_FILE]]
"""

import math
import os
import sys
import time

import rospy
from genpy.dynamic import generate_dynamic


def main() -> None:
    topic, type_name, definition = sys.argv[1:4]
    n, index, peak, press_file = int(sys.argv[4]), int(sys.argv[5]), float(sys.argv[6]), sys.argv[7]
    rate_hz = float(sys.argv[8]) if len(sys.argv) > 8 else 30.0
    mode_file = sys.argv[9] if len(sys.argv) > 9 else ""
    cls = generate_dynamic(type_name, definition)[type_name]
    rospy.init_node("fake_airskin", anonymous=True, disable_signals=True)
    pub = rospy.Publisher(topic, cls, queue_size=10)
    rest = [1013.0 + 0.5 * i for i in range(n)]
    start = time.monotonic()
    rate = rospy.Rate(rate_hz)
    while not rospy.is_shutdown():
        t = time.monotonic() - start
        values = [r + 0.02 * math.sin(t + i) for i, r in enumerate(rest)]
        if os.path.exists(press_file):
            values[index] += peak
        mode = ""
        if mode_file and os.path.exists(mode_file):
            with open(mode_file) as f:
                mode = f.read().strip()
        if mode == "nan":
            values = [float("nan")] * n
        elif mode == "pa":
            values = [v * 100.0 for v in values]
        elif mode == "short":
            values = values[:3]
        pub.publish(cls(pressures=values))
        rate.sleep()


if __name__ == "__main__":
    main()
