"""The RTDE protocol as a UR e-Series controller speaks it (version 2): packages, recipes, the variables
and registers a client may ask for; pure, no sockets (:mod:`.ur_emulator` serves it)."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any

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
