"""A UR e-Series controller emulator that the unmodified ``ur_rtde`` library talks to.

Run it with ``python -m nwr.services.tools.hardware.ur_emulator --host 127.0.0.1``; then
``rtde_receive.RTDEReceiveInterface("127.0.0.1")`` and
``rtde_control.RTDEControlInterface("127.0.0.1")`` connect to it as to a real
arm (or URSim).

What it serves
--------------
* RTDE (port 30004, protocol version 2, per Universal Robots' RTDE guide):
  protocol negotiation, controller version (reported as 5.15.0), output and
  input recipes, start / pause, DATA_PACKAGEs out at the requested rate (at
  most 500 Hz), DATA_PACKAGEs in (stored in the input registers), text
  messages (logged).
* The dashboard server (port 29999): the welcome line and the handful of
  commands ur_rtde issues, answered as a robot in remote control with no
  program loaded.
* The script port (30003): the control script ur_rtde uploads is stored, and
  its behaviour is emulated in Python (it is not interpreted): the register
  protocol of ur_rtde's ``rtde_control.script`` (input_int_register_0 = the
  command, input_double_registers = its arguments, output_int_register_0 = 1
  ready / 2 done) for servoJ, speedJ, servoStop, speedStop, stopJ, the RTDE
  watchdog and stopping the script; every other command is acknowledged
  without an effect.

Fault injection
---------------
``--control-port PORT`` opens a line-based control port on 127.0.0.1 (never
elsewhere), one answer line per command line:

* ``protective stop``: safety mode PROTECTIVE_STOP and its status bits, the
  control script stops and the arm decelerates to rest (a stop of category
  2). Cleared by the dashboard's ``unlock protective stop``, refused for
  ``--protective-unlock-delay`` seconds after the stop (5 s, as on e-Series).
* ``emergency stop``: safety mode ROBOT_EMERGENCY_STOP and its bits, the
  script stops, the arm decelerates to rest and is then powered off (category
  1). Cleared by ``release emergency stop`` (the button), then the
  dashboard's ``power on`` and ``brake release``.
* ``stop program``: the control script stopped as from the pendant (the
  dashboard's ``stop`` does the same).
* ``drop [S]``: every RTDE, dashboard and script connection closed; new ones
  refused for S seconds (default 0).
* ``stall S``: RTDE input ignored for S seconds, as if the client had gone
  silent: the RTDE watchdog, once armed, stops the script.
* ``offset J X S [speedj]``: a hostile controller: joint J's (index 0-5)
  reported position (``actual_q``) offset by X rad for S seconds while the
  arm itself moves as commanded; with ``speedj``, from the next speedJ the
  client sends (a velocity reflex's onset) rather than now.
* ``freeze S [speedj]``: no RTDE data sent to any client for S seconds, the
  connections open (a controller whose data stream stalls).
* ``nan J S``: joint J's reported position and speed not a number for S
  seconds.
  Each records a fault (``offset`` / ``freeze``) with the true arm's fastest
  joint speeds (``peak_qd``, from the fault to 1 s after it ended) and its
  joint positions meanwhile (``track``: [t, q0..q5] every other control
  period, 4 ms of the arm's motion: ``t`` is the controller's clock when it was
  integrated), for a test
  to tell what the real arm would have done.
* ``state``: the controller's state as one JSON line (joints, modes, whether
  the script runs, each fault with the controller's monotonic time of the
  fault, of the arm's rest after it and of the script's next start, motion
  commands received meanwhile, and every change of the command register with
  its receipt time).
* anything else: answered as the dashboard server would (``unlock protective
  stop``, ``power on``, ``brake release``, ``power off``, ...).

While the arm is not powered, its brakes are not released or a safety stop is
in force, an uploaded control script is not started, as on a real controller.

The arm is a kinematic 6-joint UR10e integrated at 500 Hz with the joint
position and speed limits of the packaged URDF and the acceleration limits of
``common/robots/ur10e/robot.toml``.

Structure: the protocol (packing and unpacking RTDE packages), the variable
table and :class:`Controller` (registers, the emulated control script and the
arm) are pure and socket-free; :class:`Emulator` adds the three TCP servers,
one thread per connection, plus the 500 Hz controller thread.

ur_rtde fixes its ports (RTDE 30004 and dashboard 29999; the script goes to
30003): they are options here for other clients, but ur_rtde reaches only the
defaults. Nothing here resolves names: bind addresses are used as given.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import logging
import math
import re
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- protocol

PROTOCOL_VERSION = 2
CONTROLLER_VERSION = (5, 15, 0, 0)  # major, minor, bugfix, build: an e-Series (major 5) controller
MAX_FREQUENCY_HZ = 500.0
HEADER = struct.Struct(">HB")  # package size (header included), command

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")
CONTROL_PACKAGE_START = ord("S")
CONTROL_PACKAGE_PAUSE = ord("P")
COMMANDS = frozenset({REQUEST_PROTOCOL_VERSION, GET_URCONTROL_VERSION, TEXT_MESSAGE, DATA_PACKAGE,
                      CONTROL_PACKAGE_SETUP_OUTPUTS, CONTROL_PACKAGE_SETUP_INPUTS, CONTROL_PACKAGE_START,
                      CONTROL_PACKAGE_PAUSE})

NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"

#: struct format of one value of each RTDE type (vectors flattened).
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}
_VECTOR_SIZES = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}

# TEXT_MESSAGE levels
EXCEPTION_MESSAGE, ERROR_MESSAGE, WARNING_MESSAGE, INFO_MESSAGE = 0, 1, 2, 3


class RtdeProtocolError(ValueError):
    """A malformed RTDE package."""


def pack_package(command: int, payload: bytes = b"") -> bytes:
    """One RTDE package: big-endian uint16 size (header included), uint8 command, payload."""
    if not 0 <= command <= 255:
        raise RtdeProtocolError(f"command {command} is not a byte")
    size = HEADER.size + len(payload)
    if size > 0xFFFF:
        raise RtdeProtocolError(f"payload of {len(payload)} bytes exceeds the RTDE package size limit (65535)")
    return HEADER.pack(size, command) + payload


def split_packages(buffer: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    """Split a byte stream into complete ``(command, payload)`` packages and the incomplete rest.

    Raises RtdeProtocolError on a size below the header's or an unknown command:
    the stream cannot be resynchronised after either.
    """
    packages: list[tuple[int, bytes]] = []
    offset = 0
    while len(buffer) - offset >= HEADER.size:
        size, command = HEADER.unpack_from(buffer, offset)
        if size < HEADER.size:
            raise RtdeProtocolError(f"package size {size} is smaller than the 3-byte header")
        if command not in COMMANDS:
            raise RtdeProtocolError(f"unknown RTDE command {command} ({chr(command)!r})")
        if len(buffer) - offset < size:
            break
        packages.append((command, bytes(buffer[offset + HEADER.size:offset + size])))
        offset += size
    return packages, bytes(buffer[offset:])


def parse_protocol_version(payload: bytes) -> int:
    if len(payload) != 2:
        raise RtdeProtocolError(f"REQUEST_PROTOCOL_VERSION payload has {len(payload)} bytes; expected 2")
    return int(struct.unpack(">H", payload)[0])


def pack_bool_reply(command: int, accepted: bool) -> bytes:
    """The reply to REQUEST_PROTOCOL_VERSION, START and PAUSE: one uint8, 1 = accepted."""
    return pack_package(command, struct.pack(">B", 1 if accepted else 0))


def pack_controller_version(version: Sequence[int] = CONTROLLER_VERSION) -> bytes:
    return pack_package(GET_URCONTROL_VERSION, struct.pack(">IIII", *version))


def _names(text: bytes, what: str) -> list[str]:
    try:
        decoded = text.decode("ascii")
    except UnicodeDecodeError as exc:
        raise RtdeProtocolError(f"{what}: variable names are not ASCII ({exc})") from exc
    names = decoded.split(",")
    if len(names) > 1 and names[-1] == "":
        names.pop()  # ur_rtde ends its lists with a comma; the controller accepts that
    if not decoded or any(not name.strip() for name in names):
        raise RtdeProtocolError(f"{what}: empty variable name in {decoded!r}")
    return [name.strip() for name in names]


def parse_setup_outputs(payload: bytes) -> tuple[float, list[str]]:
    """CONTROL_PACKAGE_SETUP_OUTPUTS (v2): float64 frequency, then comma-separated names."""
    if len(payload) < 9:
        raise RtdeProtocolError(f"SETUP_OUTPUTS payload has {len(payload)} bytes; expected a frequency and names")
    (frequency,) = struct.unpack_from(">d", payload)
    if not math.isfinite(frequency):
        raise RtdeProtocolError(f"SETUP_OUTPUTS frequency {frequency} is not finite")
    return float(frequency), _names(payload[8:], "SETUP_OUTPUTS")


def parse_setup_inputs(payload: bytes) -> list[str]:
    """CONTROL_PACKAGE_SETUP_INPUTS: comma-separated names."""
    return _names(payload, "SETUP_INPUTS")


def pack_setup_reply(command: int, recipe_id: int, types: Sequence[str]) -> bytes:
    """The reply to SETUP_OUTPUTS / SETUP_INPUTS: uint8 recipe id, comma-separated types."""
    return pack_package(command, struct.pack(">B", recipe_id) + ",".join(types).encode("ascii"))


def data_format(types: Sequence[str]) -> struct.Struct:
    """The struct of a DATA_PACKAGE payload: uint8 recipe id, then each value."""
    try:
        return struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in types))
    except KeyError as exc:
        raise RtdeProtocolError(f"no RTDE data type {exc.args[0]!r}") from None


def pack_data(recipe_id: int, types: Sequence[str], values: Sequence[Any]) -> bytes:
    """A DATA_PACKAGE with one value per type (a sequence for the vector types)."""
    if len(types) != len(values):
        raise RtdeProtocolError(f"{len(values)} values for {len(types)} types")
    flat: list[Any] = [recipe_id]
    for kind, value in zip(types, values, strict=True):
        if kind in _VECTOR_SIZES:
            items = list(value)
            if len(items) != _VECTOR_SIZES[kind]:
                raise RtdeProtocolError(f"{kind} needs {_VECTOR_SIZES[kind]} values, got {len(items)}")
            flat.extend(items)
        else:
            flat.append(value)
    try:
        return pack_package(DATA_PACKAGE, data_format(types).pack(*flat))
    except struct.error as exc:
        raise RtdeProtocolError(f"cannot pack {values} as {list(types)}: {exc}") from exc


def unpack_data(payload: bytes, types: Sequence[str]) -> list[Any]:
    """Values of a DATA_PACKAGE payload (without its recipe id) for a recipe's types."""
    fmt = data_format(types)
    if len(payload) != fmt.size:
        raise RtdeProtocolError(f"DATA_PACKAGE payload has {len(payload)} bytes; the recipe needs {fmt.size}")
    flat = list(fmt.unpack(payload))[1:]
    values: list[Any] = []
    for kind in types:
        n = _VECTOR_SIZES.get(kind, 1)
        values.append(flat[:n] if kind in _VECTOR_SIZES else flat[0])
        del flat[:n]
    return values


def data_recipe_id(payload: bytes) -> int:
    if not payload:
        raise RtdeProtocolError("empty DATA_PACKAGE: no recipe id")
    return payload[0]


def parse_text_message(payload: bytes) -> tuple[str, str, int]:
    """TEXT_MESSAGE (v2): uint8 length + message, uint8 length + source, uint8 level."""
    try:
        n = payload[0]
        message = payload[1:1 + n]
        m = payload[1 + n]
        source = payload[2 + n:2 + n + m]
        level = payload[2 + n + m]
    except IndexError:
        raise RtdeProtocolError(f"TEXT_MESSAGE of {len(payload)} bytes is truncated") from None
    if len(message) != n or len(source) != m or len(payload) != 3 + n + m:
        raise RtdeProtocolError(f"TEXT_MESSAGE of {len(payload)} bytes does not match its lengths ({n}, {m})")
    return message.decode("utf-8", "replace"), source.decode("utf-8", "replace"), level


def pack_text_message(message: str, source: str = "ur_emulator", level: int = INFO_MESSAGE) -> bytes:
    msg, src = message.encode()[:255], source.encode()[:255]
    return pack_package(TEXT_MESSAGE, bytes([len(msg)]) + msg + bytes([len(src)]) + src + bytes([level]))


# --------------------------------------------------------------------------- variables

_OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE",
    **{name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q", "actual_qd",
        "actual_current", "actual_current_window", "joint_control_output", "actual_TCP_pose",
        "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed", "joint_temperatures",
        "actual_joint_voltage", "payload_inertia", "ft_raw_wrench", "actual_current_as_torque",
        "target_current_as_torque")},
    "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE", "actual_robot_current": "DOUBLE",
    "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32", "analog_io_types": "UINT32", "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE", "standard_analog_output1": "DOUBLE",
    "io_current": "DOUBLE", "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
    "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE", "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32", "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE", "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32", "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8",
    "tool_digital_output1_mode": "UINT8", "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "script_control_line": "UINT32", "joint_position_deviation_ratio": "DOUBLE",
    "collision_detection_ratio": "DOUBLE", "time_scale_source": "UINT32", "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
}
_INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE", "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8", "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8", "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D", "ft_rtde_input_enable": "BOOL",
}
N_REGISTERS = 48  # int and double registers 0..47 (24..47 the "upper range" of external clients)


def _register(name: str, prefix: str, lo: int, hi: int) -> int | None:
    if not name.startswith(prefix):
        return None
    digits = name[len(prefix):]
    if not digits.isdigit() or (len(digits) > 1 and digits[0] == "0"):
        return None
    index = int(digits)
    return index if lo <= index <= hi else None


def register_type(name: str, direction: str) -> str | None:
    """The type of an input or output register variable, None if ``name`` is none."""
    for kind in ("input", "output") if direction == "output" else ("input",):
        if _register(name, f"{kind}_int_register_", 0, N_REGISTERS - 1) is not None:
            return "INT32"
        if _register(name, f"{kind}_double_register_", 0, N_REGISTERS - 1) is not None:
            return "DOUBLE"
        if _register(name, f"{kind}_bit_register_", 64, 127) is not None:
            return "BOOL"
    return None


def variable_type(name: str, direction: str) -> str | None:
    """The RTDE type of a variable for an ``"output"`` or ``"input"`` recipe; None if unknown."""
    if direction == "output":
        return _OUTPUT_TYPES.get(name) or register_type(name, "output")
    if direction == "input":
        return _INPUT_TYPES.get(name) or register_type(name, "input")
    raise ValueError(f"direction {direction!r}: expected 'output' or 'input'")


# --------------------------------------------------------------------------- the arm

ROBOT_MODE_POWER_OFF, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 5, 7
ROBOT_MODE_NAMES = {3: "POWER_OFF", 5: "IDLE", 7: "RUNNING"}
SAFETY_MODE_NORMAL, SAFETY_MODE_PROTECTIVE_STOP, SAFETY_MODE_ROBOT_EMERGENCY_STOP = 1, 3, 7
SAFETY_MODE_NAMES = {1: "NORMAL", 3: "PROTECTIVE_STOP", 7: "ROBOT_EMERGENCY_STOP"}
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
ROBOT_STATUS_POWER_ON, ROBOT_STATUS_PROGRAM_RUNNING = 1, 2
SAFETY_NORMAL = 1 << 0
SAFETY_PROTECTIVE_STOPPED = 1 << 2
SAFETY_ROBOT_EMERGENCY_STOPPED = 1 << 6
SAFETY_EMERGENCY_STOPPED = 1 << 7
SAFETY_STOPPED_DUE_TO_SAFETY = 1 << 10
#: e-Series: "Cannot unlock protective stop until 5s after occurrence".
PROTECTIVE_UNLOCK_DELAY_S = 5.0
JOINT_MODE_RUNNING = 253
DT = 0.002  # the e-Series control period


@dataclasses.dataclass
class ArmLimits:
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray


class Arm:
    """A kinematic arm: joint positions integrated from velocities under speed and acceleration limits.

    Modes: ``hold`` (decelerate to rest, then stay), ``servo`` (track a target
    position, as servoj), ``speed`` (reach a target velocity with a given
    acceleration, as speedj) and ``stop`` (decelerate at a given rate, as
    stopj / servoStop / speedStop).
    """

    def __init__(self, q0: np.ndarray, limits: ArmLimits,
                 pose: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        self.limits = limits
        self.q = np.array(q0, dtype=float)
        self.qd = np.zeros(6)
        self.qdd = np.zeros(6)
        self.target_q = self.q.copy()
        self.target_qd = np.zeros(6)
        self.mode = "hold"
        self.servo_q = self.q.copy()
        self.servo_tau = 0.1
        self.speed_qd = np.zeros(6)
        self.speed_a = float(np.max(limits.a_max))
        self.stop_a = float(np.max(limits.a_max))
        self._pose = pose
        self.tcp_pose = pose(self.q) if pose is not None else np.zeros(6)
        self.tcp_speed = np.zeros(6)

    def servo(self, q: Sequence[float], lookahead_time: float, gain: float) -> None:
        self.mode = "servo"
        self.servo_q = np.clip(np.asarray(q, dtype=float), self.limits.q_min, self.limits.q_max)
        # servoj's lookahead time smooths, its gain stiffens: a first-order lag in between.
        self.servo_tau = max(DT, min(0.2, lookahead_time) * 300.0 / max(gain, 100.0))

    def speed(self, qd: Sequence[float], acceleration: float) -> None:
        self.mode = "speed"
        self.speed_qd = np.clip(np.asarray(qd, dtype=float), -self.limits.v_max, self.limits.v_max)
        self.speed_a = acceleration

    def stop(self, deceleration: float) -> None:
        self.mode = "stop"
        self.stop_a = deceleration

    def step(self, dt: float = DT) -> None:
        lim = self.limits
        if self.mode == "servo":
            error = self.servo_q - self.q
            desired = error / self.servo_tau
            # never faster than what still stops at the target
            brake = np.sqrt(2.0 * lim.a_max * np.abs(error))
            desired = np.clip(desired, -brake, brake)
            a = lim.a_max
        elif self.mode == "speed":
            desired = self.speed_qd
            a = np.minimum(lim.a_max, max(self.speed_a, 1e-6))
        else:
            desired = np.zeros(6)
            a = lim.a_max if self.mode == "hold" else np.minimum(lim.a_max, max(self.stop_a, 1e-6))
        desired = np.clip(desired, -lim.v_max, lim.v_max)
        qd = self.qd + np.clip(desired - self.qd, -a * dt, a * dt)
        q = self.q + 0.5 * (self.qd + qd) * dt
        out = (q < lim.q_min) | (q > lim.q_max)
        q = np.clip(q, lim.q_min, lim.q_max)
        qd[out] = 0.0
        self.qdd = (qd - self.qd) / dt
        self.q, self.qd = q, qd
        self.target_qd = desired
        self.target_q = self.servo_q.copy() if self.mode == "servo" else q.copy()
        if self.mode in ("stop", "hold") and not np.any(qd):
            self.mode = "hold"
        if self._pose is not None:
            pose = self._pose(q)
            self.tcp_speed = np.concatenate([(pose[:3] - self.tcp_pose[:3]) / dt, np.zeros(3)])
            self.tcp_pose = pose


def ur10e_arm(q0: Sequence[float] | None = None) -> Arm:
    """The packaged UR10e: limits from its description, TCP poses from its URDF in UR's base frame."""
    from nwr.common.robot import RobotModel, load_description

    desc = load_description()
    model = RobotModel(dataclasses.replace(desc, base_frame="base"))

    def pose(q: np.ndarray) -> np.ndarray:
        transform = model.frame_pose(q, desc.tool_frame)
        return np.concatenate([transform[:3, 3], _rotation_vector(transform[:3, :3])])

    limits = ArmLimits(np.array(desc.q_min), np.array(desc.q_max), np.array(desc.v_max), np.array(desc.a_max))
    return Arm(np.array(desc.home if q0 is None else q0, dtype=float), limits, pose)


def _rotation_vector(r: np.ndarray) -> np.ndarray:
    angle = math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0)))
    if angle < 1e-9:
        return np.zeros(3)
    if math.pi - angle < 1e-6:
        axis = np.sqrt(np.maximum((np.diag(r) + 1.0) / 2.0, 0.0))
        for i in range(3):  # signs relative to the largest component
            k = int(np.argmax(axis))
            if i != k and r[i, k] + r[k, i] < 0:
                axis[i] = -axis[i]
        return axis / np.linalg.norm(axis) * angle
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2.0 * math.sin(angle))
    return axis * angle


# --------------------------------------------------------------------------- the controller

# ur_rtde's control script (rtde_control.script of ur_rtde 1.6.5): command ids
# in input_int_register_0 (+ the register offset), its state in output_int_register_0.
CMD_NONE = 0
CMD_SPEEDJ = 9  # qd in double registers 0..5, acceleration 6, time 7
CMD_SERVOJ = 11  # q in 0..5, speed 6, acceleration 7, time 8, lookahead time 9, gain 10
CMD_SPEED_STOP = 15  # deceleration in 0
CMD_SERVO_STOP = 16  # deceleration in 0
CMD_STOPJ = 34  # deceleration in 0, async flag in int register 1
CMD_SET_WATCHDOG = 35  # minimum frequency in 0
CMD_WATCHDOG = 99  # kickWatchdog: no branch in the script, the write itself is the kick
CMD_STOP_SCRIPT = 255
SCRIPT_READY, SCRIPT_DONE = 1, 2
#: Commands the script processes every cycle and answers "ready" (no done
#: handshake); read from the uploaded script when it lists them.
REALTIME_COMMANDS = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
_REALTIME_LINE = re.compile(r"^\s*if\s+cmd\s*==\s*\d+(\s+or\s+cmd\s*==\s*\d+)+\s*:\s*$")


def realtime_commands(script: str) -> frozenset[int]:
    """The command ids the control script's main loop treats as real-time (its ``if cmd == a or ...`` line)."""
    lines = script.splitlines()
    for i, line in enumerate(lines):
        if line.strip().startswith("while keep_running"):
            for candidate in lines[i + 1:i + 4]:
                if _REALTIME_LINE.match(candidate):
                    return frozenset(int(n) for n in re.findall(r"cmd\s*==\s*(\d+)", candidate))
    return REALTIME_COMMANDS


class Controller:
    """Registers, robot state, the emulated control script and the arm; thread-safe.

    ``tick()`` advances one 2 ms control period.
    """

    def __init__(self, arm: Arm, clock: Callable[[], float] = time.monotonic, *,
                 protective_unlock_delay_s: float = PROTECTIVE_UNLOCK_DELAY_S) -> None:
        self.lock = threading.RLock()
        self.arm = arm
        self.clock = clock
        self.start_time = clock()
        self.timestamp = 0.0
        self.input_int = [0] * N_REGISTERS
        self.input_double = [0.0] * N_REGISTERS
        self.input_bits = [False] * 128
        self.output_int = [0] * N_REGISTERS
        self.output_double = [0.0] * N_REGISTERS
        self.output_bits = [False] * 128
        self.inputs: dict[str, Any] = {}  # other input variables, as last written
        self.robot_mode = ROBOT_MODE_RUNNING
        self.safety_mode = SAFETY_MODE_NORMAL
        self.safety_status_bits = SAFETY_NORMAL
        self.runtime_state = RUNTIME_STOPPED
        self.script: str | None = None  # the program text last uploaded
        self.scripts_received = 0
        self.script_running = False
        self.register_offset = 0
        self.executing = False
        self.realtime = REALTIME_COMMANDS
        self.watchdog_hz = 0.0
        self.watchdog_variable = ""
        self.watchdog_last = 0.0
        self.commands: dict[int, int] = {}  # command id -> how often the script processed it
        self.messages: list[str] = []
        # Faults (see "Fault injection" in the module's docstring).
        self.protective_unlock_delay_s = protective_unlock_delay_s
        self.protective_since = 0.0
        self.power_off_at_rest = False
        self.stall_until = 0.0
        # Hostile reports: (joint, rad, seconds) of an offset, seconds of a freeze, armed for the next speedJ.
        self.offset_joint = 0
        self.offset_rad = 0.0
        self.offset_until = 0.0
        self.freeze_until = 0.0
        self.nan_joint = 0
        self.nan_until = 0.0
        self.armed: list[tuple[str, tuple[float, ...]]] = []
        self.faults: list[dict[str, Any]] = []
        # (receipt time, value) of every change of the command register, and motion commands received
        self.command_changes: collections.deque[tuple[float, int]] = collections.deque(maxlen=20000)
        self.motion_writes = 0

    # -- the program ---------------------------------------------------------------------
    def load_script(self, text: str) -> None:
        """A program arrived on the script port: (re)start the emulated control script.

        As a real controller, it runs only on a powered arm with its brakes
        released and no safety stop in force; otherwise it is refused.
        """
        with self.lock:
            self.script = text
            self.scripts_received += 1
            if not self.can_run():
                log.warning("control script received but not started: robot mode %s, safety mode %s",
                            ROBOT_MODE_NAMES.get(self.robot_mode, self.robot_mode),
                            SAFETY_MODE_NAMES.get(self.safety_mode, self.safety_mode))
                return
            now = self.clock()
            for fault in self.faults:
                if fault["cleared_t"] is None:
                    fault["cleared_t"] = now
            offset = 0
            for line in text.splitlines():  # ur_rtde injects the offset: "global reg_offset_int = 24"
                if line.strip().startswith("global reg_offset_int"):
                    try:
                        offset = int(line.split("=", 1)[1].strip())
                    except ValueError:
                        offset = 0
            self.register_offset = offset if offset in (0, 24) else 0
            self.realtime = realtime_commands(text)
            self.watchdog_hz = 0.0
            self.executing = False
            self.script_running = True
            self.runtime_state = RUNTIME_PLAYING
            self.output_int[self.register_offset] = SCRIPT_READY
            log.info("control script received (%d characters, register offset %d): running",
                     len(text), self.register_offset)

    def can_run(self) -> bool:
        return self.robot_mode == ROBOT_MODE_RUNNING and self.safety_mode == SAFETY_MODE_NORMAL

    # -- faults --------------------------------------------------------------------------
    def fault(self, name: str) -> dict[str, Any]:
        """Record a fault: when it happened, when the arm came to rest, motion commands received until cleared."""
        with self.lock:
            record: dict[str, Any] = {"fault": name, "t": self.clock(), "rest_t": None, "cleared_t": None,
                                      "motion_writes": 0, "last_motion_t": None, "q": self.arm.q.tolist()}
            self.faults.append(record)
            return record

    def protective_stop(self, reason: str = "injected") -> None:
        """A protective stop: safety bits set, the arm decelerates to rest, the control script stops."""
        with self.lock:
            self.safety_mode = SAFETY_MODE_PROTECTIVE_STOP
            self.safety_status_bits = SAFETY_PROTECTIVE_STOPPED | SAFETY_STOPPED_DUE_TO_SAFETY
            self.protective_since = self.clock()
            self.fault("protective_stop")
            self.stop_script(f"protective stop ({reason})")

    def unlock_protective_stop(self) -> str:
        """The dashboard's ``unlock protective stop`` (refused within 5 s of the stop, as on e-Series)."""
        with self.lock:
            if self.safety_mode == SAFETY_MODE_PROTECTIVE_STOP:
                if self.clock() - self.protective_since < self.protective_unlock_delay_s:
                    return (f"Cannot unlock protective stop until {self.protective_unlock_delay_s:g}s after "
                            "occurrence. Always inspect cause of protective stop before unlocking")
                self.safety_mode = SAFETY_MODE_NORMAL
                self.safety_status_bits = SAFETY_NORMAL
                log.info("protective stop unlocked")
            return "Protective stop releasing"

    def emergency_stop(self) -> None:
        """The emergency stop pressed: the arm stops (category 1), then its power is removed."""
        with self.lock:
            self.safety_mode = SAFETY_MODE_ROBOT_EMERGENCY_STOP
            self.safety_status_bits = (SAFETY_EMERGENCY_STOPPED | SAFETY_ROBOT_EMERGENCY_STOPPED
                                       | SAFETY_STOPPED_DUE_TO_SAFETY)
            self.power_off_at_rest = True
            self.fault("emergency_stop")
            self.stop_script("emergency stop")

    def release_emergency_stop(self) -> str:
        """The emergency stop button released: safety normal again, the arm stays powered off."""
        with self.lock:
            if self.safety_mode != SAFETY_MODE_ROBOT_EMERGENCY_STOP:
                return "not emergency stopped"
            self.safety_mode = SAFETY_MODE_NORMAL
            self.safety_status_bits = SAFETY_NORMAL
            log.info("emergency stop released: power on and release the brakes to run again")
            return "emergency stop released"

    def power_on(self) -> str:
        with self.lock:
            if self.safety_mode == SAFETY_MODE_ROBOT_EMERGENCY_STOP:
                return "Failed to execute: power on (emergency stopped)"
            if self.robot_mode == ROBOT_MODE_POWER_OFF and not self.power_off_at_rest:
                self.robot_mode = ROBOT_MODE_IDLE
            return "Powering on"

    def brake_release(self) -> str:
        with self.lock:
            if self.robot_mode == ROBOT_MODE_IDLE:
                self.robot_mode = ROBOT_MODE_RUNNING
            return "Brake releasing"

    def power_off(self) -> str:
        with self.lock:
            if self.robot_mode != ROBOT_MODE_POWER_OFF:
                self.fault("power_off")
                self.power_off_at_rest = True
                self.stop_script("power off")
            return "Powering off"

    def stall(self, seconds: float) -> None:
        """Ignore RTDE input for ``seconds``, as if the bridge had gone silent (hung, starved, network)."""
        with self.lock:
            self.stall_until = self.clock() + seconds
            self.fault("stall")

    def offset(self, joint: int, rad: float, seconds: float, at_speedj: bool = False) -> None:
        """Report joint ``joint``'s position ``rad`` off for ``seconds`` (the arm itself is not moved)."""
        if not 0 <= joint < 6 or not math.isfinite(rad) or not 0.0 < seconds < 600.0:
            raise ValueError(f"offset: joint 0-5, a finite offset and 0-600 s (got {joint}, {rad}, {seconds})")
        with self.lock:
            if at_speedj:
                self.armed.append(("offset", (joint, rad, seconds)))
                return
            self.offset_joint, self.offset_rad = joint, rad
            self.offset_until = self.clock() + seconds
            self._hostile("offset", seconds, joint=joint, rad=rad)

    def freeze(self, seconds: float, at_speedj: bool = False) -> None:
        """Send no RTDE data for ``seconds``, the connections open."""
        if not 0.0 < seconds < 600.0:
            raise ValueError(f"freeze: 0-600 s (got {seconds})")
        with self.lock:
            if at_speedj:
                self.armed.append(("freeze", (seconds,)))
                return
            self.freeze_until = self.clock() + seconds
            self._hostile("freeze", seconds)

    def nan(self, joint: int, seconds: float) -> None:
        """Report joint ``joint``'s position and speed as NaN for ``seconds``."""
        if not 0 <= joint < 6 or not 0.0 < seconds < 600.0:
            raise ValueError(f"nan: joint 0-5 and 0-600 s (got {joint}, {seconds})")
        with self.lock:
            self.nan_joint = joint
            self.nan_until = self.clock() + seconds
            self._hostile("nan", seconds, joint=joint)

    def frozen(self) -> bool:
        return self.clock() < self.freeze_until

    def _hostile(self, name: str, seconds: float, **extra: Any) -> None:
        record = self.fault(name)
        record.update(extra, seconds=seconds, end_t=record["t"] + seconds, peak_qd=[0.0] * 6,
                      track=[[record["t"], *self.arm.q.tolist()]])

    def stop_script(self, reason: str) -> None:
        with self.lock:
            if self.script_running:
                log.info("control script stopped: %s", reason)
            self.script_running = False
            self.runtime_state = RUNTIME_STOPPED
            self.watchdog_hz = 0.0
            self.output_int[self.register_offset] = 0
            self.arm.stop(float(np.max(self.arm.limits.a_max)))

    # -- registers -----------------------------------------------------------------------
    def write_inputs(self, names: Sequence[str], values: Sequence[Any]) -> None:
        with self.lock:
            now = self.clock()
            if now < self.stall_until:
                return
            command = f"input_int_register_{self.register_offset}"
            for name, value in zip(names, values, strict=True):
                if name == command:
                    self._log_command(now, int(value))
                if (i := _register(name, "input_int_register_", 0, N_REGISTERS - 1)) is not None:
                    self.input_int[i] = int(value)
                elif (i := _register(name, "input_double_register_", 0, N_REGISTERS - 1)) is not None:
                    self.input_double[i] = float(value)
                elif (i := _register(name, "input_bit_register_", 64, 127)) is not None:
                    self.input_bits[i] = bool(value)
                elif name == "input_bit_registers0_to_31":
                    self.input_bits[0:32] = [bool(int(value) >> b & 1) for b in range(32)]
                elif name == "input_bit_registers32_to_63":
                    self.input_bits[32:64] = [bool(int(value) >> b & 1) for b in range(32)]
                else:
                    self.inputs[name] = value
                if name == self.watchdog_variable:
                    self.watchdog_last = now

    def _log_command(self, now: float, value: int) -> None:
        if not self.command_changes or self.command_changes[-1][1] != value:
            self.command_changes.append((now, value))
        if value == CMD_SPEEDJ and self.armed:
            armed, self.armed = self.armed, []
            for name, args in armed:
                if name == "offset":
                    self.offset(int(args[0]), args[1], args[2])
                else:
                    self.freeze(args[0])
        if value in (CMD_SERVOJ, CMD_SPEEDJ):
            self.motion_writes += 1
            for fault in self.faults:
                if fault["cleared_t"] is None:
                    fault["motion_writes"] += 1
                    fault["last_motion_t"] = now

    def state(self) -> dict[str, Any]:
        """The controller's state for a test or an operator (the control port's ``state``)."""
        with self.lock:
            return {
                "t": self.clock(), "q": self.arm.q.tolist(), "qd": self.arm.qd.tolist(), "arm_mode": self.arm.mode,
                "at_rest": not bool(np.any(self.arm.qd)), "robot_mode": self.robot_mode,
                "safety_mode": self.safety_mode, "safety_status_bits": self.safety_status_bits,
                "script_running": self.script_running, "scripts_received": self.scripts_received,
                "watchdog_hz": self.watchdog_hz, "motion_writes": self.motion_writes,
                "commands": {str(k): v for k, v in self.commands.items()},
                # the control script's command handshake: what the client wrote, what the script answers
                "command_register": self.input_int[self.register_offset],
                "answer_register": self.output_int[self.register_offset], "executing": self.executing,
                "faults": [dict(f) for f in self.faults],
                "command_changes": [list(c) for c in self.command_changes],
            }

    def read_outputs(self, names: Sequence[str]) -> list[Any]:
        with self.lock:
            return [self._output(name) for name in names]

    def _output(self, name: str) -> Any:
        arm = self.arm
        simple: dict[str, Any] = {
            "timestamp": self.timestamp,
            "target_q": arm.target_q.tolist(), "target_qd": arm.target_qd.tolist(), "target_qdd": arm.qdd.tolist(),
            "actual_q": self._reported_q(), "actual_qd": self._reported_qd(),
            "actual_TCP_pose": arm.tcp_pose.tolist(), "target_TCP_pose": arm.tcp_pose.tolist(),
            "actual_TCP_speed": arm.tcp_speed.tolist(), "target_TCP_speed": arm.tcp_speed.tolist(),
            "robot_mode": self.robot_mode, "safety_mode": self.safety_mode, "safety_status": self.safety_mode,
            "safety_status_bits": self.safety_status_bits,
            "robot_status_bits": ((ROBOT_STATUS_POWER_ON if self.robot_mode != ROBOT_MODE_POWER_OFF else 0)
                                  | (ROBOT_STATUS_PROGRAM_RUNNING if self.script_running else 0)),
            "runtime_state": self.runtime_state,
            "joint_mode": [JOINT_MODE_RUNNING] * 6, "speed_scaling": 1.0, "target_speed_fraction": 1.0,
            "joint_temperatures": [30.0] * 6, "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0,
            "actual_joint_voltage": [48.0] * 6, "actual_execution_time": 0.1, "tool_temperature": 30.0,
            "actual_tool_accelerometer": [0.0, 0.0, -9.81],
            "output_bit_registers0_to_31": _bits(self.output_bits[0:32]),
            "output_bit_registers32_to_63": _bits(self.output_bits[32:64]),
            "input_bit_registers0_to_31": _bits(self.input_bits[0:32]),
            "input_bit_registers32_to_63": _bits(self.input_bits[32:64]),
        }
        if name in simple:
            return simple[name]
        for prefix, table in (("output_int_register_", self.output_int), ("input_int_register_", self.input_int),
                              ("output_double_register_", self.output_double),
                              ("input_double_register_", self.input_double)):
            if (i := _register(name, prefix, 0, N_REGISTERS - 1)) is not None:
                return table[i]
        for prefix, bits in (("output_bit_register_", self.output_bits), ("input_bit_register_", self.input_bits)):
            if (i := _register(name, prefix, 64, 127)) is not None:
                return bits[i]
        kind = _OUTPUT_TYPES[name]  # everything not simulated: zeros
        return [0] * _VECTOR_SIZES[kind] if kind in _VECTOR_SIZES else 0

    def _reported_q(self) -> list[float]:
        q = self.arm.q.tolist()
        if self.clock() < self.offset_until:
            q[self.offset_joint] += self.offset_rad
        if self.clock() < self.nan_until:
            q[self.nan_joint] = math.nan
        return q

    def _reported_qd(self) -> list[float]:
        qd = self.arm.qd.tolist()
        if self.clock() < self.nan_until:
            qd[self.nan_joint] = math.nan
        return qd

    # -- control -------------------------------------------------------------------------
    def tick(self, dt: float = DT) -> None:
        with self.lock:
            self.timestamp = self.clock() - self.start_time
            if self.script_running:
                self._script_step()
            if (self.script_running and self.watchdog_hz > 0.0
                    and self.clock() - self.watchdog_last > 1.0 / self.watchdog_hz):
                self.fault("watchdog")
                self.stop_script(f"RTDE watchdog: {self.watchdog_variable} not updated for "
                                 f"{1e3 / self.watchdog_hz:.0f} ms")
            self.arm.step(dt)
            now = self.clock()
            for record in self.faults:  # the true arm under a hostile report, until 1 s after it ended
                if "track" in record and now <= record["end_t"] + 1.0:
                    record["peak_qd"] = np.maximum(record["peak_qd"], np.abs(self.arm.qd)).tolist()
                    record["ticks"] = record.get("ticks", 0) + 1
                    if record["ticks"] % 2 == 0:  # every other period of the arm's (a small state)
                        record["track"].append([now, *self.arm.q.tolist()])
            if not np.any(self.arm.qd):
                if self.power_off_at_rest:
                    self.power_off_at_rest = False
                    self.robot_mode = ROBOT_MODE_POWER_OFF
                for fault in self.faults:
                    if fault["rest_t"] is None:
                        fault["rest_t"] = self.clock()
                        fault["q_rest"] = self.arm.q.tolist()

    def _script_step(self) -> None:
        """One pass of the control script's main loop (see ur_rtde's rtde_control.script)."""
        o = self.register_offset
        cmd = self.input_int[o]
        if cmd in self.realtime:
            self._process(cmd)
            self.output_int[o] = SCRIPT_READY
        elif cmd == CMD_NONE:
            self.executing = False
            self.output_int[o] = SCRIPT_READY
        elif not self.executing:
            keep = self._process(cmd)
            self.executing = True
            if keep:
                self.output_int[o] = SCRIPT_DONE
            else:
                self.stop_script("stopScript()")

    def _arg(self, i: int) -> float:
        return self.input_double[self.register_offset + i]

    def _process(self, cmd: int) -> bool:
        """Execute one command; False ends the script."""
        self.commands[cmd] = self.commands.get(cmd, 0) + 1
        arm = self.arm
        if cmd == CMD_SERVOJ:
            # q in registers 0..5, speed 6, acceleration 7, time 8, lookahead time 9, gain 10
            arm.servo([self._arg(i) for i in range(6)], self._arg(9), self._arg(10))
        elif cmd == CMD_SPEEDJ:
            # qd in registers 0..5, acceleration 6, time 7
            arm.speed([self._arg(i) for i in range(6)], self._arg(6))
        elif cmd in (CMD_SERVO_STOP, CMD_SPEED_STOP, CMD_STOPJ):
            arm.stop(self._arg(0))
        elif cmd == CMD_SET_WATCHDOG:
            self.watchdog_hz = max(0.0, self._arg(0))
            self.watchdog_variable = f"input_int_register_{self.register_offset}"
            self.watchdog_last = self.clock()
            log.info("RTDE watchdog on %s at %g Hz", self.watchdog_variable, self.watchdog_hz)
        elif cmd == CMD_STOP_SCRIPT:
            return False
        elif cmd != CMD_WATCHDOG:
            log.debug("control script command %d acknowledged without effect", cmd)
        return True


def _bits(bits: Sequence[bool]) -> int:
    return sum(1 << i for i, bit in enumerate(bits) if bit)


# --------------------------------------------------------------------------- RTDE sessions


@dataclasses.dataclass
class Recipe:
    recipe_id: int
    names: list[str]
    types: list[str]
    frequency: float = 0.0


class RtdeSession:
    """One RTDE client's protocol state, socket-free: packages in, reply bytes out.

    ``claims`` is shared by every session of a server: which session writes
    which input variable (the controller refuses a second writer with IN_USE).
    """

    def __init__(self, controller: Controller, claims: dict[str, int], claims_lock: threading.Lock) -> None:
        self.controller = controller
        self.claims = claims
        self.claims_lock = claims_lock
        self.protocol = 1
        self.outputs: dict[int, Recipe] = {}
        self.inputs: dict[int, Recipe] = {}
        self.started = False
        # Input and output recipes are numbered apart, each from 1 (ur_rtde relies on it).
        self.next_output = 1
        self.next_input = 1

    def handle(self, command: int, payload: bytes) -> bytes:
        """React to one package; return the reply (possibly empty)."""
        if command == REQUEST_PROTOCOL_VERSION:
            version = parse_protocol_version(payload)
            accepted = version in (1, 2)
            if accepted:
                self.protocol = version
            return pack_bool_reply(command, accepted)
        if command == GET_URCONTROL_VERSION:
            return pack_controller_version()
        if command == CONTROL_PACKAGE_SETUP_OUTPUTS:
            if self.protocol >= 2:
                frequency, names = parse_setup_outputs(payload)
            else:
                frequency, names = 125.0, _names(payload, "SETUP_OUTPUTS")
            types = [variable_type(name, "output") or NOT_FOUND for name in names]
            if NOT_FOUND in types or not 0.0 < frequency <= MAX_FREQUENCY_HZ or self.started:
                log.warning("output recipe refused (frequency %g Hz, started %s): %s", frequency, self.started,
                            [n for n, t in zip(names, types, strict=True) if t == NOT_FOUND])
                return pack_setup_reply(command, 0, types)
            recipe = Recipe(self.next_output, names, types, frequency)
            self.next_output += 1
            self.outputs = {recipe.recipe_id: recipe}  # one output recipe per connection: the newest
            return pack_setup_reply(command, recipe.recipe_id, types)
        if command == CONTROL_PACKAGE_SETUP_INPUTS:
            names = parse_setup_inputs(payload)
            types = [variable_type(name, "input") or NOT_FOUND for name in names]
            with self.claims_lock:
                for i, name in enumerate(names):
                    if types[i] != NOT_FOUND and self.claims.get(name, id(self)) != id(self):
                        types[i] = IN_USE
                ok = NOT_FOUND not in types and IN_USE not in types and not self.started
                if ok:
                    for name in names:
                        self.claims[name] = id(self)
            if not ok:
                log.warning("input recipe refused: %s", dict(zip(names, types, strict=True)))
                return pack_setup_reply(command, 0, types)
            recipe = Recipe(self.next_input, names, types)
            self.next_input += 1
            self.inputs[recipe.recipe_id] = recipe
            return pack_setup_reply(command, recipe.recipe_id, types)
        if command == CONTROL_PACKAGE_START:
            self.started = bool(self.outputs) or bool(self.inputs)
            return pack_bool_reply(command, self.started)
        if command == CONTROL_PACKAGE_PAUSE:
            self.started = False
            return pack_bool_reply(command, True)
        if command == DATA_PACKAGE:
            given = self.inputs.get(data_recipe_id(payload))
            if given is None:
                raise RtdeProtocolError(f"DATA_PACKAGE for unknown input recipe {data_recipe_id(payload)}")
            if self.started:
                self.controller.write_inputs(given.names, unpack_data(payload, given.types))
            return b""
        if command == TEXT_MESSAGE:
            message, source, level = parse_text_message(payload)
            log.info("text message from %s (level %d): %s", source, level, message)
            self.controller.messages.append(message)
            return b""
        raise RtdeProtocolError(f"unexpected command {command}")

    def data_packages(self) -> bytes:
        """The output DATA_PACKAGEs of the current state."""
        out = b""
        for recipe in self.outputs.values():
            out += pack_data(recipe.recipe_id, recipe.types, self.controller.read_outputs(recipe.names))
        return out

    def release(self) -> None:
        with self.claims_lock:
            for name in [n for n, owner in self.claims.items() if owner == id(self)]:
                del self.claims[name]


# --------------------------------------------------------------------------- dashboard

POLYSCOPE_VERSION = "URSoftware 5.15.0.0 (emulated)"


class Dashboard:
    """The dashboard server's answers, socket-free."""

    welcome = "Connected: Universal Robots Dashboard Server"

    def __init__(self, controller: Controller) -> None:
        self.controller = controller
        self.loaded = "<unnamed>"

    def answer(self, line: str) -> str:
        c = self.controller
        command = line.strip()
        lower = command.lower()
        if lower == "polyscopeversion":
            return POLYSCOPE_VERSION
        if lower == "version":
            return ".".join(map(str, CONTROLLER_VERSION))
        if lower == "robotmode":
            return f"Robotmode: {ROBOT_MODE_NAMES.get(c.robot_mode, c.robot_mode)}"
        if lower == "safetymode":
            return f"Safetymode: {SAFETY_MODE_NAMES.get(c.safety_mode, c.safety_mode)}"
        if lower == "safetystatus":
            return f"Safetystatus: {SAFETY_MODE_NAMES.get(c.safety_mode, c.safety_mode)}"
        if lower == "is in remote control":
            return "true"
        if lower == "programstate":
            return f"{'PLAYING' if c.script_running else 'STOPPED'} {self.loaded}"
        if lower == "running":
            return f"Program running: {'true' if c.script_running else 'false'}"
        if lower == "get loaded program":
            return f"Loaded program: {self.loaded}"
        if lower == "stop":
            c.stop_script("dashboard stop")
            return "Stopped"
        if lower == "pause":
            return "Pausing program"
        if lower == "play":
            return "Failed to execute: play"
        if lower.startswith("load "):
            return f"File not found: {command[5:]}"
        if lower == "power on":
            return c.power_on()
        if lower == "power off":
            return c.power_off()
        if lower == "brake release":
            return c.brake_release()
        if lower == "unlock protective stop":
            return c.unlock_protective_stop()
        if lower in ("close popup", "close safety popup", "clear operational mode"):
            return {"close popup": "closing popup", "close safety popup": "closing safety popup",
                    "clear operational mode": "No longer controlling the operational mode. "}[lower]
        if lower == "isprogramsaved":
            return f"true {self.loaded}"
        if lower == "get operational mode":
            return "NONE"
        if lower == "get serial number":
            return "20200000000"
        if lower == "get robot model":
            return "UR10"
        if lower == "quit":
            return "Disconnected"
        return f"could not understand: '{command}'"


# --------------------------------------------------------------------------- sockets


class Emulator:
    """The controller thread and the three TCP servers."""

    def __init__(self, host: str = "127.0.0.1", rtde_port: int = 30004, dashboard_port: int = 29999,
                 script_ports: Sequence[int] = (30003,), controller: Controller | None = None,
                 control_port: int | None = None) -> None:
        self.host = host
        self.controller = controller or Controller(ur10e_arm())
        self.stopping = threading.Event()
        self.connections: set[socket.socket] = set()
        self.connections_lock = threading.Lock()
        self.refuse_until = 0.0
        self.claims: dict[str, int] = {}
        self.claims_lock = threading.Lock()
        self.threads: list[threading.Thread] = []
        self.listeners: list[socket.socket] = []
        self.ports = {"rtde": rtde_port, "dashboard": dashboard_port}
        servers: list[tuple[str, str, int, Callable[[socket.socket], None]]] = [
            (host, "rtde", rtde_port, self._serve_rtde), (host, "dashboard", dashboard_port, self._serve_dashboard),
            *[(host, f"script{p}", p, self._serve_script) for p in script_ports]]
        if control_port is not None:  # fault injection: on the loopback only, whatever --host says
            servers.append(("127.0.0.1", "control", control_port, self._serve_control))
        for address, name, port, serve in servers:
            listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((address, port))
            listener.listen(8)
            listener.settimeout(0.2)
            self.listeners.append(listener)
            self.ports[name] = listener.getsockname()[1]
            self._spawn(self._accept, listener, serve, name=f"accept-{name}")

    def _spawn(self, target: Callable[..., None], *args: Any, name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        self.threads.append(thread)

    def start(self) -> None:
        self._spawn(self._control_loop, name="controller")
        log.info("UR emulator on %s: %s", self.host, ", ".join(f"{k} {v}" for k, v in self.ports.items()))

    def close(self) -> None:
        self.stopping.set()
        for listener in self.listeners:
            listener.close()
        for thread in self.threads:
            thread.join(timeout=2.0)

    def _control_loop(self) -> None:
        next_tick = time.monotonic()
        while not self.stopping.is_set():
            self.controller.tick(DT)
            next_tick += DT
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -0.1:
                next_tick = time.monotonic()  # overrun: do not try to catch up

    def _accept(self, listener: socket.socket, serve: Callable[[socket.socket], None]) -> None:
        while not self.stopping.is_set():
            try:
                conn, peer = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            if time.monotonic() < self.refuse_until and serve != self._serve_control:
                conn.close()  # the controller is "unreachable"
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.2)
            log.info("%s: connection from %s:%d", threading.current_thread().name, *peer[:2])
            self._spawn(self._guarded, serve, conn, name=f"{threading.current_thread().name}-{peer[1]}")

    def _guarded(self, serve: Callable[[socket.socket], None], conn: socket.socket) -> None:
        if serve != self._serve_control:
            with self.connections_lock:
                self.connections.add(conn)
        try:
            with conn:
                serve(conn)
        except (OSError, RtdeProtocolError) as exc:
            log.info("%s: connection closed (%s)", threading.current_thread().name, exc)
        finally:
            with self.connections_lock:
                self.connections.discard(conn)

    def drop(self, refuse_s: float = 0.0) -> int:
        """Close every RTDE, dashboard and script connection; refuse new ones for ``refuse_s``."""
        self.refuse_until = time.monotonic() + refuse_s
        self.controller.fault("drop")
        with self.connections_lock:
            dropped = list(self.connections)
        for conn in dropped:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        log.warning("dropped %d connection(s); refusing new ones for %.1f s", len(dropped), refuse_s)
        return len(dropped)

    def control(self, line: str) -> str:
        """One fault-injection command (see the module's docstring); anything else goes to the dashboard."""
        c = self.controller
        words = line.strip().lower().split()
        command = " ".join(words)
        try:
            if command == "state":
                return json.dumps(c.state())
            if command == "protective stop":
                c.protective_stop()
                return "protective stop"
            if command == "emergency stop":
                c.emergency_stop()
                return "emergency stop"
            if command == "release emergency stop":
                return c.release_emergency_stop()
            if command == "stop program":
                with c.lock:
                    c.fault("script_stopped")
                    c.stop_script("stopped at the pendant")
                return "Stopped"
            if words[:1] == ["drop"]:
                return f"dropped {self.drop(float(words[1]) if len(words) > 1 else 0.0)}"
            if words[:1] == ["offset"] and len(words) in (4, 5) and words[4:] in ([], ["speedj"]):
                c.offset(int(words[1]), float(words[2]), float(words[3]), at_speedj=len(words) == 5)
                return f"offset joint {words[1]} by {float(words[2]):g} rad for {float(words[3]):g} s" + (
                    " from the next speedJ" if len(words) == 5 else "")
            if words[:1] == ["freeze"] and len(words) in (2, 3) and words[2:] in ([], ["speedj"]):
                c.freeze(float(words[1]), at_speedj=len(words) == 3)
                return f"freezing RTDE output for {float(words[1]):g} s" + (
                    " from the next speedJ" if len(words) == 3 else "")
            if words[:1] == ["nan"] and len(words) == 3:
                c.nan(int(words[1]), float(words[2]))
                return f"joint {words[1]} reported NaN for {float(words[2]):g} s"
            if words[:1] == ["stall"] and len(words) == 2:
                c.stall(float(words[1]))
                return f"stalling RTDE input for {float(words[1]):g} s"
        except ValueError as exc:
            return f"error: {exc}"
        return Dashboard(c).answer(line)

    def _serve_control(self, conn: socket.socket) -> None:
        self._serve_lines(conn, self.control, "control")

    def _serve_lines(self, conn: socket.socket, answer: Callable[[str], str], what: str) -> None:
        """A line-based server (the dashboard, the control port): one answer a line, logged (not ``state``)."""
        buffer = b""
        while not self.stopping.is_set():
            data = self._recv(conn)
            if data is None:
                return
            buffer += data
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                text = line.decode("utf-8", "replace")
                reply = answer(text)
                if text.strip().lower() != "state":
                    log.info("%s: %r -> %r", what, text, reply)
                conn.sendall((reply + "\n").encode())

    def _recv(self, conn: socket.socket) -> bytes | None:
        """Bytes received, b'' on a timeout, None once the peer closed."""
        try:
            data = conn.recv(65536)
        except TimeoutError:
            return b""
        return data or None

    def _serve_rtde(self, conn: socket.socket) -> None:
        session = RtdeSession(self.controller, self.claims, self.claims_lock)
        send_lock = threading.Lock()
        closed = threading.Event()

        def sender() -> None:
            next_send = time.monotonic()
            while not (closed.is_set() or self.stopping.is_set()):
                period = 1.0 / MAX_FREQUENCY_HZ
                if session.started and session.outputs and not self.controller.frozen():
                    period = 1.0 / next(iter(session.outputs.values())).frequency
                    data = session.data_packages()
                    try:
                        with send_lock:
                            conn.sendall(data)
                    except OSError:
                        closed.set()
                        return
                next_send += period
                delay = next_send - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    next_send = time.monotonic()

        self._spawn(sender, name=f"{threading.current_thread().name}-out")
        buffer = b""
        try:
            while not (closed.is_set() or self.stopping.is_set()):
                data = self._recv(conn)
                if data is None:
                    break
                packages, buffer = split_packages(buffer + data)
                for command, payload in packages:
                    reply = session.handle(command, payload)
                    if reply:
                        with send_lock:
                            conn.sendall(reply)
        finally:
            closed.set()
            session.release()

    def _serve_dashboard(self, conn: socket.socket) -> None:
        dashboard = Dashboard(self.controller)
        conn.sendall((dashboard.welcome + "\n").encode())
        self._serve_lines(conn, dashboard.answer, "dashboard")

    def _serve_script(self, conn: socket.socket) -> None:
        """Collects programs: a program is complete at a top-level ``end`` or after 100 ms of silence."""
        buffer = ""
        last = time.monotonic()
        while not self.stopping.is_set():
            data = self._recv(conn)
            if data is None:
                break
            if data:
                buffer += data.decode("utf-8", "replace")
                last = time.monotonic()
                program, buffer = take_program(buffer)
                if program is not None:
                    self._run_program(program)
            elif buffer.strip() and time.monotonic() - last > 0.1:
                self._run_program(buffer)
                buffer = ""
        if buffer.strip():
            self._run_program(buffer)

    def _run_program(self, text: str) -> None:
        if text.lstrip().startswith(("def ", "sec ")):
            self.controller.load_script(text)
        else:
            log.info("script port: one-off script statements ignored: %r", text.strip()[:200])


def take_program(buffer: str) -> tuple[str | None, str]:
    """Split off a complete top-level program (``def``/``sec`` ... ``end`` at column 0)."""
    lines = buffer.splitlines(keepends=True)
    started = False
    for i, line in enumerate(lines):
        if line.startswith(("def ", "sec ")):
            started = True
        elif started and line.rstrip() == "end" and line.endswith("\n"):
            return "".join(lines[:i + 1]), "".join(lines[i + 1:])
    return None, buffer


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nwr.services.tools.hardware.ur_emulator",
                                     description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--rtde-port", type=int, default=30004, help="ur_rtde always uses 30004")
    parser.add_argument("--dashboard-port", type=int, default=29999, help="ur_rtde's control interface uses 29999")
    parser.add_argument("--script-port", type=int, action="append",
                        help="where programs are accepted (repeatable; default 30003, ur_rtde's choice)")
    parser.add_argument("--q0", type=float, nargs=6, metavar="RAD", help="initial joint positions (default: home)")
    parser.add_argument("--control-port", type=int, metavar="PORT",
                        help="fault injection: a line-based control port on 127.0.0.1 (see the docstring)")
    parser.add_argument("--protective-unlock-delay", type=float, default=PROTECTIVE_UNLOCK_DELAY_S, metavar="S",
                        help="'unlock protective stop' is refused this long after the stop (e-Series: 5 s)")
    parser.add_argument("--verbose", "-v", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(threadName)s: %(message)s")
    emulator = Emulator(args.host, args.rtde_port, args.dashboard_port, args.script_port or [30003],
                        Controller(ur10e_arm(args.q0), protective_unlock_delay_s=args.protective_unlock_delay),
                        control_port=args.control_port)
    emulator.start()
    print(f"ready {emulator.ports}", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        emulator.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
