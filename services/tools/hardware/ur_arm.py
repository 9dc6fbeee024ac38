"""The emulated arm: a kinematic 6-joint arm integrated at the e-Series period within its limits, its
robot and safety modes, and the packaged UR10e's (:func:`ur10e_arm`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np

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
