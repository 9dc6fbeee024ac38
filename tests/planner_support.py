"""A planner driven by hand in the tests: brought from home into its task."""

from __future__ import annotations

from nwr.common.config import PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.core import Planner


def running(cfg: PlannerSection, desc: RobotDescription, model: RobotModel) -> tuple[Planner, int]:
    """A planner of ``cfg`` that has reached its task from the robot's home pose, and the time (ns), at 500 Hz."""
    planner = Planner(cfg, desc, model)
    planner.on_state(desc.home.copy(), following=True)
    t = 0
    while planner.mode != "TASK":
        t += 2_000_000
        planner.step(t)
    return planner, t
