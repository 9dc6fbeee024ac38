"""The bridge's command check and the simulated arm."""

import math

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.services.bridge.core import Limits, SimArm, check_command

LIM = Limits(np.full(2, -1.0), np.full(2, 1.0), np.array([1.0, 2.0]), np.array([10.0, 10.0]))
TR = m.Trace(0, 0)


def pos(q, owner="p"):
    return m.PositionCommand(seq=1, stamp_ns=0, owner=owner, q=q, trace=TR)


def vel(dq, owner="p"):
    return m.VelocityCommand(seq=1, stamp_ns=0, owner=owner, dq=dq, trace=TR)


@pytest.mark.parametrize(
    ("cmd", "reason"),
    [
        (pos([0.0, 0.0]), None),
        (vel([0.0, 0.0]), None),
        (pos([0.0, 0.0], owner="intruder"), "active planner is 'p'"),
        (pos([0.0]), "has 1 joints"),
        (vel([0.0, math.nan]), "non-finite"),
        (pos([math.inf, 0.0]), "non-finite"),
    ],
)
def test_check_command(cmd, reason):
    got = check_command(cmd, "p", 2)
    if reason is None:
        assert got is None
    else:
        assert reason in got


def run(arm, seconds, dt=0.002):
    qs, dqs = [], []
    for _ in range(round(seconds / dt)):
        arm.step(dt)
        qs.append(arm.q.copy())
        dqs.append(arm.dq.copy())
    return np.array(qs), np.array(dqs)


def test_velocity_is_speed_and_acceleration_limited():
    arm = SimArm(LIM, np.zeros(2))
    arm.command_velocity(np.array([5.0, 1.0]))
    _, dqs = run(arm, 0.5)
    assert np.all(np.abs(dqs) <= LIM.v_max + 1e-12)
    acc = np.diff(dqs, axis=0) / 0.002
    assert np.all(np.abs(acc) <= LIM.a_max[0] + 1e-6)
    assert dqs[-1] == pytest.approx([1.0, 1.0])
    assert arm.clipped > 0


def test_position_target_reached_and_joint_limits_hold():
    arm = SimArm(LIM, np.zeros(2))
    arm.command_position(np.array([0.5, 3.0]))  # second joint beyond its limit: clipped
    qs, _ = run(arm, 3.0)
    assert qs[-1] == pytest.approx([0.5, 1.0], abs=1e-3)
    assert qs.max() <= 1.0 and arm.clipped == 1


def test_stop_decelerates_within_limit():
    wide = Limits(np.full(2, -10.0), np.full(2, 10.0), LIM.v_max, LIM.a_max)
    arm = SimArm(wide, np.zeros(2))
    arm.command_velocity(np.array([1.0, 2.0]))
    run(arm, 0.5)
    q_before = arm.q.copy()
    predicted = arm.stopping_distance()
    arm.stop()
    qs, dqs = run(arm, 0.5)
    assert np.all(np.abs(np.diff(dqs, axis=0)) / 0.002 <= 10.0 + 1e-6)
    assert dqs[-1] == pytest.approx([0.0, 0.0])
    assert np.abs(qs[-1] - q_before) == pytest.approx(predicted, abs=0.01)
