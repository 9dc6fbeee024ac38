"""The bridge's tracker: the commanded joint state, one setpoint per cycle within the envelope, pure.

:class:`Tracker` owns the joint state the bridge commands (``q``, ``dq``,
``ddq``) and the accepted command it follows: a position target (with the
feed-forward velocity of its stream, or a plan of setpoints ahead) or a joint
velocity. Each control cycle it moves the commanded state towards the
command within the envelope (speed, acceleration, and the braking distance to
the joint limits), or along a jerk-limited (ruckig) stop to rest, whose
distance and duration it keeps. When to follow, stop or hold is the
supervisor's decision (:class:`~nwr.services.bridge.core.BridgeCore`); a clip
the tracker makes comes back as an :class:`~nwr.services.bridge.checks.Event`
for the supervisor to count and report.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

from nwr.common import messages as m
from nwr.services.bridge.cartesian import CartesianLimiter
from nwr.services.bridge.checks import MAX_PERIOD_S, MIN_PERIOD_S, Event, command_name
from nwr.services.bridge.envelope import Envelope, clip

# Relative tolerance before an implied speed counts as a clip (rounding).
SPEED_TOLERANCE = 1.01
# The bridge's and the planner's loops are not synchronised: a velocity
# step of up to this many control cycles' worth of acceleration is jitter,
# not a clip worth reporting (the tracker shapes it all the same).
ACCEL_JITTER_CYCLES = 2.0
# Rejoining a position stream after a hold ends once the arm is this close to
# the stream's target (rad, every joint) with the rejoin speed no longer binding.
REJOIN_TOLERANCE_RAD = 0.01
# The slowest a rejoin may be capped at, m/s (a stream that has not moved yet).
REJOIN_FLOOR_M_S = 0.05

CommandMode = Literal["none", "position", "velocity"]


@dataclass
class Stop:
    """A controlled stop to rest: its trajectory, when it began, where and how far it goes."""

    trajectory: Trajectory | None  # None: ruckig failed, constant-deceleration fallback
    start_ns: int
    q0: np.ndarray
    distance: np.ndarray
    duration_s: float
    done: bool = False


class Tracker:
    """The commanded joint state and the command it follows within the envelope."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, period_s: float = 0.002,
                 limiter: CartesianLimiter | None = None) -> None:
        self.env = env
        # The Cartesian limits (None: joint limits only) and what they depend on:
        # whether the command is a withdrawal, and the direction into the contact.
        self.limiter = limiter
        self.reflex = False  # the command followed is a withdrawal's (phase REFLEX)
        # The withdrawal's limits hold from its first command until the arm,
        # commanded otherwise, is back within the collaborative speed (it
        # decelerates within the acceleration limits, not in one cycle).
        self.withdrawal = False
        self.toward: np.ndarray | None = None
        # After a hold, a position stream is rejoined no faster than any point of
        # the arm moved in the stream itself (its peak so far): no catch-up.
        self.rejoining = False
        self.rejoin_cap: float | None = None  # a fixed cap for the rejoin (a handover's), m/s
        self.rejoin_cycles = 0  # control cycles the rejoin lasts at least
        self.stream_peak = 0.0
        self.limited = 0  # control cycles the Cartesian limits scaled
        self.period_s = period_s  # the control period, s
        n = env.n
        # The commanded joint state (what the backend was last sent).
        self.q = q0.copy()
        self.dq = np.zeros(n)
        self.ddq = np.zeros(n)
        # The command being followed.
        self.mode: CommandMode = "none"
        self.target = q0.copy()  # q (position) or dq (velocity)
        self.v_ff = np.zeros(n)  # feed-forward velocity of a position stream
        self.target_ns = now_ns
        # A position command planned ahead: its setpoints (rows, the first at
        # target_ns, one every plan_period_s), their speeds, how long they reach.
        self.plan: np.ndarray | None = None
        self.plan_v = np.zeros((0, n))
        self.plan_period_s = 0.0
        self.covered_ns = 0
        self.periods: deque[float] = deque(maxlen=15)
        # The controlled stop, and the distance and duration of the last one.
        self.stop: Stop | None = None
        self.stop_distance = np.zeros(n)
        self.stop_time_s = 0.0
        self._clip_reported = False  # the tracker's clip of the current command was reported
        self._otg = Ruckig(n)
        self._otg_in = InputParameter(n)
        self._otg_in.control_interface = ControlInterface.Velocity
        self._otg_in.max_velocity = env.v_max.tolist()
        self._otg_in.max_acceleration = env.a_max.tolist()
        self._otg_in.max_jerk = env.j_max.tolist()
        self._otg_in.target_velocity = [0.0] * n
        self._otg_in.target_acceleration = [0.0] * n

    # -- the command followed ------------------------------------------------------------
    def follow_position(self, cmd: m.PositionCommand, q: np.ndarray, now_ns: int, ahead: np.ndarray | None,
                        last_seq: int | None, last_stamp_ns: int) -> Event | None:
        """Follow an accepted position target ``q`` (and its setpoints ``ahead``); a clip to report, if any.

        ``last_seq`` and ``last_stamp_ns`` are those of the command accepted
        before: a stream's targets over its period give its velocity.
        """
        env = self.env
        self._clip_reported = False
        v_ff = np.zeros(env.n)
        gap = cmd.seq - last_seq if last_seq is not None else 0
        if ahead is not None:
            return self._follow_plan(cmd, q, ahead, now_ns)
        clipped = None
        if self.mode == "position" and self.plan is not None:
            # After a plan, a stream of one command per cycle (a reflex) carries
            # on at the plan's speed until its own period is measured.
            v_ff = self.planned(now_ns)[1].copy()
            self.periods.clear()
        elif self.mode == "position" and 1 <= gap <= 10 and cmd.stamp_ns > last_stamp_ns:
            # The stream's own period (median of its stamp steps, robust to the
            # jitter of both loops) turns successive targets into a velocity.
            self.periods.append((cmd.stamp_ns - last_stamp_ns) / gap / 1e9)
            # statistics.median: the same value as np.median, without its overhead on 15 numbers.
            period = min(max(float(statistics.median(self.periods)), MIN_PERIOD_S), MAX_PERIOD_S)
            v, clipped = self._at_the_limit(cmd, ((q - self.target) / (gap * period))[None, :],
                                            "position stream moves")
            v_ff = v[0]
        elif self.mode != "position":
            self.periods.clear()
        self.mode = "position"
        self.target = q
        self.v_ff = v_ff
        self.target_ns = now_ns
        self.plan = None
        self.covered_ns = 0
        return clipped

    def _follow_plan(self, cmd: m.PositionCommand, q: np.ndarray, ahead: np.ndarray, now_ns: int) -> Event | None:
        """A position command planned ahead: its setpoints, one every ``cmd.period_s`` from now."""
        plan = np.vstack([q, ahead])
        period = cmd.period_s
        v, clipped = self._at_the_limit(cmd, np.diff(plan, axis=0) / period, "planned to move")
        self.periods.clear()
        self.mode = "position"
        self.target = q
        self.v_ff = v[0]
        self.target_ns = now_ns
        self.plan, self.plan_v, self.plan_period_s = plan, v, period
        self.covered_ns = round(len(ahead) * period * 1e9)
        return clipped

    def follow_velocity(self, dq: np.ndarray) -> None:
        """Follow an accepted joint velocity ``dq``."""
        self._clip_reported = False
        self.mode = "velocity"
        self.target = dq
        self.v_ff = np.zeros(self.env.n)
        self.plan = None
        self.covered_ns = 0

    def _at_the_limit(self, cmd: m.PositionCommand, v: np.ndarray, what: str) -> tuple[np.ndarray, Event | None]:
        """Joint velocities (one row per step) scaled down to v_max where faster; the worst one's clip, if any."""
        env = self.env
        ratio = (np.abs(v) / env.v_max).max(axis=1)
        worst = float(ratio.max())
        clipped = None
        if worst > SPEED_TOLERANCE:
            k = int(np.argmax(ratio))
            i = int(np.argmax(np.abs(v[k]) / env.v_max))
            clipped = Event(
                "warning", "command_clipped",
                f"{command_name(cmd)}: joint {env.joints[i]} {what} at {v[k, i]:.3f} rad/s, "
                f"v_max {env.v_max[i]:.3f} rad/s: followed at the limit",
            )
        return (v / np.maximum(ratio, 1.0)[:, None] if worst > 1.0 else v), clipped

    def planned(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The plan's target and feed-forward velocity at ``t_ns``: interpolated, or extrapolated past its end."""
        plan, v = self.plan, self.plan_v
        assert plan is not None
        x = max((t_ns - self.target_ns) / 1e9, 0.0) / self.plan_period_s  # in periods
        k = int(x)
        last = len(plan) - 1
        if k < last:
            return plan[k] + (plan[k + 1] - plan[k]) * (x - k), v[k]
        # Past the last setpoint (the next command is late): on at the last speed, briefly.
        over = min((x - last) * self.plan_period_s, MAX_PERIOD_S)
        return clip(plan[last] + v[last - 1] * over, self.env.q_min, self.env.q_max), v[last - 1]

    def observe(self, q: np.ndarray) -> None:
        """The measured pose; in velocity mode (not stopping) the integrated command follows it."""
        if self.mode == "velocity" and self.stop is None:
            self.q = np.asarray(q, dtype=float).copy()

    def restart(self, q: np.ndarray) -> None:
        """Start over at rest from the measured pose ``q``, following nothing (after a fault)."""
        self.q = np.asarray(q, dtype=float).copy()
        self.dq[:] = 0.0
        self.ddq[:] = 0.0
        self.stop = None
        self.mode = "none"

    # -- one control cycle -------------------------------------------------------------
    def hold(self) -> None:
        """Stay where the arm is commanded, at rest."""
        self.dq[:] = 0.0
        self.ddq[:] = 0.0

    def track(self, h: float, t_ns: int, active: str) -> Event | None:
        """One cycle of ``h`` s at ``t_ns`` towards the command of ``active``; a clip to report, if any."""
        env = self.env
        if self.mode == "position":
            if self.plan is not None:
                target, v_ff = self.planned(t_ns)
            else:
                ahead = min((t_ns - self.target_ns) / 1e9, MAX_PERIOD_S)
                target = clip(self.target + self.v_ff * max(ahead, 0.0), env.q_min, env.q_max)
                v_ff = self.v_ff
            return self._limit(v_ff.tolist(), h, target.tolist(), active)
        clipped = None
        if self.mode == "velocity":
            v_des = self.target.copy()
            jump = np.abs(v_des - self.dq) / (env.a_max * max(h, self.period_s))
            if float(np.max(jump)) > ACCEL_JITTER_CYCLES and not self._clip_reported:
                i = int(np.argmax(jump))
                clipped = self._clip(
                    "command_clipped",
                    f"velocity command from {active!r}: joint {env.joints[i]} asks for {v_des[i]:.3f} rad/s "
                    f"from {self.dq[i]:.3f} rad/s, a_max {env.a_max[i]:.2f} rad/s^2: ramped at the limit",
                )
        else:
            v_des = np.zeros(env.n)
        bounded = self._limit(v_des.tolist(), h, None, active)
        return clipped or bounded

    def begin_rejoin(self, cap: float | None = None, cycles: int = 0) -> None:
        """Rejoin the stream (when it is a position stream) at no more than its own peak speed, or ``cap`` (m/s).

        After a hold, the stream's own peak so far; after a switch, the
        outgoing stream's (the incoming one's speed is its claim) for at
        least ``cycles`` control cycles, joined or not.
        """
        self.rejoining = True
        self.rejoin_cap = cap
        self.rejoin_cycles = cycles

    def _limit(self, v_des: list[float], h: float, target: list[float] | None, active: str) -> Event | None:
        """Integrate one cycle towards ``v_des`` within the envelope (per joint, in floats); a clip, if any.

        With a position ``target``, ``v_des`` is its feed-forward velocity, plus
        a correction that can always brake in time: no overshoot on a step, no
        lag on a smooth stream. Then the speed limit; never faster towards a
        joint limit than a jerk-limited stop allows (:meth:`Envelope.braking_speed`,
        the same formula); the Cartesian limits (every point's speed, the speed
        toward a contact, the momentum; while rejoining a stream, its own peak
        speed), which scale the joint velocity as a whole; the acceleration
        limit; the joint limits.
        """
        q0, dq0 = self.q.tolist(), self.dq.tolist()
        bounded_v: list[float] = []
        bound_i, bound_by, bound_v = -1, 1e-9, 0.0  # the joint the braking distance bounds most (reported once)
        per_joint = self.env.per_joint
        for i, (q_min, q_max, v_max, a_max, k) in enumerate(per_joint):
            q = q0[i]
            v = v_des[i]
            if target is not None:
                e = target[i] - q
                correction = min(abs(e) / h, math.sqrt(2.0 * a_max * abs(e)))
                v = v + correction if e >= 0.0 else v - correction
            v = min(max(v, -v_max), v_max)
            d = max(q_max - q, 0.0)
            v_hi = a_max * (math.sqrt(k * k + 2.0 * d / a_max) - k)
            d = max(q - q_min, 0.0)
            v_lo = -(a_max * (math.sqrt(k * k + 2.0 * d / a_max) - k))
            bounded = min(max(v, v_lo), v_hi)
            if abs(bounded - v) > bound_by:
                bound_i, bound_by, bound_v = i, abs(bounded - v), bounded
            v_des[i] = v
            bounded_v.append(bounded)
        scaled_before = self.limited
        limited = self._cartesian(bounded_v, target, active) if self.limiter is not None else None
        v1 = []
        for i, (_q_min, _q_max, _v_max, a_max, _k) in enumerate(per_joint):
            dq, bounded = dq0[i], bounded_v[i]
            v1.append(min(max(bounded, dq - a_max * h), dq + a_max * h))
        if self.limiter is not None:
            limited = self._power(v1, h, active) or limited
            self.limited = min(self.limited, scaled_before + 1)  # cycles scaled, not scalings
        q1, a1 = [], []
        for i, (q_min, q_max, _v_max, _a_max, _k) in enumerate(per_joint):
            q, dq, v = q0[i], dq0[i], v1[i]
            q1.append(min(max(q + 0.5 * (dq + v) * h, q_min), q_max))
            a1.append((v - dq) / h)
        clipped = limited
        if clipped is None and bound_i >= 0 and not self._clip_reported:
            env, i = self.env, bound_i
            clipped = self._clip(
                "joint_limit",
                f"{self.mode} command from {active!r}: joint {env.joints[i]} at {q0[i]:.4f} rad approaches "
                f"its limit [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}] at {v_des[i]:.3f} rad/s: speed bounded to "
                f"{bound_v:.3f} rad/s (the braking distance)",
            )
        self.q, self.dq, self.ddq = np.array(q1), np.array(v1), np.array(a1)
        return clipped

    def _cartesian(self, v: list[float], target: list[float] | None, active: str) -> Event | None:
        """Scale the cycle's joint velocity ``v`` (in place) into the Cartesian limits; a scaling to report, if any."""
        limiter = self.limiter
        assert limiter is not None
        cap = None
        if self.mode == "position":
            own = float(limiter.speeds(self.q, self.v_ff).max()) if self.v_ff.any() else 0.0
            self.stream_peak = min(max(self.stream_peak, own), limiter.limits.speed_m_s)
            if self.rejoining:
                cap = self.rejoin_cap if self.rejoin_cap is not None else max(self.stream_peak, REJOIN_FLOOR_M_S)
        else:
            self.rejoining = False
        if self.withdrawal and not self.reflex and \
                float(limiter.speeds(self.q, self.dq).max()) <= limiter.limits.speed_m_s:
            self.withdrawal = False
            self.toward = None
        dq = np.array(v)
        scaling = limiter.scale(self.q, dq, withdrawal=self.withdrawal, toward=self.toward, speed_cap=cap)
        self.rejoin_cycles -= 1
        if self.rejoining and self.rejoin_cycles <= 0 and (scaling is None or scaling.what != "rejoin speed") \
                and target is not None:
            if float(np.max(np.abs(np.asarray(target) - self.q))) < REJOIN_TOLERANCE_RAD:
                self.rejoining = False
        if scaling is None:
            return None
        for i in range(len(v)):
            v[i] *= scaling.factor
        self.limited += 1
        if self._clip_reported:
            return None
        return self._clip("cartesian_limit", f"{self.mode} command from {active!r}: {scaling.describe()}")

    def _power(self, v: list[float], h: float, active: str) -> Event | None:
        """Ease the cycle's acceleration (``v``, in place) into the power limit; a scaling to report, if any."""
        limiter = self.limiter
        assert limiter is not None
        if not any(v) and not self.dq.any():
            return None
        scaling = limiter.power_scale(self.q, self.dq, np.array(v), h)
        if scaling is None:
            return None
        s, dq0 = scaling.factor, self.dq.tolist()
        for i in range(len(v)):
            v[i] = dq0[i] + s * (v[i] - dq0[i])
        self.limited += 1
        if self._clip_reported:
            return None
        return self._clip("cartesian_limit", f"{self.mode} command from {active!r}: {scaling.describe()}")

    def _clip(self, code: str, message: str) -> Event:
        """A clip of the tracker, reported once per command (not per cycle)."""
        self._clip_reported = True
        return Event("warning", code, message)

    # -- the controlled stop -------------------------------------------------------------
    def begin_stop(self, now_ns: int) -> Event | None:
        """Plan a jerk-limited stop to rest from the commanded state; an error to report if ruckig failed."""
        env = self.env
        n = env.n
        inp = self._otg_in
        inp.current_position = self.q.tolist()
        inp.current_velocity = np.clip(self.dq, -env.v_max, env.v_max).tolist()
        inp.current_acceleration = np.clip(self.ddq, -env.a_max, env.a_max).tolist()
        trajectory: Trajectory | None = Trajectory(n)
        result = self._otg.calculate(inp, trajectory)
        failed = None
        if result in (Result.Working, Result.Finished):
            assert trajectory is not None
            end, _, _ = trajectory.at_time(trajectory.duration)
            distance = np.asarray(end) - self.q
            duration = float(trajectory.duration)
        else:
            # Constant deceleration at the acceleration limit, per joint: never
            # happens with valid limits, but a stop must never fail.
            trajectory = None
            distance = self.dq * np.abs(self.dq) / (2.0 * env.a_max)
            duration = float(np.max(np.abs(self.dq) / env.a_max))
            failed = Event("error", "stop_fallback",
                           f"ruckig could not plan the stop ({result}): constant deceleration instead")
        self.stop = Stop(trajectory, now_ns, self.q.copy(), distance, duration)
        self.stop_distance = distance
        self.stop_time_s = duration
        return failed

    def stop_step(self, now_ns: int, h: float) -> None:
        """One cycle of ``h`` s of the stop at ``now_ns``; at rest once it is done."""
        stop = self.stop
        assert stop is not None
        env = self.env
        t = (now_ns - stop.start_ns) / 1e9
        if stop.done:
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            return
        if t >= stop.duration_s:
            stop.done = True
            q = stop.q0 + stop.distance
            self.q = np.clip(q, env.q_min, env.q_max)
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            return
        if stop.trajectory is not None:
            q, dq, ddq = stop.trajectory.at_time(t)
            q, dq, ddq = np.asarray(q), np.asarray(dq), np.asarray(ddq)
        else:
            dq = np.sign(self.dq) * np.maximum(np.abs(self.dq) - env.a_max * h, 0.0)
            ddq = (dq - self.dq) / h
            q = self.q + 0.5 * (self.dq + dq) * h
        self.q = np.clip(q, env.q_min, env.q_max)
        self.dq, self.ddq = dq, ddq

    def release(self) -> None:
        """Drop the trajectory generator at shutdown (its objects must not outlive their module)."""
        self._otg = self._otg_in = None
        if self.stop is not None:
            self.stop.trajectory = None
