"""The study's task: the arm draws a figure-eight ("infinity sign") and pauses for reflexes.

The eight is a joint-space Lissajous curve around the home pose: the base
swings at the task frequency and the shoulder and elbow at twice it, so the
tool traces an eight in front of the robot. The task's own clock ``s`` only
advances in TASK, so the task resumes exactly where it paused; its rate eases
from 0 to 1 (smoothstep) over ``ramp_s`` on resume so that the arm leaves
the saved pose without a velocity jump.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from nwr.common.config import TaskSection

if TYPE_CHECKING:
    from nwr.common.robot import RobotModel


class FigureEight:
    def __init__(self, cfg: TaskSection, home: np.ndarray) -> None:
        if len(cfg.amplitude_rad) != len(home):
            raise ValueError(f"planner.task.amplitude_rad has {len(cfg.amplitude_rad)} joints, the robot {len(home)}")
        self.home = np.asarray(home, dtype=float)
        self.amplitude = np.asarray(cfg.amplitude_rad, dtype=float)
        self.multiple = np.where(np.asarray(cfg.double_frequency) > 0, 2.0, 1.0)
        self.omega = 2.0 * np.pi / cfg.period_s
        self.ramp_s = cfg.ramp_s

    def position(self, s: float) -> np.ndarray:
        return self.home + self.amplitude * np.sin(self.multiple * self.omega * s)

    def range(self) -> tuple[np.ndarray, np.ndarray]:
        """The lowest and highest position of each joint on the task's path."""
        reach = np.abs(self.amplitude)
        return self.home - reach, self.home + reach

    def velocity(self, s: float) -> np.ndarray:
        """dq/ds."""
        return self.amplitude * self.multiple * self.omega * np.cos(self.multiple * self.omega * s)


def peak_point_speed(task: FigureEight, period_s: float, model: RobotModel, samples: int = 240) -> float:
    """The speed of the task's fastest point (any the bridge's Cartesian limits watch: pads, elbow, flange)
    over one period, m/s: the profile's load checks it, the bridge paces a handover's stream with it."""
    return max(float(np.linalg.norm(model.speed_jacobians(task.position(s)) @ task.velocity(s), axis=1).max())
               for s in np.linspace(0.0, period_s, samples, endpoint=False))


class TaskClock:
    """The task's time s, advanced at a rate that eases in after a pause."""

    def __init__(self, ramp_s: float) -> None:
        self.s = 0.0
        self.ramp_s = ramp_s
        self.since_resume = ramp_s  # start at full speed

    def resume(self) -> None:
        self.since_resume = 0.0

    def rate(self) -> float:
        if self.ramp_s <= 0 or self.since_resume >= self.ramp_s:
            return 1.0
        x = self.since_resume / self.ramp_s
        return x * x * (3.0 - 2.0 * x)

    def advance(self, dt: float) -> float:
        """Advance by one control period; returns the rate used (ds/dt)."""
        rate = self.rate()
        self.s += rate * dt
        self.since_resume += dt
        return rate


def nearest_time(task: FigureEight, q: np.ndarray, dq: np.ndarray | None = None, near_s: float = 0.0,
                 samples: int = 1440) -> tuple[float, float]:
    """The task time whose pose is nearest ``q`` (every joint), and that distance, rad.

    The eight crosses itself (at home, twice a period): where several times
    fit as well, the one whose direction agrees with the measured ``dq`` wins,
    or without motion the one nearest ``near_s``. The time returned is the one
    of its period nearest ``near_s``, so a task clock keeps counting.
    """
    period = 2.0 * np.pi / task.omega
    s = np.linspace(0.0, period, samples, endpoint=False)
    phase = np.outer(s, task.multiple * task.omega)
    poses = task.home + task.amplitude * np.sin(phase)
    error = np.max(np.abs(poses - q), axis=1)
    fits = np.flatnonzero(error <= error.min() + 0.02)
    if dq is not None and float(np.max(np.abs(dq))) > 1e-3:
        velocity = task.amplitude * task.multiple * task.omega * np.cos(phase[fits])
        agree = velocity @ dq / np.maximum(np.linalg.norm(velocity, axis=1), 1e-12)
        best = int(fits[int(np.argmax(agree))])
    else:
        gap = np.abs((s[fits] - near_s + period / 2.0) % period - period / 2.0)
        best = int(fits[int(np.argmin(gap))])
    # Refine within one sample on either side.
    fine = s[best] + np.linspace(-1.0, 1.0, 41) * (period / samples)
    fine_error = np.array([float(np.max(np.abs(task.position(x) - q))) for x in fine])
    k = int(np.argmin(fine_error))
    found = float(fine[k])
    found += period * round((near_s - found) / period)
    return found, float(fine_error[k])
