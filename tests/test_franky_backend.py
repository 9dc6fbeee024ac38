"""The franky backend (services/bridge/backends/franky.py) against a test double of its link to franky.

franky itself (libfranka against franky-sim, the real protocol) is driven by
tests/test_franky_e2e.py; here every fault the controller can report is
injected: Franka's reflex and its recovery, the user stop, a robot in no mode
to move, a refused motion, a frozen state stream, a lost connection.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.services.bridge.backends.franky import (
    FrankyBackend,
    LinkLost,
    MotionRefused,
    Report,
    RobotConnectionError,
    Settings,
)
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.wiring import envelope_for
from nwr.services.profile import load_profile

HOME = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])


def fr3_profile() -> Profile:
    return load_profile("fr3")


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class FakeLink:
    """What the backend calls on franky, recorded; the controller's state and faults set by the test."""

    made: list[FakeLink] = []
    fail_next = 0  # connections to refuse (RobotConnectionError) before one succeeds

    def __init__(self, host: str, settings: Settings) -> None:
        if FakeLink.fail_next:
            FakeLink.fail_next -= 1
            raise RobotConnectionError(f"cannot connect to the Franka controller at {host} (refused)")
        FakeLink.made.append(self)
        self.q = HOME.copy()
        self.dq = np.zeros(7)
        self.tau_ext = np.array([0.1, -0.2, 0.0, 1.5, 0.0, 0.0, 0.0])
        self.time_s = 1.0
        self.mode = "Idle"
        self.errors = ""
        self.calls: list[tuple] = []
        self.refuse: str = ""  # the next start() raises this
        self.ended: str = ""  # the running motion ended with this error
        self.lost = False
        self.recover_ok = True
        self.running = False

    def read(self) -> Report:
        if self.lost:
            raise LinkLost("NetworkException: libfranka: UDP receive: Timeout")
        return Report(self.q.copy(), self.dq.copy(), self.tau_ext.copy(), self.time_s, self.mode, self.errors)

    def tick(self, dt: float = 0.002) -> None:
        self.time_s += dt

    def motion_error(self) -> str:
        if self.ended:
            ended, self.ended, self.running = self.ended, "", False
            return ended
        return ""

    def start(self, q: np.ndarray) -> None:
        if self.refuse:
            raise MotionRefused(self.refuse)
        self.calls.append(("start", q.copy()))
        self.running = True
        self.mode = "Move"

    def target(self, q: np.ndarray, dq: np.ndarray) -> None:
        self.calls.append(("target", q.copy(), dq.copy()))

    def recover(self) -> bool:
        self.calls.append(("recover",))
        if self.recover_ok:
            self.mode, self.errors = "Idle", ""
        return self.recover_ok

    def stop(self) -> None:
        self.calls.append(("stop",))
        self.running = False


@pytest.fixture
def arm() -> tuple[FrankyBackend, Clock]:
    FakeLink.made.clear()
    FakeLink.fail_next = 0
    env, _, _ = envelope_for(fr3_profile())
    clock = Clock()
    backend = FrankyBackend(env, 0.002, "127.0.0.1", Settings(), factory=FakeLink, clock=clock)
    backend.connect()
    return backend, clock


def link(backend: FrankyBackend) -> FakeLink:
    assert isinstance(backend.link, FakeLink)
    return backend.link


def sp(mode: str, q: np.ndarray, dq: np.ndarray | None = None) -> Setpoint:
    return Setpoint(mode, q, np.zeros(7) if dq is None else dq, np.zeros(7), 0.002)  # type: ignore[arg-type]


def test_it_streams_each_setpoint_as_the_reference_of_one_motion_started_at_once(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    backend.send_action(sp("hold", HOME))  # the first cycle holds: the motion starts there, tracking the pose
    q1 = HOME + 0.001
    backend.send_action(sp("position", q1, np.full(7, 0.5)))
    q2 = q1 + 0.001
    backend.send_action(sp("velocity", q2, np.full(7, 0.5)))
    backend.send_action(sp("hold", q2, np.full(7, 0.3)))
    assert [c[0] for c in fake.calls] == ["start", "target", "target", "target", "target"]
    assert np.array_equal(fake.calls[0][1], HOME)  # the motion starts where the first setpoint is
    assert np.array_equal(fake.calls[1][2], np.zeros(7))
    assert np.array_equal(fake.calls[3][1], q2) and np.array_equal(fake.calls[3][2], np.full(7, 0.5))
    assert np.array_equal(fake.calls[4][2], np.zeros(7))  # a hold is a reference at rest
    backend.disconnect()
    assert fake.calls[-1] == ("stop",)
    backend.disconnect()  # twice is safe


def test_the_observation_carries_the_external_torques_and_the_controllers_clock(arm) -> None:
    backend, clock = arm
    obs = backend.get_observation()
    assert obs.fault is None and obs.stamp_s == 1.0
    assert obs.tau_ext is not None and obs.tau_ext[3] == 1.5


def test_franka_reflex_is_reported_with_its_errors_and_recovered_only_after_the_arm_has_rested(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    backend.send_action(sp("position", HOME))
    fake.mode, fake.errors, fake.ended = "Reflex", "[joint_reflex]", "ControlException: libfranka: joint_reflex"
    fake.dq[:] = 0.2  # still moving after the reflex
    obs = backend.get_observation()
    assert obs.fault == "robot_reflex" and "joint_reflex" in obs.detail and "error recovery" in obs.detail
    backend.send_action(sp("hold", HOME))  # the core sends nothing in a fault; even so, the backend would not
    assert not backend.streaming and fake.calls.count(("recover",)) == 0 and len(fake.calls) == 2
    for _ in range(3):
        clock.t += 1.0
        fake.tick()
        assert backend.get_observation().fault == "robot_reflex"
    assert ("recover",) not in fake.calls  # never while the arm moves
    fake.dq[:] = 0.0
    fake.tick()
    assert backend.get_observation().fault == "robot_reflex"  # at rest from now
    clock.t += 0.5
    fake.tick()
    assert backend.get_observation().fault == "robot_reflex"  # not yet recover_rest_s
    clock.t += 0.6
    fake.tick()
    assert backend.get_observation().fault is None
    assert fake.calls[-1] == ("recover",) and backend.recoveries == 1
    backend.send_action(sp("position", HOME))
    assert fake.calls[-2][0] == "start"  # a fresh motion after the fault


def test_a_failed_recovery_is_tried_again_with_backoff(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    fake.mode, fake.recover_ok = "Reflex", False
    backend.get_observation()
    clock.t += 1.1
    fake.tick()
    assert backend.get_observation().fault == "robot_reflex"
    clock.t += 0.1
    fake.tick()
    backend.get_observation()
    assert fake.calls.count(("recover",)) == 1  # backoff: 0.5 s
    clock.t += 0.5
    fake.tick()
    backend.get_observation()
    assert fake.calls.count(("recover",)) == 2


@pytest.mark.parametrize("mode, status, words", [
    ("UserStopped", "emergency_stop", "user stop"),
    ("Guiding", "motion_refused", "mode Guiding"),
    ("Other", "motion_refused", "mode Other"),
])
def test_a_robot_in_no_mode_to_move_is_a_fault_and_nothing_is_sent(arm, mode: str, status: str, words: str) -> None:
    backend, clock = arm
    fake = link(backend)
    fake.mode = mode
    obs = backend.get_observation()
    assert obs.fault == status and words in obs.detail
    fake.mode = "Idle"
    fake.tick()
    assert backend.get_observation().fault is None


def test_a_refused_motion_is_motion_refused_until_its_retry(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    fake.refuse = "CommandException: libfranka: Move command rejected: command not possible in the current mode"
    backend.send_action(sp("position", HOME))
    obs = backend.get_observation()
    assert obs.fault == "motion_refused" and "Move command rejected" in obs.detail
    backend.send_action(sp("position", HOME))
    assert fake.calls == []  # nothing until the retry
    fake.refuse = ""
    clock.t += 0.6
    fake.tick()
    assert backend.get_observation().fault is None
    backend.send_action(sp("position", HOME))
    assert fake.calls[0][0] == "start"


def test_a_motion_the_controller_ends_outside_a_reflex_is_motion_refused(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    backend.send_action(sp("position", HOME))
    fake.ended, fake.mode = "the motion ended", "Idle"
    obs = backend.get_observation()
    assert obs.fault == "motion_refused" and "ended the motion" in obs.detail


def test_a_frozen_state_stream_is_a_lost_connection_after_state_timeout(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    backend.get_observation()
    clock.t += 0.09
    assert backend.get_observation().fault is None
    clock.t += 0.02
    obs = backend.get_observation()
    assert obs.fault == "disconnected" and "no state from the controller for 110 ms" in obs.detail
    fake.tick()
    assert backend.get_observation().fault is None  # it flows again


def test_a_lost_connection_reconnects_with_backoff_reporting_the_last_pose(arm) -> None:
    backend, clock = arm
    fake = link(backend)
    backend.send_action(sp("position", HOME + 0.01))
    fake.lost = True
    FakeLink.fail_next = 1
    obs = backend.get_observation()
    assert obs.fault == "disconnected" and "Timeout" in obs.detail
    assert np.array_equal(obs.q, HOME) and not obs.dq.any()
    obs = backend.get_observation()  # the first attempt, refused
    assert obs.fault == "disconnected" and "reconnection 1 failed" in obs.detail
    clock.t += 0.2
    assert backend.get_observation().fault == "disconnected" and len(FakeLink.made) == 1  # backoff 0.5 s
    clock.t += 0.4
    assert backend.get_observation().fault is None and len(FakeLink.made) == 2
    backend.send_action(sp("position", HOME))
    assert link(backend).calls[0][0] == "start"  # a fresh motion on the fresh link


def test_the_bridge_publishes_the_external_torques_and_the_reflex_and_restarts_after_recovery() -> None:
    from nwr.common.clock import ManualClock
    from nwr.common.journal import Untracked
    from nwr.services.bridge.wiring import BridgeWiring

    FakeLink.made.clear()
    FakeLink.fail_next = 0
    profile = fr3_profile()
    env, _, _ = envelope_for(profile)
    clock = ManualClock()
    clock.t_ns = 10**9
    backend = FrankyBackend(env, 0.002, "127.0.0.1", Settings(), factory=FakeLink,
                            clock=lambda: clock.t_ns / 1e9)
    backend.connect()
    states: list[m.RobotState] = []
    wiring = BridgeWiring(profile, journal=Untracked(clock), out=lambda k, msg: states.append(msg),
                          backend=backend, diag=lambda *a, **k: None)
    fake = link(backend)
    for _ in range(30):
        fake.tick()
        wiring.tick()
        clock.t_ns += 2_000_000
    assert states and states[-1].tau_ext == fake.tau_ext.tolist()
    fake.mode, fake.errors = "Reflex", "[cartesian_reflex]"
    for _ in range(30):
        fake.tick()
        wiring.tick()
        clock.t_ns += 2_000_000
    assert states[-1].status == "robot_reflex" and "cartesian_reflex" in states[-1].detail
    for _ in range(600):
        fake.tick()
        wiring.tick()
        clock.t_ns += 2_000_000
    assert ("recover",) in fake.calls and states[-1].status in ("idle", "stale_skin")


def test_the_backend_needs_a_seven_joint_robot_and_an_address() -> None:
    with pytest.raises(ConfigError, match="7-joint"):
        _ur_profile_with_franky()
    env, _, _ = envelope_for(fr3_profile())
    with pytest.raises(RobotConnectionError, match="--robot-ip"):
        FrankyBackend(env, 0.002, "", Settings(), factory=FakeLink)


def _ur_profile_with_franky() -> None:
    from nwr.common.robot import load_description
    from nwr.services.profile import check_plugins

    profile = Profile()
    profile.bridge.backend = "franky"
    check_plugins(profile, load_description(None))


def test_franky_is_not_imported_by_the_bridge() -> None:
    probe = subprocess.run([sys.executable, "-c", "import sys, nwr.services.bridge.main, "
                            "nwr.services.bridge.backends.franky; print('franky' in sys.modules)"],
                           capture_output=True, text=True, check=True)
    assert probe.stdout.strip() == "False"
