"""The cost of planning a return (its legs) without and with recent touches near its way, in one process.

    .venv/bin/python scripts/benchmarks/return_legs.py [--pairs 30]

A planner at a start away from its task plans the approach to the task's start (a return) with no recent touch
(A) and with three recent touches whose places lie on the way of three pads (B, the legs split and capped near
each), A and B alternating ``--pairs`` times. Prints the medians of each (ms, ``time.perf_counter``), the ratio
B/A and the machine's load: on a shared machine the ratio holds better than the times.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from nwr.common.config import PlannerSection
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.contacts import ContactPoint
from nwr.services.planner.core import Planner

AWAY = np.array([0.9, -0.35, 0.0, 0.3, 0.0, 0.0])
PLACES = [("wrist_1", 0.15), ("elbow_outer", 0.6), ("upper_arm_bottom", 0.85)]


def plan(desc, model, places: bool) -> float:  # type: ignore[no-untyped-def]
    planner = Planner(PlannerSection(strategy="cartesian"), desc, model)
    q0 = desc.home + AWAY
    target = planner.task.position(0.0)
    names = [pad.name for pad in desc.pads]
    for name, x in PLACES if places else []:
        i = names.index(name)
        q = q0 + x * (target - q0)
        planner.contacts.touches[i] = ContactPoint(i, model.pad_point(q, i), model.pad_normal(q, i), 0.0, 0, 0)
    start = time.perf_counter()
    planner.on_state(q0.copy(), following=True)  # the first approach: its legs planned here
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=30)
    args = parser.parse_args()
    desc = load_description()
    model = RobotModel(desc)
    plan(desc, model, False), plan(desc, model, True)  # warm-up
    a, b = [], []
    for _ in range(args.pairs):
        a.append(plan(desc, model, False))
        b.append(plan(desc, model, True))
    ma, mb = 1e3 * statistics.median(a), 1e3 * statistics.median(b)
    print(f"plan a return: no recent touch {ma:.2f} ms, three near its way {mb:.2f} ms (medians of {args.pairs}); "
          f"ratio {mb / ma:.2f}; load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
