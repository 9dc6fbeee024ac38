"""The study's task: the arm draws a figure-eight ("infinity sign") and pauses for reflexes.

The eight is a joint-space Lissajous curve around the home pose: the base
swings at the task frequency and the shoulder and elbow at twice it, so the
tool traces an eight in front of the robot. The task's own clock ``s`` only
advances in TASK, so the task resumes exactly where it paused; its rate eases
from 0 to 1 (smoothstep) over ``ramp_s`` on resume so that the arm leaves
the saved pose without a velocity jump.
"""

from __future__ import annotations

import numpy as np

from nwr.common.config import TaskSection


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

    def velocity(self, s: float) -> np.ndarray:
        """dq/ds."""
        return self.amplitude * self.multiple * self.omega * np.cos(self.multiple * self.omega * s)


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
