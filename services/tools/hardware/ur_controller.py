"""The emulated controller: the control script ur_rtde uploads, run as its main loop would (servoJ,
speedJ, the stops, the watchdog), the registers it reads and writes, and the faults a test injects."""

from __future__ import annotations

import collections
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from nwr.services.tools.hardware.rtde import (
    _OUTPUT_TYPES,
    _VECTOR_SIZES,
    N_REGISTERS,
    _register,
)
from nwr.services.tools.hardware.ur_arm import (
    DT,
    JOINT_MODE_RUNNING,
    PROTECTIVE_UNLOCK_DELAY_S,
    ROBOT_MODE_IDLE,
    ROBOT_MODE_NAMES,
    ROBOT_MODE_POWER_OFF,
    ROBOT_MODE_RUNNING,
    ROBOT_STATUS_POWER_ON,
    ROBOT_STATUS_PROGRAM_RUNNING,
    RUNTIME_PLAYING,
    RUNTIME_STOPPED,
    SAFETY_EMERGENCY_STOPPED,
    SAFETY_MODE_NAMES,
    SAFETY_MODE_NORMAL,
    SAFETY_MODE_PROTECTIVE_STOP,
    SAFETY_MODE_ROBOT_EMERGENCY_STOP,
    SAFETY_NORMAL,
    SAFETY_PROTECTIVE_STOPPED,
    SAFETY_ROBOT_EMERGENCY_STOPPED,
    SAFETY_STOPPED_DUE_TO_SAFETY,
    Arm,
)

log = logging.getLogger(__name__)

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
#: What an armed hostile report waits for: the client's next write of a command of these ids ("write"), or the
#: client's acknowledgement of the control script's answer "done" to one ("done": the client has read the answer
#: and cleared the command; the report begins before the script's "ready" goes out).
ARMED_AT = {"speedj": ("write", frozenset({CMD_SPEEDJ})),
            "stop": ("done", frozenset({CMD_SERVO_STOP, CMD_SPEED_STOP, CMD_STOPJ}))}
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
        self.executed = 0  # the last non-real-time command the script executed
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
        # Hostile reports: (joint, rad, seconds) of an offset, seconds of a freeze; armed ones wait for the next
        # command of theirs (ARMED_AT) the client writes.
        self.offset_joint = 0
        self.offset_rad = 0.0
        self.offset_until = 0.0
        self.freeze_until = 0.0
        self.nan_joint = 0
        self.nan_until = 0.0
        self.armed: list[tuple[str, tuple[float, ...], str]] = []  # (report, its arguments, ARMED_AT key)
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

    def offset(self, joint: int, rad: float, seconds: float, at: str = "") -> None:
        """Report joint ``joint``'s position ``rad`` off for ``seconds`` (the arm itself is not moved); ``at`` (a
        key of :data:`ARMED_AT`): from the client's next such command rather than now."""
        if not 0 <= joint < 6 or not math.isfinite(rad) or not 0.0 < seconds < 600.0:
            raise ValueError(f"offset: joint 0-5, a finite offset and 0-600 s (got {joint}, {rad}, {seconds})")
        with self.lock:
            if at:
                self.armed.append(("offset", (joint, rad, seconds), _armed_at(at)))
                return
            self.offset_joint, self.offset_rad = joint, rad
            self.offset_until = self.clock() + seconds
            self._hostile("offset", seconds, joint=joint, rad=rad)

    def freeze(self, seconds: float, at: str = "") -> None:
        """Send no RTDE data for ``seconds``, the connections open; ``at`` as for :meth:`offset`
        (``stop``: once the client has read the control script's answer to a stop, before the script's "ready"
        goes out: its last report says busy, and ur_rtde's next command waits for its readiness through the
        frozen stream)."""
        if not 0.0 < seconds < 600.0:
            raise ValueError(f"freeze: 0-600 s (got {seconds})")
        with self.lock:
            if at:
                self.armed.append(("freeze", (seconds,), _armed_at(at)))
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
        self._fire("write", value)
        if value in (CMD_SERVOJ, CMD_SPEEDJ):
            self.motion_writes += 1
            for fault in self.faults:
                if fault["cleared_t"] is None:
                    fault["motion_writes"] += 1
                    fault["last_motion_t"] = now

    def _fire(self, event: str, command: int) -> None:
        """The armed hostile reports waiting for ``event`` ("write" or "done") of ``command`` begin."""
        fired = [(name, args) for name, args, at in self.armed if ARMED_AT[at][0] == event and command in
                 ARMED_AT[at][1]]
        if not fired:
            return
        self.armed = [a for a in self.armed if not (ARMED_AT[a[2]][0] == event and command in ARMED_AT[a[2]][1])]
        for name, args in fired:
            if name == "offset":
                self.offset(int(args[0]), args[1], args[2])
            else:
                self.freeze(args[0])

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
            if self.executing:  # the client read the answer to the command just done and cleared it
                self._fire("done", self.executed)
            self.executing = False
            self.output_int[o] = SCRIPT_READY
        elif not self.executing:
            keep = self._process(cmd)
            self.executing = True
            self.executed = cmd
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


def _armed_at(at: str) -> str:
    if at not in ARMED_AT:
        raise ValueError(f"armed at {at!r}: one of {', '.join(ARMED_AT)}")
    return at


def _bits(bits: Sequence[bool]) -> int:
    return sum(1 << i for i, bit in enumerate(bits) if bit)
