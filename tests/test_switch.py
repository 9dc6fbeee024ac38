"""Switching the active planner at runtime: the bridge's rules and the planners' handover."""

import msgspec
import numpy as np
import pytest
from test_bridge import ENV, pos, skin  # noqa: E402  (the bridge tests' helpers)

from nwr.common import messages as m
from nwr.common.config import PlannerSection, Profile
from nwr.common.robot import RobotModel, load_description
from nwr.common.task import FigureEight, nearest_time
from nwr.services.bridge.cartesian import CartesianLimiter, Limits
from nwr.services.bridge.core import BridgeCore
from nwr.services.bridge.wiring import envelope_for
from nwr.services.planner import claims
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


class Session:
    """Planner a active, b on standby, the bridge's states at 125 Hz and a's status at 20 Hz, 6 s into the task."""

    def __init__(self) -> None:
        self.a = Planner(PlannerSection(name="a", strategy="cartesian"), DESC, MODEL)
        self.b = Planner(PlannerSection(name="b", strategy="uniform"), DESC, MODEL)
        self.t = 0
        for planner in (self.a, self.b):
            planner.on_state(DESC.home.copy(), True, dq=np.zeros(6), owner="a", now_ns=0)
        self.last = self.run(self.a, self.b, 3000)  # the initial return, then the task

    def run(self, active, standby, cycles, phase="TASK", forged=None):
        """``cycles`` control cycles of ``active`` with ``standby`` mirroring; its last command."""
        last = None
        for i in range(cycles):
            self.t += 2 * MS
            cmd = active.step(self.t)
            if cmd is not None:
                last = cmd
            assert standby.step(self.t) is None  # the inactive planner never commands
            if i % 4 == 0:  # robot state at 125 Hz: the arm is where the active planner commanded it
                for planner in (active, standby):
                    planner.on_state(active.q.copy(), True, dq=active.dq.copy(), owner=active.name, now_ns=self.t,
                                     phase=phase)
            if i % 25 == 0:  # planner status at 20 Hz
                standby.on_peer_status(active.status(self.t), self.t)
            if forged is not None and i % 5 == 0:
                standby.on_peer_status(forged, self.t)
        return last

    def switch(self, to, phase="TASK"):
        """The bridge's first state naming ``to`` as the owner."""
        other = self.b if to is self.a else self.a
        q, dq = other.q.copy(), other.dq.copy()
        for planner in (to, other):
            planner.on_state(q, True, dq=dq, owner=to.name, now_ns=self.t, phase=phase)


def forged(name="b", **kw):
    """A status claiming a reflex under way and a saved pose the arm was never at."""
    fields = dict(seq=99, stamp_ns=0, name=name, strategy="uniform", mode="REFLEX", task_time_s=3.0,
                  saved_pose=(DESC.home + np.array([0.6, -0.4, 0.3, 0.5, 0.8, 1.0])).tolist(), active=True)
    fields.update(kw)
    return m.PlannerStatus(**fields)


def test_incoming_planner_continues_the_task_without_a_jump():
    s = Session()
    a, b = s.a, s.b
    assert a.mode == "TASK" and b.mode == "TASK" and not b.active
    assert b.clock.s == pytest.approx(a.clock.s, abs=0.06)
    s.switch(b)  # b learns it is active from the robot state
    assert b.active and b.mode == "TASK"
    assert not a.active and a.step(s.t + 2 * MS) is None
    first = b.step(s.t + 2 * MS)
    step = np.abs(np.asarray(first.q) - np.asarray(s.last.q))
    # The first command of the incoming planner is within what the speed limits allow in two cycles.
    assert np.all(step <= DESC.v_max * 0.004)
    assert first.owner == "b" and first.phase == "TASK"
    assert not a.drain_notes() and not b.drain_notes()  # nothing to report in a normal switch


def test_a_forged_reflex_claim_is_refused_at_the_takeover():
    s = Session()
    a, b = s.a, s.b
    s.switch(b)
    last = s.run(b, a, 200)
    # Just after the bridge's next change (nothing settled yet), b's key claims a reflex and a saved pose.
    s.switch(b)
    a.on_peer_status(forged(), s.t)
    assert a.peer is not None and a.peer.mode == "REFLEX"  # mirrored: the claim may yet be true
    s.switch(a)  # the bridge switched back while following b's task
    assert a.active and a.mode == "TASK" and a.saved is None  # no return to the claimed saved pose
    first = a.step(s.t + 2 * MS)
    assert first.phase == "TASK"
    assert np.all(np.abs(np.asarray(first.q) - np.asarray(last.q)) <= DESC.v_max * 0.004)
    notes = a.drain_notes()
    assert notes and all(code == "claim_refused" and "'b'" in text for _, code, text in notes), notes
    assert any("claimed mode REFLEX" in text for _, _, text in notes)
    assert any("task time 3.000 s" in text for _, _, text in notes)  # the claimed time: not where the arm is


def test_statuses_that_contradict_the_bridge_are_reported_and_not_mirrored():
    s = Session()
    a, b = s.a, s.b
    s.switch(b)
    s.run(b, a, 500, forged=forged())  # b's real statuses, and forged ones in between
    notes = a.drain_notes()
    assert [code for _, code, _ in notes] == ["claim_contradicted"]  # once per claimant and kind every 5 s
    assert "'b'" in notes[0][2] and "saved pose" in notes[0][2]
    assert a.peer is not None and a.peer.mode == "TASK"  # b's real status, never the forged one
    # A third planner claiming to be active while the bridge follows b.
    a.on_peer_status(forged(name="c", saved_pose=None, mode="TASK"), s.t)
    assert [(code, "'c'" in text) for _, code, text in a.drain_notes()] == [("claim_contradicted", True)]
    s.switch(a)
    assert a.mode == "TASK" and not a.drain_notes()


def _reflex_then_takeover(saved_pose):
    """a starts a reflex and dies mid-withdrawal; b takes over with a's status claiming ``saved_pose``."""
    s = Session()
    a, b = s.a, s.b
    pad = DESC.pad("upper_arm_top")
    gains = [0.0] * len(DESC.pads)
    gains[pad.id] = 0.5
    contact = m.Contact(pad=pad.id, name=pad.name, region=pad.region, change_hpa=14.0, level=4, gain=0.5)
    pain = m.SkinPain(seq=1, stamp_ns=s.t, trace=m.Trace(1, 0), model="continuous", level=[1] * len(gains),
                      gain=gains, strongest=contact)
    assert a.on_pain(pain, s.t) is not None
    saved = a.saved.copy()
    s.run(a, b, 100, phase="REFLEX")
    claim = a.status(s.t)
    if saved_pose is not None:
        claim = msgspec.structs.replace(claim, saved_pose=saved_pose(saved))
    b.on_peer_status(claim, s.t)
    b.on_state(a.q.copy(), False, dq=np.zeros(6), owner="b", now_ns=s.t + 2 * MS, phase="REFLEX", ok=False)
    return b, saved


def test_a_takeover_mid_reflex_returns_where_it_saw_the_arm_leave_the_task():
    # It holds first (planner.sustained_contact = "hold"): the touch may still be there; nothing is felt, so the
    # return begins at its first check.
    b, saved = _reflex_then_takeover(None)
    assert b.mode == "HOLDING" and np.allclose(b.saved, saved, atol=1e-12)  # the claim, confirmed
    assert not b.drain_notes()
    b, saved = _reflex_then_takeover(lambda q: (q + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])).tolist())
    assert b.mode == "HOLDING" and claims.distance(b.saved, saved) < 0.02  # where it saw the arm leave the task
    for _ in range(20):
        b.step(b.hold_since_ns + 25 * MS)
    assert b.mode == "RETURNING"
    notes = b.drain_notes()
    assert [code for _, code, _ in notes] == ["claim_refused"] and "saved pose refused" in notes[0][2]


def test_the_task_time_at_a_pose_tells_the_eight_s_crossing_apart():
    task = FigureEight(PlannerSection().task, DESC)
    period = PlannerSection().task.period_s
    for s0 in (0.0, period / 2, 1.3, 7.9):  # home twice a period: the direction of motion tells which
        q, dq = task.position(s0), task.velocity(s0)
        s, off = nearest_time(task, q, dq, near_s=100.0)
        assert off < 1e-4 and abs((s - s0 + period / 2) % period - period / 2) < 0.01
        assert abs(s - 100.0) <= period / 2  # in the period nearest the clock


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


def ur10e_bridge():
    """The UR10e's bridge with the profile's Cartesian limits, planners a (active) and b alive."""
    profile = Profile()
    env, q0, n_pads = envelope_for(profile)
    limiter = CartesianLimiter(MODEL, Limits.of(profile.bridge.limits, MODEL, "bridge.limits"), a_max=env.a_max,
                               j_max=env.j_max)
    c = BridgeCore(env, q0, 0, active="a", n_pads=n_pads, limiter=limiter)
    for name in ("a", "b"):
        c.on_planner_token(name, True, 0)
    return c, q0, n_pads, limiter


def test_a_handover_s_first_motion_goes_no_faster_and_nowhere_the_arm_has_not_been():
    c, q0, n_pads, limiter = ur10e_bridge()
    t, q, seq = 0, q0.copy(), 0

    def cycle(owner, velocity):
        nonlocal t, q, seq
        t += 2 * MS
        q = q + np.asarray(velocity) * 0.002
        seq += 1
        c.on_skin(skin(pads=n_pads), t)
        verdict = c.on_command(pos(q, owner=owner, seq=seq, stamp=t), t)
        c.step(t)
        return verdict

    slow = np.zeros(6)
    slow[0] = 0.1  # a's stream: the base at 0.1 rad/s, for 1 s
    for _ in range(500):
        assert cycle("a", slow).accepted
    peak = c.tracker.stream_peak
    assert c.request_switch(request("b", stamp=t), t)
    seq = 0
    fast = slow.copy()
    fast[5] = 1.0  # b's stream: a's, plus wrist 3 at 1 rad/s, to where the arm never was
    speeds, refused = [], []
    for _ in range(300):
        verdict = cycle("b", fast)
        speeds.append(float(limiter.speeds(c.tracker.q, c.tracker.dq).max()))
        refused += [e for e in c.drain_events() if e.code == "handover_refused"]
        if not verdict.accepted:
            break
    # No faster than a's stream moved the arm; refused before wrist 3 left the range it covered by 0.1 rad.
    assert max(speeds) <= peak * 1.001
    assert refused and "wrist_3" in refused[0].message and "'b'" in refused[0].message
    assert abs(c.tracker.q[5] - q0[5]) <= 0.1 + 1e-9


def test_a_reflex_right_after_a_switch_is_not_slowed_and_ends_the_handover():
    c, q0, n_pads, limiter = ur10e_bridge()
    c.on_skin(skin(pads=n_pads), 0)
    assert c.on_command(pos(q0, owner="a", seq=1, stamp=2 * MS), 2 * MS).accepted
    c.step(2 * MS)
    assert c.request_switch(request("b", stamp=2 * MS), 2 * MS) and c.joining
    target = q0.copy()
    target[2] += 0.09  # the elbow withdraws toward where the arm never was
    assert c.on_command(pos(target, owner="b", seq=1, phase="REFLEX", reflex=1, stamp=4 * MS), 4 * MS).accepted
    assert not c.joining and not c.tracker.rejoining  # a withdrawal is the planner's own: no handover cap
    c.step(4 * MS)
    back = target.copy()
    back[2] += 0.05  # its return, from outside the range covered before the switch
    verdict = c.on_command(pos(back, owner="b", seq=2, phase="RETURNING", reflex=1, stamp=6 * MS), 6 * MS)
    assert verdict.accepted and not [e for e in c.drain_events() if e.code == "handover_refused"]


def test_a_mode_just_changed_is_not_a_contradiction_until_the_bridge_has_had_time_to_show_it():
    """A planner's status goes out the moment its mode changes (a task paused for a touch below a reflex's
    level: HOLDING), the bridge's state with the new phase up to a state period later: in between the two
    disagree honestly. Held past the settling time, the disagreement is a contradiction."""
    s = Session()
    a, b = s.a, s.b
    real = a.status(s.t)
    holding = msgspec.structs.replace(real, mode="HOLDING", saved_pose=a.q.tolist())
    b.on_peer_status(holding, s.t)  # the bridge still shows TASK, as it has for seconds
    assert not b.drain_notes() and b.peer is not None and b.peer.mode == "HOLDING"
    t = s.t + round(claims.SETTLE_S * 1e9) + 2 * MS  # still TASK at the bridge after the settling time
    b.on_state(a.q.copy(), True, dq=np.zeros(6), owner="a", now_ns=t, phase="TASK")
    b.on_peer_status(msgspec.structs.replace(holding, stamp_ns=t), t)
    notes = b.drain_notes()
    assert [code for _, code, _ in notes] == ["claim_contradicted"] and "mode HOLDING" in notes[0][2]
