"""Switching the active planner at runtime: the bridge's rules and the planners' handover."""

import numpy as np
import pytest
from test_bridge import ENV, pos, skin  # noqa: E402  (the bridge tests' helpers)

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.robot import RobotModel, load_description
from nwr.services.bridge.core import BridgeCore
from nwr.services.planner.core import Planner

MS = 1_000_000


def bridge(active="a"):
    c = BridgeCore(ENV, np.zeros(2), 0, active=active, n_pads=3)
    for name in ("a", "b"):
        c.on_planner_token(name, True, 0)
    c.on_skin(skin(), 0)
    return c


def request(name, stamp=0):
    return m.SwitchRequest(seq=0, stamp_ns=stamp, name=name)


def test_switch_refused_to_a_planner_that_is_not_running():
    c = bridge()
    assert not c.request_switch(request("ghost"), 1 * MS)
    assert c.active == "a" and c.pending is None
    assert any(e.code == "switch_rejected" and "ghost" in e.message for e in c.drain_events())


def test_switch_during_task_is_immediate_and_quiet_for_the_outgoing_planner():
    c = bridge()
    c.on_command(pos([0.0, 0.0], owner="a", seq=1, stamp=1 * MS), 1 * MS)
    assert c.request_switch(request("b", stamp=2 * MS), 2 * MS)
    assert c.active == "b" and c.publish_now
    state = c.state(0, 2 * MS, np.zeros(2), np.zeros(2), "sim")
    assert state.owner == "b" and state.handover.previous == "a" and state.handover.first_command_ns == 0
    c.drain_events()
    late = c.on_command(pos([0.0, 0.0], owner="a", seq=2, stamp=3 * MS), 3 * MS)
    assert not late.accepted and not c.drain_events()  # dropped without a warning
    first = c.on_command(pos([0.001, 0.0], owner="b", seq=0, stamp=4 * MS), 4 * MS)
    assert first.accepted
    assert c.handover.first_command_ns == 4 * MS


def test_switch_waits_for_the_reflex_and_its_return():
    c = bridge()
    c.on_command(pos([0.0, 0.0], owner="a", seq=1, phase="REFLEX", reflex=1, stamp=1 * MS), 1 * MS)
    assert not c.request_switch(request("b"), 2 * MS)
    assert c.pending is not None and c.active == "a"
    assert c.state(0, 2 * MS, np.zeros(2), np.zeros(2), "sim").pending_owner == "b"
    c.on_command(pos([0.0, 0.0], owner="a", seq=2, phase="RETURNING", reflex=1, stamp=3 * MS), 3 * MS)
    assert c.active == "a"
    verdict = c.on_command(pos([0.0, 0.0], owner="a", seq=3, phase="TASK", stamp=4 * MS), 4 * MS)
    assert verdict.switched and c.active == "b"


def test_switch_abandoned_when_the_incoming_planner_dies():
    c = bridge()
    c.on_command(pos([0.0, 0.0], owner="a", seq=1, phase="REFLEX", reflex=1), 1 * MS)
    c.request_switch(request("b"), 2 * MS)
    c.on_planner_token("b", False, 3 * MS)
    c.on_command(pos([0.0, 0.0], owner="a", seq=2, phase="TASK"), 4 * MS)
    assert c.active == "a" and c.pending is None


DESC = load_description()
MODEL = RobotModel(DESC)


def test_incoming_planner_continues_the_task_without_a_jump():
    a = Planner(PlannerSection(name="a", strategy="cartesian"), DESC, MODEL)
    b = Planner(PlannerSection(name="b", strategy="uniform"), DESC, MODEL)
    t = 0
    q, dq = DESC.home.copy(), np.zeros(6)
    for planner in (a, b):
        planner.on_state(q, True, dq=dq, owner="a", now_ns=t)
    last = None
    for i in range(3000):  # 6 s: the initial return, then the task
        t += 2 * MS
        cmd = a.step(t)
        if cmd is not None:
            last = cmd
        assert b.step(t) is None  # the inactive planner never commands
        if i % 4 == 0:  # robot state at 125 Hz: the arm is where a commanded it
            for planner in (a, b):
                planner.on_state(a.q.copy(), True, dq=a.dq.copy(), owner="a", now_ns=t)
        if i % 25 == 0:  # planner status at 20 Hz
            b.on_peer_status(a.status(t), t)
    assert a.mode == "TASK" and b.mode == "TASK" and not b.active
    assert b.clock.s == pytest.approx(a.clock.s, abs=0.06)
    # The switch: b learns it is active from the robot state.
    b.on_state(a.q.copy(), True, dq=a.dq.copy(), owner="b", now_ns=t)
    assert b.active and b.mode == "TASK"
    a.on_state(a.q.copy(), True, dq=a.dq.copy(), owner="b", now_ns=t)
    assert not a.active and a.step(t + 2 * MS) is None
    first = b.step(t + 2 * MS)
    step = np.abs(np.asarray(first.q) - np.asarray(last.q))
    # The first command of the incoming planner is within what the speed limits allow in two cycles.
    assert np.all(step <= DESC.v_max * 0.004)
    assert first.owner == "b" and first.phase == "TASK"


def test_inactive_planner_computes_shadow_reflexes():
    b = Planner(PlannerSection(name="b", strategy="uniform"), DESC, MODEL)
    b.on_state(DESC.home.copy(), True, dq=np.zeros(6), owner="a", now_ns=0)
    pad = DESC.pad("upper_arm_top")
    gains = [0.0] * len(DESC.pads)
    gains[pad.id] = 0.5
    contact = m.Contact(pad=pad.id, name=pad.name, region=pad.region, change_hpa=14.0, level=4, gain=0.5)
    pain = m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="continuous", level=[1] * len(gains),
                      gain=gains, strongest=contact)
    assert b.on_pain(pain, 1 * MS) is None  # it never commands
    status = b.status(1 * MS)
    assert not status.active and status.reflex is not None and status.reflex.shadow
    assert status.reflex.retreat is not None and status.reflex.retreat.approached  # UR pushes this pad into the hand
    np.testing.assert_allclose(status.reflex.target[:4],
                               DESC.home[:4] + np.array([1, -1, 1, 1]) * np.radians([20, 35, 73, 36.5]), atol=1e-9)
