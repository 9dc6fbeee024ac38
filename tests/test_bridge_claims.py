"""The robot's reported joint state is a claim: the bridge's StateCheck and what the supervisor does with it (pure)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from test_bridge import DT, JOINTS, MS, lim, pos, skin, vel

from nwr.common import messages as m
from nwr.services.bridge.checks import StateBounds, StateCheck
from nwr.services.bridge.core import CLEAR_S, BridgeCore

V = np.array([1.0, 2.0])
A = np.array([10.0, 10.0])


def check(tau_s: float = 0.0, **bounds: float) -> StateCheck:
    return StateCheck(JOINTS, V, A, np.zeros(2), 0, bounds=StateBounds(**bounds), tau_s=tau_s)


class Follower:
    """An arm that follows position setpoints with a first-order lag and velocity setpoints exactly (as the
    controller emulator's servoj / speedj do), plus an offset in its reports."""

    def __init__(self, tau_s: float) -> None:
        self.tau_s = tau_s
        self.q = np.zeros(2)
        self.dq = np.zeros(2)

    def step(self, mode: str, q: np.ndarray, dq: np.ndarray, h: float) -> None:
        before = self.q.copy()
        if mode == "velocity":
            self.q = self.q + dq * h
        elif self.tau_s > 0:
            self.q = self.q + (q - self.q) * (1.0 - math.exp(-h / self.tau_s))
        else:
            self.q = q.copy()
        self.dq = (self.q - before) / h


def drive(sc: StateCheck, arm: Follower, n: int, command, offset=lambda k: np.zeros(2), t0: int = 0):
    """n cycles: the arm's report checked, then a command sent and followed; the first reason, with its cycle."""
    t = t0
    for k in range(n):
        t += 2 * MS
        why = sc.observe(arm.q + offset(k), arm.dq, t)
        if why is not None:
            return k, why
        mode, q, dq = command(k)
        if mode == "velocity":
            sc.command(mode, np.zeros(2), dq * DT, dq, t)  # the displacement commanded over the cycle
        else:
            sc.command(mode, q, q, dq, t)
        arm.step(mode, q, dq, DT)
    return None


def sine(k: int) -> tuple[str, np.ndarray, np.ndarray]:
    w = 2.0  # from rest, as the planner's streams start
    c, s = 1.0 - math.cos(w * k * DT), math.sin(w * k * DT)
    return "position", np.array([0.4 * c, -0.3 * c]), np.array([0.8 * s, -0.6 * s])


def test_a_lagging_arm_that_follows_its_commands_is_believed():
    assert drive(check(tau_s=0.1), Follower(0.1), 3000, sine) is None
    assert drive(check(), Follower(0.0), 3000, sine) is None


def test_velocity_then_position_streams_are_believed():
    arm = Follower(0.1)
    sc = check(tau_s=0.1)
    ramp = lambda k: min(1.0, k / 100) * min(1.0, max(0.0, (500 - k) / 100))  # noqa: E731

    def command(k: int):
        if k < 500:  # a withdrawal: ramped in and out
            return "velocity", np.zeros(2), np.array([0.5, -0.4]) * ramp(k)
        return "position", sc.commanded.copy(), np.zeros(2)  # then held where it went

    assert drive(sc, arm, 1500, command) is None


def test_an_offset_report_is_a_jump_naming_the_joint_and_the_size():
    got = drive(check(tau_s=0.1), Follower(0.1), 2000, sine,
                offset=lambda k: np.array([0.0, 0.3 if k >= 700 else 0.0]))
    assert got is not None
    k, why = got
    assert k == 700
    assert "joint b jumped 0.29" in why


def test_a_creeping_offset_is_a_following_error():
    # 0.1 mrad per cycle (0.05 rad/s): never a jump; caught by the following error well before 0.08 rad.
    got = drive(check(tau_s=0.1), Follower(0.1), 3000, sine,
                offset=lambda k: np.array([1e-4 * max(0, k - 500), 0.0]))
    assert got is not None
    k, why = got
    assert "joint a reported" in why and "from where the bridge commanded it" in why
    assert 1e-4 * (k - 500) < 0.05 + 0.05 * 0.8 + 0.01


def test_a_frozen_report_is_caught_within_the_frozen_time_while_the_commands_move():
    sc = check()
    arm = Follower(0.0)
    assert drive(sc, arm, 100, sine) is None
    frozen_q, frozen_dq = arm.q.copy(), arm.dq.copy()
    t = 100 * 2 * MS
    for k in range(100, 200):
        t += 2 * MS
        why = sc.observe(frozen_q, frozen_dq, t)
        if why is not None:
            break
        mode, q, dq = sine(k)
        sc.command(mode, q, q, dq, t)
    assert why is not None and "frozen" in why
    assert (k - 100) * DT <= StateBounds().frozen_s + 2 * DT


def test_a_controller_clock_that_stands_still_is_caught_while_the_arm_is_commanded_nearly_still():
    """Reports that stop coming (the stamp stands still) while the commands barely move: the frozen check cannot
    tell, the controller's clock can: caught after STILL_CLOCK_FACTOR * frozen_s, never before."""
    from nwr.services.bridge.checks import STILL_CLOCK_FACTOR
    sc = check()
    q, t, stamp = np.zeros(2), 0, 0.0
    for _ in range(200):  # a still arm whose reports keep coming: believed, identical values and all
        t += 2 * MS
        stamp += DT
        assert sc.observe(q, np.zeros(2), t, stamp) is None
        sc.command("position", q, q, np.zeros(2), t)
    limit = STILL_CLOCK_FACTOR * StateBounds().frozen_s
    for k in range(1, 1000):  # the stream stops: the same report, its stamp with it
        t += 2 * MS
        why = sc.observe(q, np.zeros(2), t, stamp)
        target = q + np.array([1e-6 * k, 0.0])  # 0.5 mrad/s: never the frozen check's 1 mrad in the limit
        sc.command("position", target, target, np.array([5e-4, 0.0]), t)
        if why is not None:
            break
    assert why is not None and "clock has stood" in why, why
    assert limit - 2 * DT <= k * DT <= limit + 2 * DT


def test_a_bridge_that_was_not_looking_does_not_blame_the_controllers_clock():
    """The bridge's own process stopped for 1.5 s (SIGSTOP, a hang): its first report after is the one from before,
    the stamp unchanged; that is no stopped controller. A clock that still stands from then on is caught, counted
    from the bridge's return."""
    from nwr.services.bridge.checks import STILL_CLOCK_FACTOR
    sc = check()
    q, t, stamp = np.zeros(2), 0, 0.0
    for _ in range(200):
        t += 2 * MS
        stamp += DT
        assert sc.observe(q, np.zeros(2), t, stamp) is None
        sc.command("position", q, q, np.zeros(2), t)
    t += 1500 * MS  # the bridge stopped; nothing observed, nothing commanded
    back = t
    limit = STILL_CLOCK_FACTOR * StateBounds().frozen_s
    why = None
    while why is None and t - back < 2 * limit * 1e9:
        why = sc.observe(q, np.zeros(2), t, stamp)
        sc.command("position", q, q, np.zeros(2), t)
        t += 2 * MS
    assert why is not None and "clock has stood" in why, why
    assert limit - 2 * DT <= (t - back) / 1e9 <= limit + 2 * DT


def test_reports_that_arrive_late_then_in_a_burst_are_no_jump():
    """A client starved for 40 ms sees the same report again and again, then the newest: not a jump."""
    sc = check()
    q, t = np.zeros(2), 0
    stale = None
    for k in range(300):
        t += 2 * MS
        q = q + np.array([0.9, 0.0]) * DT  # 0.9 rad/s, v_max 1
        dq = np.array([0.9, 0.0])  # moving from the first report on
        late = 100 <= k < 120
        if late and stale is None:
            stale = (q.copy(), dq.copy())
        report = stale if late and stale is not None else (q, dq)
        if not late:
            stale = None
        assert sc.observe(*report, t) is None, k
        sc.command("position", q, q, dq, t)


def test_the_controllers_timestamps_time_the_reports():
    sc = check()
    assert sc.observe(np.zeros(2), np.zeros(2), 2 * MS, stamp_s=10.0) is None
    # 0.02 rad in 2 ms of the bridge's clock, but 40 ms of the controller's: possible
    assert sc.observe(np.array([0.02, 0.0]), np.zeros(2), 4 * MS, stamp_s=10.04) is None
    # 0.05 rad in 2 ms of the controller's: not
    why = sc.observe(np.array([0.07, 0.0]), np.zeros(2), 6 * MS, stamp_s=10.042)
    assert why is not None and "joint a jumped 0.0500 rad in 2.0 ms" in why


def test_a_report_unchanged_at_rest_is_no_fault():
    sc = check()
    for k in range(1000):
        t = (k + 1) * 2 * MS
        assert sc.observe(np.zeros(2), np.zeros(2), t) is None
        sc.command("hold", np.zeros(2), np.zeros(2), np.zeros(2), t)


@pytest.mark.parametrize("q, dq", [([math.nan, 0.0], [0.0, 0.0]), ([0.0, 0.0], [0.0, math.inf])])
def test_non_finite_reports_are_not_believed(q, dq):
    why = check().observe(np.array(q), np.array(dq), 2 * MS)
    assert why is not None and "non-finite" in why


def test_a_speed_the_arm_cannot_reach_in_one_cycle_is_not_believed():
    sc = check()
    assert sc.observe(np.zeros(2), np.zeros(2), 2 * MS) is None
    why = sc.observe(np.zeros(2), np.array([0.0, 1.0]), 4 * MS)  # 500 rad/s^2 for a_max 10
    assert why is not None and "joint b speed jumped" in why


# --------------------------------------------------------------------------- the supervisor


class Arm:
    """The core's setpoints, followed exactly (the simulated arm), reported with ``offset``."""

    def __init__(self, c: BridgeCore) -> None:
        self.c = c
        self.q = c.tracker.q.copy()
        self.dq = np.zeros(2)
        self.t = 0
        self.offset = np.zeros(2)
        self.freeze = False
        self.reported = (self.q.copy(), self.dq.copy())
        self.modes: list[str] = []

    def cycles(self, n: int, command=None) -> None:
        for k in range(n):
            self.t += 2 * MS
            if (self.t // MS) % 40 < 2:
                self.c.on_skin(skin(), self.t)
            if not self.freeze:
                self.reported = (self.q + self.offset, self.dq.copy())
            self.c.observe(*self.reported, self.t)
            if command is not None:
                self.c.on_command(command(k, self.t), self.t)
            sp = self.c.step(self.t)
            self.modes.append(sp.mode)
            if self.c.fault is None:
                self.q, self.dq = sp.q.copy(), (sp.dq.copy() if sp.mode != "hold" else np.zeros(2))


def supervised(**kw) -> tuple[BridgeCore, Arm]:
    env = lim(q_min=[-3.0, -3.0], q_max=[3.0, 3.0])
    c = BridgeCore(env, np.zeros(2), 0, active="p", n_pads=3, **kw)
    c.on_planner_alive(True, 0)
    c.on_skin(skin(), 0)
    return c, Arm(c)


def test_the_simulated_arm_is_always_believed():
    c, arm = supervised()
    arm.cycles(300, lambda k, t: vel([0.4, -0.6], seq=k, stamp=t))
    start = arm.q.copy()
    arm.cycles(300, lambda k, t: pos(start + [0.0002 * k, 0.0], seq=300 + k, stamp=t))
    assert c.status == "ok" and not c.implausible
    assert "state_implausible" not in [e.code for e in c.drain_events()]


def test_a_misreported_pose_in_a_velocity_reflex_stops_the_arm_and_is_never_adopted():
    c, arm = supervised()
    reflex = lambda k, t: vel([0.0, 0.5], seq=k, stamp=t)  # noqa: E731
    arm.cycles(100, reflex)
    assert c.status == "ok"
    commanded = c.tracker.q.copy()
    arm.offset = np.array([0.0, 0.3])
    arm.cycles(1, reflex)
    assert c.status == "state_implausible" and re.search(r"joint b jumped 0\.(29|30)", c.detail)
    assert abs(c.tracker.q[1] - commanded[1]) < 0.01  # the false pose was not taken as the bridge's own
    assert arm.modes[-1] == "hold"  # the backend's own controlled stop
    events = c.drain_events()
    assert [e.level for e in events if e.code == "state_implausible"] == ["error"]
    state = c.state(0, arm.t, arm.q, arm.dq, "sim")
    assert state.status == "state_implausible" and "joint b" in state.detail
    # commands are not followed while the reports are not believed
    arm.cycles(50, lambda k, t: vel([0.0, 0.5], seq=200 + k, stamp=t))
    assert c.status == "state_implausible" and set(arm.modes[-50:]) == {"hold"}
    assert "command_ignored" in [e.code for e in c.drain_events()]


def test_a_misreported_pose_in_a_position_stream_stops_the_arm_and_clears_once_the_reports_agree_again():
    c, arm = supervised()
    task = lambda k, t: pos([min(0.0004 * k, 0.05), 0.0], seq=k, stamp=t)  # noqa: E731
    arm.cycles(50, task)
    arm.offset = np.array([0.08, 0.0])
    arm.cycles(1, task)
    assert c.status == "state_implausible" and "joint a" in c.detail
    # the offset persists: the fault stays, however long
    arm.cycles(round(2 * CLEAR_S / DT))
    assert c.status == "state_implausible"
    # the reports agree again: believed after CLEAR_S at rest where the arm was stopped
    arm.offset = np.zeros(2)
    arm.cycles(round(CLEAR_S / DT) - 5)
    assert c.status == "state_implausible"
    arm.cycles(10)
    assert c.status == "idle" and not c.implausible
    assert "state_plausible" in [e.code for e in c.drain_events()]
    arm.cycles(50, lambda k, t: pos(arm.q.tolist(), seq=1000 + k, stamp=t))
    assert c.status == "ok"


def test_a_frozen_report_while_the_arm_is_commanded_to_move_stops_it_within_a_few_cycles():
    c, arm = supervised()
    reflex = lambda k, t: vel([0.3, 0.0], seq=k, stamp=t)  # noqa: E731
    arm.cycles(100, reflex)
    arm.freeze = True
    for k in range(100):
        arm.cycles(1, lambda _k, t, k=k: vel([0.3, 0.0], seq=100 + k, stamp=t))
        if c.status != "ok":
            break
    assert c.status == "state_implausible" and "frozen" in c.detail
    assert k * DT <= StateBounds().frozen_s + 2 * DT


def test_a_fault_of_the_controller_resets_the_check():
    c, arm = supervised()
    arm.cycles(50, lambda k, t: vel([0.3, 0.0], seq=k, stamp=t))
    c.on_fault("protective_stop", "injected", arm.q, arm.t)
    arm.q, arm.dq = arm.q + 0.01, np.zeros(2)  # the controller's own stop moved the arm, and stopped it
    c.on_fault(None, "", arm.q, arm.t + 2 * MS)
    arm.cycles(20)
    assert not c.implausible


def test_the_bounds_come_from_the_profile():
    from nwr.common.config import Profile
    from nwr.services.bridge.wiring import state_bounds

    profile = Profile()
    profile.bridge.following_error_rad = 0.03
    profile.bridge.report_frozen_s = 0.02
    b = state_bounds(profile)
    assert b.error_rad == 0.03 and b.frozen_s == 0.02 and b.lag_s == 0.05 and b.jump_rad == 0.01


def test_status_is_a_robot_status():
    import typing

    assert "state_implausible" in typing.get_args(m.RobotStatus)



# --------------------------------------------------------------------------- never silent, never non-finite


def _wiring(backend_factory):
    from nwr.common.clock import ManualClock
    from nwr.common.config import Profile
    from nwr.common.journal import Untracked
    from nwr.services.bridge.wiring import BridgeWiring, envelope_for

    profile = Profile()
    env, q0, _ = envelope_for(profile)
    backend = backend_factory(env, 1.0 / profile.bridge.rate_hz, q0)
    clock = ManualClock()
    clock.t_ns = 10**9
    states: list[m.RobotState] = []
    reports: list[tuple[str, str]] = []
    wiring = BridgeWiring(profile, journal=Untracked(clock), out=lambda k, msg: states.append(msg), backend=backend,
                          diag=lambda level, code, message, every_s=1.0: reports.append((code, message)))
    return wiring, backend, clock, states, reports


def test_a_non_finite_report_is_a_fault_and_never_published():
    from nwr.services.bridge.backend import Observation, SimBackend

    class Hostile(SimBackend):
        name = "hostile"
        nan = False

        def get_observation(self) -> Observation:
            dq = self.dq.copy()
            if self.nan:
                dq[3] = math.nan
            return Observation(self.q.copy(), dq)

    wiring, backend, clock, states, reports = _wiring(Hostile)
    for _ in range(20):
        wiring.tick()
        clock.t_ns += 2 * MS
    backend.nan = True
    for _ in range(20):
        wiring.tick()
        clock.t_ns += 2 * MS
    assert wiring.core.status == "state_implausible" and "non-finite" in wiring.core.detail
    assert any(code == "state_implausible" for code, _ in reports)
    assert states and all(np.isfinite(s.q).all() and np.isfinite(s.dq).all() for s in states)
    assert states[-1].pose_stale and states[-1].status == "state_implausible"
    import msgspec

    msgspec.msgpack.Decoder(m.RobotState).decode(msgspec.msgpack.encode(states[-1]))  # consumers can decode it


def test_while_disconnected_the_state_goes_on_at_its_rate_with_the_last_pose_marked_stale():
    from nwr.services.bridge.backend import Observation, SimBackend

    class Unreachable(SimBackend):
        name = "unreachable"
        down = False

        def get_observation(self) -> Observation:
            if self.down:
                return Observation(self.q.copy(), np.zeros_like(self.q), "disconnected", "reconnecting")
            return Observation(self.q.copy(), self.dq.copy())

    wiring, backend, clock, states, _ = _wiring(Unreachable)
    backend.down = True
    for _ in range(100):  # 0.2 s at 500 Hz: 10 states at 50 Hz
        wiring.tick()
        clock.t_ns += 2 * MS
    down = [s for s in states if s.status == "disconnected"]
    assert len(down) >= 9 and all(s.pose_stale for s in down)
