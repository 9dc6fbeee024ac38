"""Returns near recent contacts (services/planner/returning.py): no pad nor the flange within approach_distance_m
of a touch felt in the last recent_contact_s moves toward it faster than approach_speed_m_s.

Synthetic contacts are placed on the way of a return (the first approach to the task's start, which is one), and
the planner's commanded stream, integrated cycle by cycle, is measured against each of them.
"""

from __future__ import annotations

import numpy as np
import pytest

from nwr.common.config import PlannerSection
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.contacts import ContactPoint
from nwr.services.planner.core import Planner

DESC = load_description()
MODEL = RobotModel(DESC)
NAMES = [pad.name for pad in DESC.pads]
DT_NS = 2_000_000  # the planner's 500 Hz cycle
CFG = PlannerSection(strategy="cartesian")
# A start away from the task's: the base and the shoulder turned, so that every pad sweeps across the room.
AWAY = np.array([0.9, -0.35, 0.0, 0.3, 0.0, 0.0])


def points(q: np.ndarray) -> np.ndarray:
    """The points the rule keeps slow: every pad and the flange."""
    return np.vstack([MODEL.pad_points(q), MODEL.tool_position(q)])


def approach(contacts: list[tuple[str, float]]) -> tuple[list[np.ndarray], list[ContactPoint], Planner]:
    """The commanded poses of the first approach from DESC.home + AWAY to the task's start, with a recent touch
    on each (pad, fraction of the straight way) of ``contacts``, where that pad passes at that fraction."""
    planner = Planner(CFG, DESC, MODEL)
    q0 = DESC.home + AWAY
    target = planner.task.position(0.0)
    places = []
    for name, x in contacts:
        i = NAMES.index(name)
        q = q0 + x * (target - q0)
        places.append(ContactPoint(i, MODEL.pad_point(q, i), MODEL.pad_normal(q, i), 0.0, 0, 0))
        planner.contacts.touches[i] = places[-1]
    planner.on_state(q0.copy(), following=True)
    poses, t = [q0.copy()], 0
    while planner.mode != "TASK":
        t += DT_NS
        planner.step(t)
        poses.append(planner.q.copy())
        assert t < 60e9, "the approach arrives"
    return poses, places, planner


def fastest_toward(poses: list[np.ndarray], place: np.ndarray, within: float) -> float:
    """The fastest any pad or the flange moved toward ``place`` while within ``within`` of it, m/s."""
    worst = 0.0
    for a, b in zip(poses, poses[1:]):
        xa, xb = points(a), points(b)
        to = place - xa
        dist = np.linalg.norm(to, axis=1)
        close = (dist <= within) & (dist > 1e-9)
        if close.any():
            speed = np.einsum("pk,pk->p", xb - xa, to) / np.where(close, dist, 1.0) / (DT_NS / 1e9)
            worst = max(worst, float(np.max(np.where(close, speed, 0.0))))
    return worst


def test_without_a_recent_contact_the_way_sweeps_fast_through_where_one_would_be() -> None:
    poses, _, _ = approach([])
    q0, target = poses[0], poses[-1]
    for name, x in [("wrist_1", 0.15), ("wrist_2", 0.5), ("wrist_3", 0.85)]:
        i = NAMES.index(name)
        place = MODEL.pad_point(q0 + x * (target - q0), i)
        assert fastest_toward(poses, place, CFG.approach_distance_m) > 2.5 * CFG.approach_speed_m_s


@pytest.mark.parametrize("contacts", [[("wrist_2", 0.5)], [("wrist_3", 0.3), ("forearm_top", 0.7)],
                                      [("wrist_1", 0.15), ("elbow_outer", 0.6), ("upper_arm_bottom", 0.85)]])
def test_no_point_approaches_a_recent_contact_faster_than_the_approach_speed(contacts: list[tuple[str, float]]
                                                                              ) -> None:
    poses, places, planner = approach(contacts)
    assert np.allclose(poses[-1], planner.task.position(0.0), atol=1e-6)  # it still arrives where the task starts
    for place in places:
        assert fastest_toward(poses, place.point, CFG.approach_distance_m) <= CFG.approach_speed_m_s * 1.001
    # Away from the contacts it keeps the return's pace: every point within return_speed_m_s, the fastest near it.
    fastest_away = 0.0
    for a, b in zip(poses, poses[1:]):
        speeds = np.linalg.norm(points(b) - points(a), axis=1) / (DT_NS / 1e9)
        assert speeds.max() <= CFG.return_speed_m_s * 1.001
        if min(np.linalg.norm(points(a) - p.point, axis=1).min() for p in places) > 2 * CFG.approach_distance_m:
            fastest_away = max(fastest_away, float(speeds.max()))
    assert fastest_away >= 0.8 * CFG.return_speed_m_s


def test_a_touch_that_begins_during_a_return_slows_the_rest_of_it_near_every_recent_contact() -> None:
    """A touch felt during a return (PL 2, no reflex) has the rest of the return planned again: near it, and near
    every other recent contact, no point moves toward the place faster than the approach speed."""
    from nwr.common import messages as m

    def run(felt: bool) -> float:
        planner = Planner(CFG, DESC, MODEL)
        q0 = DESC.home + AWAY
        target = planner.task.position(0.0)
        planner.on_state(q0.copy(), following=True)
        poses, t = [q0.copy()], 0
        for _ in range(300):  # under way
            t += DT_NS
            planner.step(t)
            poses.append(planner.q.copy())
        assert planner.mode == "RETURNING"
        i = NAMES.index("wrist_2")  # a place ahead on its way, known since now
        ahead = q0 + 0.6 * (target - q0)
        place = ContactPoint(i, MODEL.pad_point(ahead, i), MODEL.pad_normal(ahead, i), 0.0, t, t)
        planner.contacts.touches[i] = place
        if felt:  # a touch on the shoulder, felt now: the return is planned again
            level = [1] * len(NAMES)
            level[NAMES.index("shoulder_back")] = 2
            pain = m.SkinPain(seq=1, stamp_ns=t, trace=m.Trace(1, t), model="continuous", level=level,
                              gain=[0.0] * len(NAMES), strongest=None)
            assert planner.on_pain(pain, t) is None and planner.mode == "RETURNING"
            assert planner.contacts.touches[i] is place  # still recent
        while planner.mode != "TASK":
            t += DT_NS
            planner.step(t)
            poses.append(planner.q.copy())
        assert np.allclose(poses[-1], target, atol=1e-6)
        return fastest_toward(poses[301:], place.point, CFG.approach_distance_m)

    assert run(felt=False) > 2.5 * CFG.approach_speed_m_s  # planned before the place was known: through it fast
    assert run(felt=True) <= CFG.approach_speed_m_s * 1.001
