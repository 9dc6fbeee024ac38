"""The ur_rtde backend against a test double of RTDEControlInterface / RTDEReceiveInterface."""

from __future__ import annotations

import math
import subprocess
import sys
import time

import numpy as np
import pytest

from nwr.common.config import Profile
from nwr.services.bridge.backends.ur_rtde import KICKS_PER_PERIOD, RobotConnectionError, URRtdeBackend
from nwr.services.bridge.core import Setpoint
from nwr.services.bridge.wiring import envelope_for

DT = 0.002


class FakeRobot:
    """Shared state of the fake controller: what was called, and injectable faults."""

    def __init__(self, q) -> None:
        self.q = list(q)
        self.calls: list[tuple] = []
        self.connected = True
        self.protective = False
        self.estop = False
        self.program = True
        self.refuse_connect = False
        self.refuse_watchdog = False


class FakeControl:
    def __init__(self, robot: FakeRobot) -> None:
        self.r = robot

    def _call(self, name, *args):
        if not self.r.connected and name not in ("disconnect", "isConnected", "reconnect"):
            raise RuntimeError(f"{name}: not connected")
        self.r.calls.append((name, *args))

    # ur_rtde's servoJ takes positional arguments only: so does the double.
    def servoJ(self, q, speed, acceleration, time, lookahead_time, gain, /):
        self._call("servoJ", list(q), speed, acceleration, time, lookahead_time, gain)
        self.r.q = list(q)
        return self.r.program

    def speedJ(self, qd, acceleration, time, /):
        self._call("speedJ", list(qd), acceleration, time)
        return self.r.program

    def servoStop(self, a, /):
        self._call("servoStop", a)
        return True

    def speedStop(self, a, /):
        self._call("speedStop", a)
        return True

    def setWatchdog(self, min_frequency=10.0, /):
        self._call("setWatchdog", min_frequency)
        return not self.r.refuse_watchdog

    def kickWatchdog(self):
        self._call("kickWatchdog")
        return True

    def initPeriod(self):
        self._call("initPeriod")
        return 0

    def waitPeriod(self, t, /):
        self._call("waitPeriod", t)

    def isConnected(self):
        return self.r.connected

    def isProgramRunning(self):
        self._call("isProgramRunning")
        return self.r.program

    def reuploadScript(self):
        self._call("reuploadScript")
        self.r.program = True
        return True

    def reconnect(self):
        self.r.calls.append(("reconnect",))
        return not self.r.refuse_connect and self.r.connected

    def stopScript(self):
        self._call("stopScript")

    def disconnect(self):
        self.r.calls.append(("disconnect",))


class FakeReceive:
    def __init__(self, robot: FakeRobot) -> None:
        self.r = robot

    def _check(self):
        if not self.r.connected:
            raise RuntimeError("receive: not connected")

    def getActualQ(self):
        self._check()
        return list(self.r.q)

    def getActualQd(self):
        self._check()
        return [0.0] * len(self.r.q)

    def getTimestamp(self):
        self._check()
        return 0.0

    def isProtectiveStopped(self):
        return self.r.protective

    def isEmergencyStopped(self):
        return self.r.estop

    def isConnected(self):
        return self.r.connected

    def reconnect(self):
        return not self.r.refuse_connect and self.r.connected

    def disconnect(self):
        self.r.calls.append(("receive.disconnect",))


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def setup():
    env, q0, _ = envelope_for(Profile())
    robot = FakeRobot(q0)
    clock = Clock()
    made = []

    def factory(ip, hz):
        if robot.refuse_connect:
            raise RuntimeError("connection refused")
        made.append((ip, hz))
        return FakeControl(robot), FakeReceive(robot)

    backend = URRtdeBackend(env, DT, "192.0.2.10", lookahead_s=0.1, gain=300.0, reconnect_min_s=0.5,
                            reconnect_max_s=4.0, watchdog_hz=20.0, factory=factory, clock=clock)
    return backend, robot, clock, made, np.asarray(q0)


def names(robot):
    return [c[0] for c in robot.calls]


def test_rtde_is_not_imported_by_the_bridge():
    # In a fresh interpreter: this one may have imported ur_rtde for another test (the emulator's).
    probe = subprocess.run([sys.executable, "-c", "import sys, nwr.services.bridge.main; "
                            "print(sorted({'rtde_control', 'rtde_receive'} & set(sys.modules)))"],
                           capture_output=True, text=True, timeout=60, check=True)
    assert probe.stdout.strip() == "[]", probe.stdout


def test_position_and_velocity_streams(setup):
    backend, robot, _, made, q0 = setup
    backend.connect()
    assert made == [("192.0.2.10", 500.0)]
    q = q0 + 0.001
    sent = backend.send_action(Setpoint("position", q, np.zeros(6), np.zeros(6), DT))
    assert np.array_equal(sent.q, q)
    name, q_sent, speed, acc, time, lookahead, gain = robot.calls[-1]
    assert name == "servoJ" and q_sent == q.tolist() and time == DT and lookahead == 0.1 and gain == 300.0
    backend.send_action(Setpoint("velocity", q, np.full(6, 0.2), np.zeros(6), DT))
    assert robot.calls[-1] == ("speedJ", [0.2] * 6, 8.0, DT)
    backend.send_action(Setpoint("hold", q, np.zeros(6), np.zeros(6), DT))
    assert robot.calls[-1] == ("speedStop", 8.0)
    backend.send_action(Setpoint("hold", q, np.zeros(6), np.zeros(6), DT))
    assert names(robot).count("speedStop") == 1  # the stream ends once


def test_send_returns_what_the_guard_let_through(setup):
    backend, robot, _, _, q0 = setup
    backend.connect()
    wild = q0 + 0.5
    sent = backend.send_action(Setpoint("position", wild, np.zeros(6), np.zeros(6), DT))
    assert backend.guarded == 1
    assert np.all(np.abs(sent.q - q0) <= backend.env.v_max * DT * 1.5 + 1e-9)
    assert robot.calls[-1][1] == sent.q.tolist()


def test_pacing_uses_init_and_wait_period(setup):
    backend, robot, _, _, _ = setup
    backend.connect()
    pacer = backend.pacer(500.0)
    robot.calls.clear()
    assert pacer.sleep() and pacer.sleep()
    # The controller's watchdog is kicked KICKS_PER_PERIOD times per watchdog period, not every cycle.
    assert names(robot) == ["initPeriod", "kickWatchdog", "waitPeriod", "initPeriod"]
    time.sleep(1.0 / (KICKS_PER_PERIOD * backend.watchdog_hz))
    assert pacer.sleep() and names(robot)[-1] == "kickWatchdog"


def test_faults_are_reported(setup):
    backend, robot, _, _, _ = setup
    backend.connect()
    assert backend.get_observation().fault is None
    robot.protective = True
    obs = backend.get_observation()
    assert obs.fault == "protective_stop" and "pendant" in obs.detail
    robot.protective, robot.estop = False, True
    assert backend.get_observation().fault == "emergency_stop"
    robot.estop, robot.program = False, False
    assert backend.get_observation().fault == "script_not_running"
    assert "reuploadScript" in names(robot)
    assert backend.get_observation().fault is None  # re-uploaded


def test_protective_stop_is_never_cleared_by_the_bridge(setup):
    backend, robot, _, _, _ = setup
    backend.connect()
    robot.protective = True
    for _ in range(10):
        assert backend.get_observation().fault == "protective_stop"
    assert "reuploadScript" not in names(robot)


def test_disconnect_and_reconnect_with_backoff(setup):
    backend, robot, clock, made, q0 = setup
    backend.connect()
    backend.send_action(Setpoint("position", q0, np.zeros(6), np.zeros(6), DT))
    robot.connected = False
    robot.refuse_connect = True
    obs = backend.get_observation()
    assert obs.fault == "disconnected" and np.array_equal(obs.q, q0)
    # Sending while disconnected does nothing and does not raise.
    backend.send_action(Setpoint("position", q0, np.zeros(6), np.zeros(6), DT))
    attempts = []
    for t in np.arange(0.0, 10.0, 0.1):
        clock.t = float(t)
        before = backend.reconnects
        assert backend.get_observation().fault == "disconnected"
        if backend.reconnects > before:
            attempts.append(round(float(t), 1))
    gaps = np.diff(attempts)
    assert attempts[0] == 0.0 and list(gaps[:3]) == pytest.approx([0.5, 1.0, 2.0], abs=0.11)
    assert max(gaps) <= 4.0 + 0.11  # capped at reconnect_max_s
    robot.connected, robot.refuse_connect = True, False
    clock.t = 100.0
    assert backend.get_observation().fault is None and backend.connected


def test_a_slow_reconnection_runs_in_its_thread_and_the_loop_goes_on(setup):
    """ur_rtde's constructors retry while the controller refuses: the loop reports disconnected meanwhile."""
    import threading

    backend, robot, clock, made, q0 = setup
    release = threading.Event()
    fast = backend.factory

    def slow(ip, hz):
        release.wait(10.0)
        return fast(ip, hz)

    backend.factory = slow
    backend.reconnect_in_thread = True
    release.set()
    backend.connect()
    release.clear()
    robot.connected = False
    started = time.monotonic()
    for _ in range(50):  # 50 cycles while the attempt hangs: none of them waits for it
        obs = backend.get_observation()
        assert obs.fault == "disconnected" and np.array_equal(obs.q, q0)
    assert time.monotonic() - started < 1.0 and backend.reconnects == 1
    robot.connected = True
    release.set()
    backend._connector.join(5.0)
    assert backend.get_observation().fault is None and backend.connected and backend.reconnects == 1


@pytest.mark.parametrize("first", ["hold", "position"])
def test_a_command_the_controller_does_not_answer_leaves_the_loop_running(setup, first):
    """A frozen data stream holds ur_rtde's commands (a stop's acknowledgement, the script's readiness before any
    command): they go from a thread of their own, the loop reading, pacing and publishing on, and nothing after the
    unanswered one (no setpoint, no kick) reaches the controller until it is answered; then the newest setpoint."""
    import threading

    from nwr.services.bridge.courier import Courier

    backend, robot, clock, made, q0 = setup
    answer = threading.Event()
    entered = threading.Event()

    class Frozen(FakeControl):
        def _call(self, name, *args):
            if name in ("servoStop", "servoJ") and not answer.is_set() and robot.freeze:
                entered.set()
                answer.wait(10.0)  # ur_rtde waiting for the control script through the frozen stream
            super()._call(name, *args)

    robot.freeze = False
    backend.commands_in_thread = True
    backend.courier = Courier("rtde-commands", threaded=True)
    backend.factory = lambda ip, hz: (Frozen(robot), FakeReceive(robot))
    backend.connect()
    pacer = backend.pacer(500.0)
    backend.send_action(Setpoint("position", q0, np.zeros(6), np.zeros(6), DT))
    assert backend.courier.wait_idle(5.0)
    robot.freeze = True
    started = time.monotonic()
    backend.send_action(Setpoint(first, q0, np.zeros(6), np.zeros(6), DT))
    assert entered.wait(5.0)
    robot.calls.clear()
    for i in range(20):  # 20 cycles (40 ms) while the command waits: none of them waits for it
        assert pacer.sleep()
        assert backend.get_observation().fault is None
        backend.send_action(Setpoint("position", q0 + 1e-4 * (i + 1), np.zeros(6), np.zeros(6), DT))
    assert time.monotonic() - started < 1.0 and backend.courier.busy_s() > 0.0
    assert not {"servoJ", "speedJ", "kickWatchdog", "servoStop"} & set(names(robot)), names(robot)
    answer.set()
    assert backend.courier.wait_idle(5.0)
    sent = [c for c in robot.calls if c[0] != "isProgramRunning" and c[0] not in ("initPeriod", "waitPeriod")]
    # the answered command, then the newest kick and the newest setpoint (the 19 before it replaced)
    assert [c[0] for c in sent] == [{"hold": "servoStop", "position": "servoJ"}[first], "kickWatchdog", "servoJ"], sent
    assert sent[2][1] == pytest.approx((q0 + 2e-3).tolist())
    assert backend.courier.replaced >= 19
    robot.calls.clear()
    time.sleep(1.0 / (KICKS_PER_PERIOD * backend.watchdog_hz))
    assert pacer.sleep()
    assert backend.courier.wait_idle(5.0) and "kickWatchdog" in names(robot)  # the controller is watched again
    backend.disconnect()


def test_a_command_that_fails_in_the_courier_is_a_lost_connection(setup):
    from nwr.services.bridge.courier import Courier

    backend, robot, clock, made, q0 = setup
    backend.courier = Courier("rtde-commands", threaded=True)
    backend.connect()
    robot.connected = False  # the double raises on the next command
    backend.send_action(Setpoint("position", q0, np.zeros(6), np.zeros(6), DT))
    assert backend.courier.wait_idle(5.0)
    robot.connected = True  # (isConnected() says nothing: the error alone tells)
    backend.get_observation()  # the error taken for a lost connection: fresh interfaces at once (the double's)
    assert backend.reconnects == 1 and len(made) == 2 and "servoJ: not connected" in backend.fault_reason
    backend.disconnect()


def test_lost_interfaces_are_kept_not_destroyed_while_the_bridge_runs(setup):
    """ur_rtde's destructor holds the GIL for about 0.5 s: the lost interfaces are disconnected and kept (at most
    KEPT_LOST), released at shutdown."""
    import weakref

    from nwr.services.bridge.backends.ur_rtde import KEPT_LOST

    backend, robot, clock, made, q0 = setup
    backend.connect()
    first = weakref.ref(backend.control)
    for i in range(KEPT_LOST):  # KEPT_LOST / 2 + ... drops: each loses two interfaces
        robot.connected = False
        clock.t = 100.0 * (i + 1)
        assert backend.get_observation().fault == "disconnected"
        robot.connected = True
        clock.t += 50.0
        assert backend.get_observation().fault is None
        if 2 * (i + 1) <= KEPT_LOST:
            assert first() is not None, i  # kept: never destroyed by the loop or the reconnection
    assert len(backend._lost_interfaces) == KEPT_LOST and first() is None  # the oldest went, beyond the bound
    assert "receive.disconnect" in names(robot)  # disconnected before it was kept
    backend.disconnect()
    assert backend._lost_interfaces == []


def test_a_non_finite_report_is_passed_on_not_taken_for_a_lost_connection(setup):
    backend, robot, _, _, q0 = setup
    backend.connect()
    robot.q = [math.nan] * 6
    obs = backend.get_observation()
    assert obs.fault is None and backend.connected and not np.isfinite(obs.q).any()
    assert np.array_equal(backend.last_q, q0)  # the last finite report is kept


def test_a_call_that_raises_marks_the_connection_lost(setup):
    backend, robot, _, _, q0 = setup
    backend.connect()
    robot.connected = False
    backend.send_action(Setpoint("velocity", q0, np.zeros(6), np.zeros(6), DT))
    assert not backend.connected


def test_clean_release_on_shutdown(setup):
    backend, robot, _, _, q0 = setup
    backend.connect()
    backend.send_action(Setpoint("position", q0, np.zeros(6), np.zeros(6), DT))
    backend.disconnect()
    assert names(robot)[-4:] == ["servoStop", "stopScript", "disconnect", "receive.disconnect"]
    backend.disconnect()  # twice is fine
    assert backend.control is None


def test_connection_failure_says_what_to_check(setup):
    backend, robot, _, _, _ = setup
    robot.refuse_connect = True
    with pytest.raises(RobotConnectionError, match="remote control mode.*30004"):
        backend.connect()


def test_the_controller_watches_the_bridge(setup):
    """setWatchdog right after connecting, and again whenever the control script restarts."""
    backend, robot, clock, _, _ = setup
    backend.connect()
    assert robot.calls[0] == ("setWatchdog", 20.0)
    robot.program = False  # the script stopped (program stopped on the pendant): re-uploaded, re-armed
    backend.get_observation()
    assert names(robot)[-2:] == ["reuploadScript", "setWatchdog"]
    robot.connected = False  # a lost connection: the new one is watched again
    backend.get_observation()
    robot.connected = True
    clock.t = 100.0
    robot.calls.clear()
    assert backend.get_observation().fault is None
    assert ("setWatchdog", 20.0) in robot.calls


def test_no_watchdog_no_arm(setup):
    """A controller that refuses the watchdog is not driven: at start, after a reconnection, after a re-upload."""
    backend, robot, clock, _, _ = setup
    robot.refuse_watchdog = True
    with pytest.raises(RobotConnectionError, match="watchdog"):
        backend.connect()
    assert not backend.connected and "stopScript" in names(robot)
    robot.refuse_watchdog = False
    backend.connect()
    robot.refuse_watchdog, robot.program = True, False
    backend.get_observation()  # re-uploads, cannot arm: stops the script again
    assert names(robot)[-3:] == ["reuploadScript", "setWatchdog", "stopScript"]
    robot.connected = False
    backend.get_observation()
    robot.connected = True
    clock.t = 100.0
    assert backend.get_observation().fault == "disconnected" and "watchdog" in backend.fault_reason


HUNG = """
import sys, threading, time
sys.path.insert(0, {tests!r})
from test_rtde_backend import FakeControl, FakeReceive, FakeRobot
from nwr.common.config import Profile
from nwr.services.bridge.backends.ur_rtde import URRtdeBackend
from nwr.services.bridge.wiring import envelope_for

class Hung(FakeControl):
    def setWatchdog(self, min_frequency=10.0, /):
        threading.Event().wait()  # as ur_rtde waiting for an acknowledgement that never comes

env, q0, _ = envelope_for(Profile())
robot = FakeRobot(q0)
backend = URRtdeBackend(env, 0.002, "192.0.2.10", factory=lambda ip, hz: (Hung(robot), FakeReceive(robot)),
                        stall_exit_s=0.5)
started = time.monotonic()
backend.connect()
print("connect() returned", flush=True)
"""


def test_a_call_into_ur_rtde_that_never_returns_ends_the_process_for_a_fresh_start():
    """ur_rtde can wait 300 s for a command's answer from a controller that dropped the connection: the stall
    guard exits the bridge (EXIT_STALLED) so that its supervisor starts a fresh one."""
    from pathlib import Path

    from nwr.services.bridge.backends.ur_rtde import EXIT_STALLED

    run = subprocess.run([sys.executable, "-c", HUNG.format(tests=str(Path(__file__).parent))],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == EXIT_STALLED, (run.returncode, run.stdout, run.stderr)
    assert "connect() returned" not in run.stdout
    assert "has not returned" in run.stderr and "fresh bridge" in run.stderr, run.stderr


def test_the_stall_guard_watches_only_the_real_library_unless_asked(setup):
    backend, *_ = setup
    assert backend.stall_exit_s == 0.0  # a test double's factory: no guard (it would end the test's process)
    backend.connect()
    assert backend._guard is None
