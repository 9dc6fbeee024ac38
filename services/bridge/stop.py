"""The tracker's controlled stop: a jerk-limited (ruckig) trajectory to rest, its distance and duration.

:class:`ControlledStop` owns the stop under way (:class:`Stop`), the distance
and duration of the last one (the robot state reports them), and the
trajectory generator that plans it. It plans from the commanded joint state
(:class:`~.law.Joints`, the tracker's) and moves that state along the stop one
cycle at a time; when to stop is the supervisor's decision (:mod:`.core`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ruckig import ControlInterface, Result, Ruckig, RuckigError, Synchronization, Trajectory

from nwr.services.bridge.cartesian import CartesianLimiter
from nwr.services.bridge.checks import Event
from nwr.services.bridge.envelope import Envelope, clip
from nwr.services.bridge.law import Joints, ruckig_input
from nwr.services.bridge.limits import LIMIT_SLACK_RAD

# A controlled stop is checked against the Cartesian speed limit every this
# many s over its first STOP_CHECK_SPAN_S (where its speed peaks), m/s of slack.
STOP_CHECK_S = 0.004
STOP_CHECK_SPAN_S = 0.12
STOP_SPEED_SLACK_M_S = 1e-4


@dataclass
class Stop:
    """A controlled stop to rest: its trajectory, when it began, where and how far it goes."""

    trajectory: Trajectory | None  # None: ruckig failed, constant-deceleration fallback
    start_ns: int
    q0: np.ndarray
    distance: np.ndarray
    duration_s: float
    done: bool = False


class ControlledStop:
    """The stop to rest of the commanded joint state (module docstring)."""

    def __init__(self, env: Envelope, joints: Joints) -> None:
        self.env = env
        self.joints = joints
        # The controlled stop, and the distance and duration of the last one.
        self.stop: Stop | None = None
        self.stop_distance = np.zeros(env.n)
        self.stop_time_s = 0.0
        self.otg = Ruckig(env.n)
        # The stop: to rest, every joint ending together.
        self.otg_in = ruckig_input(env, ControlInterface.Velocity)

    def begin(self, now_ns: int, limiter: CartesianLimiter | None, withdrawal: bool) -> Event | None:
        """Plan a jerk-limited stop to rest from the commanded state; an error to report if ruckig failed.

        The stop starts from the commanded acceleration (its jerk stays within
        ``j_max``), every joint ending together. Begun while the arm
        accelerates, the speed still rises while the acceleration ramps down:
        if a point would then move faster than the Cartesian speed limit (or
        than at the stop's start, when that was faster), the stop starts at
        zero acceleration instead (a step in acceleration, the one the limits
        cost) and keeps the joints in proportion, so no point moves faster than
        at its start. If a joint would pass its limit, the joints stop each on
        its own, time-optimally (the tracker kept that possible).
        """
        env, joints = self.env, self.joints
        velocity = clip(joints.dq, -env.v_max, env.v_max)
        acceleration = clip(joints.ddq, -env.a_max, env.a_max)
        zero = np.zeros(env.n)
        first: Trajectory | None = None  # the stop as it starts, if nothing fits better
        fits_limits: Trajectory | None = None  # the first within the joint limits
        trajectory: Trajectory | None = None  # within both
        result = Result.Error
        for a0, sync in ((acceleration, Synchronization.Time), (zero, Synchronization.Phase),
                         (acceleration, Synchronization.No), (zero, Synchronization.No)):
            if a0 is zero and not acceleration.any():
                continue
            candidate = Trajectory(env.n)
            result = self._plan(velocity, a0, sync, candidate)
            if result not in (Result.Working, Result.Finished):
                break
            within, faster = self._check(candidate, velocity, limiter, withdrawal)
            if first is None:
                first = candidate
            if within and fits_limits is None:
                fits_limits = candidate
            if within and not faster:
                trajectory = candidate
                break
        if trajectory is None:
            trajectory = fits_limits if fits_limits is not None else first
        self.otg_in.synchronization = Synchronization.Time
        failed = None
        if trajectory is not None:
            end, _, _ = trajectory.at_time(trajectory.duration)
            distance = np.asarray(end) - joints.q
            duration = float(trajectory.duration)
        else:
            # Constant deceleration at the acceleration limit, per joint: never
            # happens with valid limits, but a stop must never fail.
            distance = joints.dq * np.abs(joints.dq) / (2.0 * env.a_max)
            duration = float(np.max(np.abs(joints.dq) / env.a_max))
            failed = Event("error", "stop_fallback",
                           f"ruckig could not plan the stop ({result}): constant deceleration instead")
        self.stop = Stop(trajectory, now_ns, joints.q.copy(), distance, duration)
        self.stop_distance = distance
        self.stop_time_s = duration
        return failed

    def _plan(self, velocity: np.ndarray, acceleration: np.ndarray, sync: Synchronization,
              trajectory: Trajectory) -> Result:
        inp = self.otg_in
        inp.current_position = self.joints.q.tolist()
        inp.current_velocity = velocity.tolist()
        inp.current_acceleration = acceleration.tolist()
        inp.synchronization = sync
        try:
            return self.otg.calculate(inp, trajectory)
        except (RuckigError, RuntimeError, ValueError):
            return Result.Error

    def _check(self, trajectory: Trajectory, velocity: np.ndarray, limiter: CartesianLimiter | None,
               withdrawal: bool) -> tuple[bool, bool]:
        """Whether a planned stop stays within the joint limits, and whether any point then moves faster than allowed:
        the Cartesian speed limit of the motion, or the speed at the start if that was faster.

        Sampled every :data:`STOP_CHECK_S` over its first :data:`STOP_CHECK_SPAN_S`
        (its speed peaks while the acceleration ramps down, within ``a_max / j_max``)
        and at its end.
        """
        env, q0 = self.env, self.joints.q
        duration = float(trajectory.duration)
        times = np.append(np.arange(STOP_CHECK_S, min(duration, STOP_CHECK_SPAN_S), STOP_CHECK_S), duration)
        allowed = 0.0
        if limiter is not None:
            limit = limiter.limits.withdrawal_speed_m_s if withdrawal else limiter.limits.speed_m_s
            allowed = max(limit, float(limiter.speeds(q0, velocity).max())) + STOP_SPEED_SLACK_M_S
        within, faster = True, False
        for t in times:
            q, dq, _ = trajectory.at_time(float(t))
            q = np.asarray(q)
            if np.any(q < env.q_min - LIMIT_SLACK_RAD) or np.any(q > env.q_max + LIMIT_SLACK_RAD):
                within = False
            if limiter is not None and not faster and float(limiter.speeds(q, np.asarray(dq)).max()) > allowed:
                faster = True
        return within, faster

    def step(self, now_ns: int, h: float) -> None:
        """One cycle of ``h`` s of the stop at ``now_ns``; at rest once it is done."""
        stop = self.stop
        assert stop is not None
        env, joints = self.env, self.joints
        t = (now_ns - stop.start_ns) / 1e9
        if stop.done:
            joints.dq[:] = 0.0
            joints.ddq[:] = 0.0
            return
        if t >= stop.duration_s:
            stop.done = True
            q = stop.q0 + stop.distance
            joints.q = np.clip(q, env.q_min, env.q_max)
            joints.dq[:] = 0.0
            joints.ddq[:] = 0.0
            return
        if stop.trajectory is not None:
            q, dq, ddq = stop.trajectory.at_time(t)
            q, dq, ddq = np.asarray(q), np.asarray(dq), np.asarray(ddq)
        else:
            dq = np.sign(joints.dq) * np.maximum(np.abs(joints.dq) - env.a_max * h, 0.0)
            ddq = (dq - joints.dq) / h
            q = joints.q + 0.5 * (joints.dq + dq) * h
        joints.q = np.clip(q, env.q_min, env.q_max)
        joints.dq, joints.ddq = dq, ddq

    def release(self) -> None:
        """Drop the trajectory generator at shutdown (its objects must not outlive their module)."""
        self.otg = self.otg_in = None
        if self.stop is not None:
            self.stop.trajectory = None
