"""The study's task: the arm draws a figure-eight ("infinity sign") and pauses for reflexes.

The eight is a joint-space Lissajous curve around the home pose: the base
swings at the task frequency and the shoulder and elbow at twice it, so the
tool traces an eight in front of the robot. The task's own clock ``s`` only
advances in TASK, so the task resumes exactly where it paused; its rate eases
from 0 to 1 (smoothstep) over ``ramp_s`` on resume so that the arm leaves
the saved pose without a velocity jump.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated

import msgspec
import numpy as np

from nwr.common.errors import ConfigError
from nwr.common.section import Section

if TYPE_CHECKING:
    from nwr.common.robot import RobotDescription, RobotModel


class TaskSection(Section):
    """``[planner.task]``: the figure-eight's period, amplitudes and ease-in."""

    # Period of the figure-eight, s. The task's fastest point (0.19 m/s on the
    # UR10e by default) must stay within bridge.limits.speed_m_s.
    period_s: Annotated[float, msgspec.Meta(gt=0, le=3600)] = 12.0
    # Joint amplitudes of the figure-eight around the home pose, rad, one per
    # joint; empty = the robot's (robot.toml [task]; the UR10e's: the base
    # swings at the task frequency, shoulder and elbow at twice it, which draws
    # an eight with the tool). Within the joint limits.
    amplitude_rad: list[Annotated[float, msgspec.Meta(ge=-math.pi, le=math.pi)]] = []
    # Twice-frequency joints (1) versus task-frequency joints (0), one per
    # joint; empty = the robot's.
    double_frequency: list[Annotated[int, msgspec.Meta(ge=0, le=1)]] = []
    # Time to ease in and out of the task when it resumes or pauses, s.
    ramp_s: Annotated[float, msgspec.Meta(ge=0, le=10)] = 0.5
    # The pose the figure-eight is drawn around, rad, one per joint; empty = the
    # robot's home (robot.toml). The arm first returns to it from wherever it
    # is; a simulated arm starts there with bridge.initial_q set to the same.
    home_rad: list[Annotated[float, msgspec.Meta(ge=-2 * math.pi, le=2 * math.pi)]] = []


class FigureEight:
    def __init__(self, cfg: TaskSection, desc: RobotDescription) -> None:
        """The figure-eight of ``cfg`` around its home (``desc``'s where ``cfg`` leaves it empty); its amplitudes and
        frequencies the robot's (robot.toml [task]) where ``cfg`` leaves them empty."""
        amplitude = cfg.amplitude_rad or list(desc.task_amplitude_rad)
        double = cfg.double_frequency or list(desc.task_double_frequency)
        home = cfg.home_rad or list(desc.home)
        n = len(desc.home)
        if len(amplitude) != n or len(double) != n or len(home) != n:
            raise ValueError(f"planner.task.amplitude_rad / double_frequency / home_rad have {len(amplitude)} / "
                             f"{len(double)} / {len(home)} joints, robot {desc.name!r} {n}")
        self.home = np.asarray(home, dtype=float)
        self.amplitude = np.asarray(amplitude, dtype=float)
        self.multiple = np.where(np.asarray(double) > 0, 2.0, 1.0)
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


def check_task(task: TaskSection, desc: RobotDescription, model: RobotModel, q_lo: Sequence[float],
               q_hi: Sequence[float], speed_limit_m_s: float) -> None:
    """The task on robot ``desc`` stays within the joint ranges ``q_lo``..``q_hi`` the bridge enforces, and its
    fastest point within the robot's max_point_speed and ``speed_limit_m_s`` (bridge.limits.speed_m_s); else a
    ConfigError naming the field (the profile's load checks it)."""
    try:
        figure = FigureEight(task, desc)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    lo, hi = figure.range()
    for i, joint in enumerate(desc.joints):
        if lo[i] < q_lo[i] or hi[i] > q_hi[i]:
            raise ConfigError(f"planner.task.amplitude_rad[{i}] = {figure.amplitude[i]:g} swings {joint} over "
                              f"[{lo[i]:.3f}, {hi[i]:.3f}] rad around {figure.home[i]:g} rad (the task's home), "
                              f"beyond its limits [{q_lo[i]:.3f}, {q_hi[i]:.3f}] rad: shrink it or move "
                              "planner.task.home_rad")
    peak = peak_point_speed(figure, task.period_s, model)
    for bound, name, why in (
        (desc.max_point_speed, f"robot {desc.name!r}'s max_point_speed", "the arm cannot"),
        (speed_limit_m_s, "bridge.limits.speed_m_s", "the bridge would slow it every cycle"),
    ):
        if peak > bound:
            raise ConfigError(
                f"planner.task.period_s = {task.period_s} s with amplitude_rad = {figure.amplitude.tolist()} moves "
                f"the task's fastest point at {peak:.3g} m/s, above {name} = {bound} m/s ({why}): lengthen period_s or "
                "shrink amplitude_rad"
            )


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
