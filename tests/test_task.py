"""The study's task around a home a profile chooses (planner.task.home_rad): reflexes from several poses."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from nwr.common.config import Profile, check_against_robot
from nwr.common.errors import ConfigError
from nwr.common.robot import load_description
from nwr.common.task import FigureEight, TaskSection

DESC = load_description()
# Another pose of the UR10e: the elbow nearly stretched, the wrist turned (within every joint's limits).
ELSEWHERE = [0.6, -1.4, 0.6, -1.2, -1.57, 0.8]


def test_the_eight_is_drawn_around_the_task_home() -> None:
    robots = FigureEight(TaskSection(), DESC)
    moved = FigureEight(TaskSection(home_rad=ELSEWHERE), DESC)
    assert np.allclose(robots.position(0.0), DESC.home) and np.allclose(moved.position(0.0), ELSEWHERE)
    for s in (1.0, 2.5, 7.0):  # the same swing, around the other pose
        assert np.allclose(moved.position(s) - moved.home, robots.position(s) - robots.home)
    lo, hi = moved.range()
    assert np.allclose((lo + hi) / 2, ELSEWHERE)


def test_a_profile_checks_the_task_home_against_the_robot() -> None:
    profile = msgspec.convert({"planner": {"task": {"home_rad": ELSEWHERE}}}, Profile)
    check_against_robot(profile, DESC)  # within the limits, its fastest point within the bridge's
    short = msgspec.convert({"planner": {"task": {"home_rad": ELSEWHERE[:5]}}}, Profile)
    with pytest.raises(ConfigError, match="home_rad have .* 5 joints"):
        check_against_robot(short, DESC)
    # The base swings 0.35 rad: around a home 0.1 rad inside the bridge's limit it would swing beyond it.
    edge = [*ELSEWHERE]
    edge[0] = float(DESC.q_max[0]) - 0.1  # (the profile narrows no joint's range)
    beyond = msgspec.convert({"planner": {"task": {"home_rad": edge}}}, Profile)
    with pytest.raises(ConfigError, match=r"around 6.18319 rad \(the task's home\).*planner.task.home_rad"):
        check_against_robot(beyond, DESC)
