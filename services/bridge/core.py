"""Robot bridge core: the last check before the arm, and the simulated arm.

:func:`check_command` is the one pure function every command passes: it
rejects what cannot be trusted (wrong owner, wrong length, non-finite
numbers) and returns the reason. :class:`SimArm` integrates accepted
commands at the control rate within the joint position, speed and
acceleration limits, clipping (and counting) whatever exceeds them, and
decelerates to rest within the acceleration limit when commands go stale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nwr.common import messages as m


@dataclass(frozen=True)
class Limits:
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray


def check_command(cmd: m.Command, active: str, n: int) -> str | None:
    """None if the command may reach the backend, otherwise why not."""
    if cmd.owner != active:
        return f"command from {cmd.owner!r} ignored: the active planner is {active!r}"
    values = cmd.q if isinstance(cmd, m.PositionCommand) else cmd.dq
    if len(values) != n:
        return f"{type(cmd).__name__} {cmd.seq} from {cmd.owner!r} has {len(values)} joints, the robot has {n}"
    if not all(math.isfinite(v) for v in values):
        return f"{type(cmd).__name__} {cmd.seq} from {cmd.owner!r} has non-finite values {values}"
    return None


class SimArm:
    """Simulated joint-level arm: follows position or velocity targets within limits."""

    backend = "sim"

    def __init__(self, limits: Limits, q0: np.ndarray) -> None:
        self.limits = limits
        self.q = np.array(q0, dtype=float)
        self.dq = np.zeros_like(self.q)
        self.mode: str = "none"
        self.target = self.q.copy()
        self.clipped = 0

    def command_position(self, q: np.ndarray) -> None:
        self.mode = "position"
        clipped = np.clip(q, self.limits.q_min, self.limits.q_max)
        if not np.array_equal(clipped, q):
            self.clipped += 1
        self.target = clipped

    def command_velocity(self, dq: np.ndarray) -> None:
        self.mode = "velocity"
        self.target = dq.copy()

    def stop(self) -> None:
        """Decelerate to rest within the acceleration limit, then hold."""
        self.mode = "velocity"
        self.target = np.zeros_like(self.q)

    def step(self, dt: float) -> None:
        lim = self.limits
        if self.mode == "position":
            wanted = (self.target - self.q) / dt
        elif self.mode == "velocity":
            wanted = self.target
        else:
            return
        v = np.clip(wanted, -lim.v_max, lim.v_max)
        if self.mode == "velocity" and not np.array_equal(v, wanted):
            self.clipped += 1
        # A position stream from a planner moves the target every cycle, so the
        # arm follows one cycle behind at the target's speed; the acceleration
        # limit smooths whatever a planner gets wrong.
        v = np.clip(v, self.dq - lim.a_max * dt, self.dq + lim.a_max * dt)
        q = self.q + v * dt
        at_limit = (q <= lim.q_min) | (q >= lim.q_max)
        if at_limit.any():
            q = np.clip(q, lim.q_min, lim.q_max)
            v[at_limit] = 0.0
        self.q, self.dq = q, v

    def stopping_distance(self) -> np.ndarray:
        """Per-joint distance to rest at the acceleration limit, rad."""
        return self.dq**2 / (2 * self.limits.a_max)
