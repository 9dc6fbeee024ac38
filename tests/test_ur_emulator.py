"""The UR controller emulator: RTDE packing (fast) and the real ur_rtde against it (slow, e2e).

ur_rtde fixes its ports (RTDE 30004, dashboard 29999, script 30003), so the
e2e test binds those on 127.0.0.1: one emulator at a time, and it skips when
something else holds them.
"""

from __future__ import annotations

import struct
import subprocess
import threading
import time

import numpy as np
import pytest
from ur_support import emulator_process, skip_unless_free

from nwr.services.tools.hardware import rtde, ur_arm, ur_controller
from nwr.services.tools.hardware import ur_emulator as u

HOME = [0.0, -1.15, 1.85, -2.27, -1.57, 0.0]


# --------------------------------------------------------------------------- packing


def test_package_round_trip_and_split() -> None:
    a = rtde.pack_package(rtde.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))
    b = rtde.pack_bool_reply(rtde.CONTROL_PACKAGE_START, True)
    assert a == b"\x00\x05V\x00\x02"
    packages, rest = rtde.split_packages(a + b + b[:2])
    assert packages == [(rtde.REQUEST_PROTOCOL_VERSION, b"\x00\x02"), (rtde.CONTROL_PACKAGE_START, b"\x01")]
    assert rest == b[:2]
    assert rtde.parse_protocol_version(packages[0][1]) == 2


@pytest.mark.parametrize("raw, message", [
    (b"\x00\x02V", "smaller than the 3-byte header"),
    (b"\x00\x05z\x00\x02", "unknown RTDE command"),
])
def test_split_rejects_garbage(raw: bytes, message: str) -> None:
    with pytest.raises(rtde.RtdeProtocolError, match=message):
        rtde.split_packages(raw)


def test_data_round_trip() -> None:
    types = ["DOUBLE", "VECTOR6D", "INT32", "UINT32", "UINT64", "BOOL", "UINT8", "VECTOR3D", "VECTOR6INT32"]
    values = [1.5, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6], -7, 7, 2**40, True, 255, [1.0, 2.0, 3.0], [1, -2, 3, -4, 5, -6]]
    package = rtde.pack_data(3, types, values)
    (command, payload), = rtde.split_packages(package)[0]
    assert command == rtde.DATA_PACKAGE and rtde.data_recipe_id(payload) == 3
    assert rtde.unpack_data(payload, types) == values


def test_data_errors_are_clear() -> None:
    with pytest.raises(rtde.RtdeProtocolError, match="needs 6 values"):
        rtde.pack_data(1, ["VECTOR6D"], [[1.0, 2.0]])
    with pytest.raises(rtde.RtdeProtocolError, match="no RTDE data type 'FLOAT'"):
        rtde.data_format(["FLOAT"])
    with pytest.raises(rtde.RtdeProtocolError, match="has 5 bytes; the recipe needs 9"):
        rtde.unpack_data(b"\x01\x00\x00\x00\x00", ["DOUBLE"])
    with pytest.raises(rtde.RtdeProtocolError, match="no recipe id"):
        rtde.data_recipe_id(b"")
    with pytest.raises(rtde.RtdeProtocolError, match="expected 2"):
        rtde.parse_protocol_version(b"\x02")


def test_setup_and_text_message_parsing() -> None:
    payload = struct.pack(">d", 500.0) + b"timestamp,actual_q,"  # ur_rtde's trailing comma
    assert rtde.parse_setup_outputs(payload) == (500.0, ["timestamp", "actual_q"])
    assert rtde.parse_setup_inputs(b"input_int_register_0") == ["input_int_register_0"]
    with pytest.raises(rtde.RtdeProtocolError, match="empty variable name"):
        rtde.parse_setup_inputs(b"a,,b")
    with pytest.raises(rtde.RtdeProtocolError, match="expected a frequency"):
        rtde.parse_setup_outputs(b"\x00")
    message = rtde.pack_text_message("hello", "tester", rtde.WARNING_MESSAGE)
    (command, body), = rtde.split_packages(message)[0]
    assert command == rtde.TEXT_MESSAGE and rtde.parse_text_message(body) == ("hello", "tester", rtde.WARNING_MESSAGE)
    with pytest.raises(rtde.RtdeProtocolError, match="truncated"):
        rtde.parse_text_message(body[:4])


def test_variable_types() -> None:
    assert rtde.variable_type("actual_q", "output") == "VECTOR6D"
    assert rtde.variable_type("output_int_register_47", "output") == "INT32"
    assert rtde.variable_type("input_double_register_3", "output") == "DOUBLE"
    assert rtde.variable_type("input_bit_register_64", "input") == "BOOL"
    assert rtde.variable_type("output_int_register_0", "input") is None
    assert rtde.variable_type("output_int_register_48", "output") is None
    assert rtde.variable_type("output_int_register_01", "output") is None
    assert rtde.variable_type("no_such_thing", "output") is None


# --------------------------------------------------------------------------- the session


def _reply(session: u.RtdeSession, command: int, payload: bytes = b"") -> tuple[int, bytes]:
    (answer,), rest = rtde.split_packages(session.handle(command, payload))
    assert rest == b""
    return answer


def _controller() -> ur_controller.Controller:
    """A controller on a frozen clock: the watchdog sees no time pass unless a test moves it."""
    limits = ur_arm.ArmLimits(np.full(6, -6.28), np.full(6, 6.28), np.full(6, 2.0), np.full(6, 8.0))
    return ur_controller.Controller(ur_arm.Arm(np.array(HOME), limits), clock=lambda: 0.0)


def test_session_recipes_and_registers() -> None:
    controller = _controller()
    claims: dict[str, int] = {}
    lock = threading.Lock()
    session = u.RtdeSession(controller, claims, lock)
    assert _reply(session, rtde.REQUEST_PROTOCOL_VERSION, b"\x00\x02") == (rtde.REQUEST_PROTOCOL_VERSION, b"\x01")
    command, body = _reply(session, rtde.GET_URCONTROL_VERSION)
    assert struct.unpack(">IIII", body)[0] == 5
    out = struct.pack(">d", 500.0) + b"timestamp,actual_q,output_int_register_0,nope"
    assert _reply(session, rtde.CONTROL_PACKAGE_SETUP_OUTPUTS, out)[1] == b"\x00DOUBLE,VECTOR6D,INT32,NOT_FOUND"
    out = struct.pack(">d", 500.0) + b"timestamp,actual_q,input_int_register_0"
    assert _reply(session, rtde.CONTROL_PACKAGE_SETUP_OUTPUTS, out)[1] == b"\x01DOUBLE,VECTOR6D,INT32"
    # input recipes are numbered from 1, apart from the output recipes
    assert _reply(session, rtde.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_0,input_double_register_0")[1] \
        == b"\x01INT32,DOUBLE"
    assert _reply(session, rtde.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_0")[1] == b"\x02INT32"
    other = u.RtdeSession(controller, claims, lock)
    assert _reply(other, rtde.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_0,input_int_register_1")[1] \
        == b"\x00IN_USE,INT32"
    assert _reply(session, rtde.CONTROL_PACKAGE_START) == (rtde.CONTROL_PACKAGE_START, b"\x01")
    (_, data), = rtde.split_packages(rtde.pack_data(1, ["INT32", "DOUBLE"], [42, 0.5]))[0]
    assert session.handle(rtde.DATA_PACKAGE, data) == b""
    assert controller.input_int[0] == 42 and controller.input_double[0] == 0.5
    (command, payload), = rtde.split_packages(session.data_packages())[0]
    timestamp, q, register = rtde.unpack_data(payload, ["DOUBLE", "VECTOR6D", "INT32"])
    assert q == HOME and register == 42
    with pytest.raises(rtde.RtdeProtocolError, match="unknown input recipe 9"):
        session.handle(rtde.DATA_PACKAGE, b"\x09")
    session.release()
    assert _reply(other, rtde.CONTROL_PACKAGE_SETUP_INPUTS, b"input_int_register_0")[1] == b"\x01INT32"


def test_control_script_emulation() -> None:
    controller = _controller()
    controller.load_script("def rtde_control():\n  global reg_offset_int = 0\nend\n")
    assert controller.script_running and controller.output_int[0] == ur_controller.SCRIPT_READY
    controller.write_inputs(["input_int_register_0", "input_double_register_0"], [ur_controller.CMD_SET_WATCHDOG, 10.0])
    controller.tick()
    assert controller.output_int[0] == ur_controller.SCRIPT_DONE and controller.watchdog_hz == 10.0
    controller.write_inputs(["input_int_register_0"], [0])
    controller.tick()
    assert controller.output_int[0] == ur_controller.SCRIPT_READY
    target = list(HOME)
    target[0] = 0.1
    names = ["input_int_register_0"] + [f"input_double_register_{i}" for i in range(11)]
    for _ in range(400):  # 0.8 s of servoJ
        controller.write_inputs(names, [ur_controller.CMD_SERVOJ, *target, 0.5, 0.5, 0.002, 0.1, 300.0])
        controller.tick()
    assert controller.arm.q[0] == pytest.approx(0.1, abs=1e-3)
    assert np.all(np.abs(controller.arm.qd) <= 2.0 + 1e-9)
    controller.write_inputs(["input_int_register_0", "input_double_register_0"], [ur_controller.CMD_STOP_SCRIPT, 0.0])
    controller.tick()
    assert not controller.script_running and controller.runtime_state == ur_arm.RUNTIME_STOPPED


def test_watchdog_stops_the_script() -> None:
    now = [0.0]
    controller = ur_controller.Controller(_controller().arm, clock=lambda: now[0])
    controller.load_script("def rtde_control():\nend\n")
    controller.write_inputs(["input_int_register_0", "input_double_register_0"], [ur_controller.CMD_SET_WATCHDOG, 10.0])
    controller.tick()
    now[0] = 0.09
    controller.tick()
    assert controller.script_running
    now[0] = 0.2
    controller.tick()
    assert not controller.script_running


def _running(now: list[float]) -> ur_controller.Controller:
    controller = ur_controller.Controller(_controller().arm, clock=lambda: now[0], protective_unlock_delay_s=5.0)
    controller.load_script("def rtde_control():\nend\n")
    controller.arm.speed([0.5, 0, 0, 0, 0, 0], 8.0)
    for _ in range(100):
        controller.tick()
    assert controller.arm.qd[0] == pytest.approx(0.5)
    return controller


def _to_rest(controller: ur_controller.Controller) -> None:
    for _ in range(500):
        controller.tick()
    assert not np.any(controller.arm.qd)


def test_protective_stop_and_its_unlock() -> None:
    now = [0.0]
    controller = _running(now)
    controller.protective_stop()
    assert not controller.script_running and controller.safety_mode == ur_arm.SAFETY_MODE_PROTECTIVE_STOP
    assert controller.safety_status_bits & ur_arm.SAFETY_PROTECTIVE_STOPPED
    _to_rest(controller)
    fault, = controller.faults
    assert fault["fault"] == "protective_stop" and fault["rest_t"] is not None and fault["cleared_t"] is None
    controller.load_script("def rtde_control():\nend\n")  # refused while stopped
    assert not controller.script_running
    dashboard = u.Dashboard(controller)
    assert dashboard.answer("safetymode") == "Safetymode: PROTECTIVE_STOP"
    assert dashboard.answer("unlock protective stop").startswith("Cannot unlock protective stop until 5s")
    now[0] = 5.0
    assert dashboard.answer("unlock protective stop") == "Protective stop releasing"
    assert controller.safety_status_bits == ur_arm.SAFETY_NORMAL
    controller.load_script("def rtde_control():\nend\n")
    assert controller.script_running and fault["cleared_t"] == 5.0


def test_emergency_stop_powers_the_arm_off() -> None:
    now = [0.0]
    controller = _running(now)
    controller.emergency_stop()
    assert controller.safety_status_bits & ur_arm.SAFETY_EMERGENCY_STOPPED and not controller.script_running
    _to_rest(controller)
    assert controller.robot_mode == ur_arm.ROBOT_MODE_POWER_OFF
    dashboard = u.Dashboard(controller)
    assert dashboard.answer("robotmode") == "Robotmode: POWER_OFF"
    assert dashboard.answer("power on").startswith("Failed")  # the button is still pressed
    assert controller.release_emergency_stop() == "emergency stop released"
    controller.load_script("def rtde_control():\nend\n")
    assert not controller.script_running  # powered off
    dashboard.answer("power on")
    dashboard.answer("brake release")
    assert controller.robot_mode == ur_arm.ROBOT_MODE_RUNNING
    controller.load_script("def rtde_control():\nend\n")
    assert controller.script_running


def test_stall_trips_the_watchdog_and_motion_is_logged() -> None:
    now = [0.0]
    controller = _running(now)
    names = ["input_int_register_0", "input_double_register_0"]
    controller.write_inputs(names, [ur_controller.CMD_SET_WATCHDOG, 10.0])
    controller.tick()
    controller.write_inputs(names, [ur_controller.CMD_SPEEDJ, 0.1])
    assert controller.motion_writes == 1 and controller.command_changes[-1] == (0.0, ur_controller.CMD_SPEEDJ)
    controller.stall(1.0)
    now[0] = 0.05
    controller.write_inputs(names, [ur_controller.CMD_WATCHDOG, 0.0])  # ignored: the stall
    controller.tick()
    assert controller.script_running
    now[0] = 0.2
    controller.tick()
    assert not controller.script_running
    assert [f["fault"] for f in controller.faults] == ["stall", "watchdog"]


def test_offset_reports_a_joint_off_while_the_arm_moves_as_commanded() -> None:
    now = [0.0]
    controller = _running(now)
    names = ["input_int_register_0", *(f"input_double_register_{i}" for i in range(7))]
    controller.offset(2, 0.3, 1.0, at="speedj")
    assert controller.read_outputs(["actual_q"])[0] == pytest.approx(controller.arm.q.tolist())  # armed, not yet active
    # the reflex's first speedJ
    controller.write_inputs(names, [ur_controller.CMD_SPEEDJ, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 8.0])
    for _ in range(100):
        controller.tick()
        now[0] += ur_arm.DT
    reported = controller.read_outputs(["actual_q"])[0]
    assert reported[2] == pytest.approx(controller.arm.q[2] + 0.3)
    assert reported[:2] == pytest.approx(controller.arm.q[:2].tolist())
    (fault,) = [f for f in controller.faults if f["fault"] == "offset"]
    assert fault["joint"] == 2 and fault["peak_qd"][2] == pytest.approx(0.5) and len(fault["track"]) > 40
    now[0] = 1.01
    assert controller.read_outputs(["actual_q"])[0][2] == pytest.approx(controller.arm.q[2])  # over
    with pytest.raises(ValueError, match="joint 0-5"):
        controller.offset(6, 0.1, 1.0)


def test_freeze_stops_the_rtde_output_for_a_while() -> None:
    now = [0.0]
    controller = _running(now)
    assert not controller.frozen()
    controller.freeze(0.5)
    assert controller.frozen() and controller.faults[-1]["fault"] == "freeze"
    now[0] = 0.6
    assert not controller.frozen()
    e = u.Emulator.__new__(u.Emulator)  # the control port's parsing alone
    e.controller = controller
    assert e.control("freeze 1 speedj").startswith("freezing RTDE output for 1 s from the next speedJ")
    assert e.control("offset 2 0.08 3").startswith("offset joint 2 by 0.08 rad for 3 s")
    assert controller.armed == [("freeze", (1.0,), "speedj")]
    assert e.control("freeze 2 stop").startswith("freezing RTDE output for 2 s from the next stop")
    names = ["input_int_register_0", "input_double_register_0"]
    now[0] = 1.0
    controller.write_inputs(names, [ur_controller.CMD_SPEED_STOP, 4.0])
    assert not controller.frozen() and len(controller.armed) == 2  # written, not yet answered
    controller.tick()  # the script answers "done"
    assert controller.output_int[0] == ur_controller.SCRIPT_DONE and not controller.frozen()
    controller.write_inputs(names, [ur_controller.CMD_NONE, 0.0])  # the client read it and cleared the command
    controller.tick()  # the freeze begins before the script's "ready" goes out
    assert controller.frozen() and controller.armed == [("freeze", (1.0,), "speedj")]  # the speedJ's still armed
    assert controller.faults[-1]["seconds"] == 2.0
    now[0] += 2.0
    assert not controller.frozen()


def test_speed_is_acceleration_limited() -> None:
    arm = _controller().arm
    arm.speed([1.0, 0, 0, 0, 0, 0], 100.0)  # above the 8 rad/s^2 limit
    arm.step()
    assert arm.qd[0] == pytest.approx(8.0 * ur_arm.DT)
    for _ in range(200):
        arm.step()
    assert arm.qd[0] == pytest.approx(1.0)
    arm.stop(4.0)
    arm.step()
    assert arm.qd[0] == pytest.approx(1.0 - 4.0 * ur_arm.DT)


def test_take_program() -> None:
    program, rest = u.take_program("def a():\n  x = 1\n  end\nend\nsec b():\n")
    assert program == "def a():\n  x = 1\n  end\nend\n" and rest == "sec b():\n"
    assert u.take_program("def a():\n  x = 1\n") == (None, "def a():\n  x = 1\n")


# --------------------------------------------------------------------------- e2e


@pytest.fixture
def emulator(tmp_path):
    skip_unless_free()
    with emulator_process(tmp_path / "emulator.log") as process:
        yield process


@pytest.mark.slow
@pytest.mark.e2e
def test_ur_rtde_against_the_emulator(emulator: subprocess.Popen) -> None:
    rtde_receive = pytest.importorskip("rtde_receive")
    rtde_control = pytest.importorskip("rtde_control")
    receive = rtde_receive.RTDEReceiveInterface("127.0.0.1", 500.0)
    control = None
    try:
        time.sleep(0.1)
        assert receive.isConnected()
        assert receive.getActualQ() == pytest.approx(HOME)
        assert receive.getRobotMode() == ur_arm.ROBOT_MODE_RUNNING
        assert receive.getSafetyMode() == ur_arm.SAFETY_MODE_NORMAL
        assert not receive.isProtectiveStopped() and not receive.isEmergencyStopped()
        t, started = receive.getTimestamp(), time.monotonic()
        time.sleep(0.2)
        # the controller's clock runs (not compared with the wall clock: a loaded machine starves both sides)
        assert 0.0 < receive.getTimestamp() - t <= time.monotonic() - started + 0.05

        control = rtde_control.RTDEControlInterface("127.0.0.1", 500.0)
        assert control.isConnected() and control.isProgramRunning()
        time.sleep(0.05)  # the receive interface's newest sample is a few ms old
        assert receive.getRuntimeState() == ur_arm.RUNTIME_PLAYING
        # The bridge arms 10 Hz; 1 Hz here, so a loaded test machine's stalls do not trip it.
        assert control.setWatchdog(1.0)
        target = list(HOME)
        for i in range(400):  # 0.8 s of a servoJ stream, as the bridge sends it
            period = control.initPeriod()
            control.kickWatchdog()
            target[0] = 0.1 * min(1.0, i / 200)
            assert control.servoJ(target, 0.5, 0.5, 0.002, 0.1, 300.0)
            control.waitPeriod(period)
        assert control.servoStop(2.0)
        deadline = time.monotonic() + 3.0
        while max(abs(v) for v in receive.getActualQd()) > 0.0 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.05)
        q = receive.getActualQ()
        assert q[0] == pytest.approx(0.1, abs=0.01)
        assert q[1:] == pytest.approx(HOME[1:])
        assert max(abs(v) for v in receive.getActualQd()) < 1e-6
        control.stopScript()
        assert not control.isProgramRunning()
    finally:
        if control is not None:
            control.disconnect()
        receive.disconnect()
