"""The bridge's tracker: the commanded joint state, one setpoint per cycle within the envelope, pure.

:class:`Tracker` owns the joint state the bridge commands (``q``, ``dq``,
``ddq``) and the accepted command it follows: a position target (with the
feed-forward velocity of its stream, or a plan of setpoints ahead) or a joint
velocity. Each control cycle it moves the commanded state towards the
command within the envelope (speed, acceleration, jerk, and the stop before
the joint limits), or along a jerk-limited (ruckig) stop to rest, whose
distance and duration it keeps. When to follow, stop or hold is the
supervisor's decision (:class:`~nwr.services.bridge.core.BridgeCore`); a clip
the tracker makes comes back as an :class:`~nwr.services.bridge.checks.Event`
for the supervisor to count and report.

How a cycle follows the command (:meth:`Tracker.track`):

- **The reference.** A command becomes a reference with a velocity, an
  acceleration and a jerk: a plan's setpoints the curve whose velocity runs
  linearly between its segments' velocities (continuous in velocity, within
  nanoradians of the setpoints); a stream of one command per cycle the cubic
  through its last four targets (its derivatives at the newest), a velocity
  stream its velocity and rate of change. Each command goes on its stream's
  own timeline, where the previous one puts it (a plan's first setpoint on the
  previous plan's path, a stream's next target one period on); the timeline
  follows the commands' earliest arrivals and drifts later by at most
  :data:`DRIFT`, so the jitter of the planner's and the bridge's loops does not
  make the reference jump back and forth (it did, and the task ran 20-30 %
  faster than planned).
- **The law.** The commanded state relative to the reference (moving over the
  cycle as the reference does) is brought to rest along ruckig's time-optimal
  jerk-limited trajectory, each joint on its own (a velocity step's joints in
  proportion), sampled one cycle in; the relative limits are what ``v_max``,
  ``a_max`` and ``j_max`` leave once the reference's own motion is counted, so
  the absolute jerk of every cycle is within ``j_max``. A step is reached
  without overshoot; a smooth stream is followed to rounding. The reference's
  jerk is counted only where the joint is on it (:data:`ON_REFERENCE_RAD` ...):
  farther off, the law needs the whole jerk limit to get there.
- **The joint limits.** A joint whose next state could not stop (its
  time-optimal jerk-limited stop, :func:`~.envelope.stop_extent`) before its
  limits brakes along that stop instead (:func:`~.envelope.brake`): by
  induction the arm can always stop within them.
- **The Cartesian limits** (every point's speed, the speed toward a contact,
  the momentum, the stopping time and distance, a rejoin's speed) are
  anticipated: where the joints, their acceleration ramped down from the next
  cycle on, would level off beyond them, or the velocity is within
  :data:`NEAR_LIMIT` of them, the law runs again with the joint speeds capped
  in proportion, a little below (:data:`CAP_MARGIN`): the arm levels off at
  the limit within the jerk limit. They remain hard caps: a velocity still
  beyond them is scaled down as a whole, within ``a_max``; then the power
  limit eases the acceleration. Only these hard caps (never in the demo
  sessions: a stream beyond the limits), a fault's hold, and a stop begun
  while accelerating too close to the speed limit (:meth:`Tracker.begin_stop`)
  make a cycle's jerk exceed ``j_max``.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Synchronization, Trajectory

from nwr.common import messages as m
from nwr.services.bridge.cartesian import CartesianLimiter, Scaling
from nwr.services.bridge.checks import MAX_PERIOD_S, MIN_PERIOD_S, Event, command_name
from nwr.services.bridge.envelope import Envelope, brake, clip, stop_extent

# Relative tolerance before an implied speed counts as a clip (rounding).
SPEED_TOLERANCE = 1.01
# The bridge's and the planner's loops are not synchronised: a velocity
# step of up to this many control cycles' worth of acceleration is jitter,
# not a clip worth reporting (the tracker shapes it all the same).
ACCEL_JITTER_CYCLES = 2.0
# Rejoining a position stream after a hold ends once the arm is on the stream:
# this close to its reference (rad, every joint) and its velocity (rad/s), with
# the rejoin speed no longer binding. Closer than that, what is left to catch up
# adds next to nothing to the stream's own speed (the law closes a gap
# time-optimally: 10 mrad would take a point 0.1 m/s beyond the stream).
REJOIN_TOLERANCE_RAD = 1e-5
REJOIN_TOLERANCE_RAD_S = 1e-3
# The slowest a rejoin may be capped at, m/s (a stream that has not moved yet).
REJOIN_FLOOR_M_S = 0.05
# A stream's timeline follows its earliest arrivals, and moves later by at
# most this share of the time the stream covers (a few times the drift of two
# hosts' clocks, 10-100 ppm; the loops' jitter of a millisecond or two moves
# the reference by a fraction of a microsecond per command).
DRIFT = 2e-4
# A command arriving later than this after where the stream's timeline
# expects it (the stream stalled) starts the timeline afresh, s.
MAX_LATE_S = 0.02
# A plan continues the one followed when its first setpoint is this close to
# that plan's path (rad, every joint): the planner's overlapping setpoints agree
# to the last bit.
PLAN_MATCH_RAD = 1e-6
# A position stream's reference is the cubic through its last this many steps' targets.
STREAM_STEPS = 3
# The median of a stream's stamp steps is smoothed by this share per command.
PERIOD_SMOOTHING = 0.05
# A stream's acceleration is extrapolated this many periods past its last
# command (a late command), its velocity on to MAX_PERIOD_S.
ACCEL_PERIODS = 2.0
# The reference the law follows stays strictly within the speed and
# acceleration limits (the law needs room to correct around it).
FEASIBLE = 0.999
# A velocity law's acceleration this close to the direction of its velocity's
# change (relative, every joint) is taken as along it.
COLLINEAR = 1e-6
# A joint is on its reference within these (position, velocity, acceleration).
ON_REFERENCE_RAD = 3e-3
ON_REFERENCE_RAD_S = 0.04
ON_REFERENCE_RAD_S2 = 2.0
# The law keeps at least this share of the jerk limit to correct with, however
# hard the reference itself jerks (the frame's jerk is clipped to the rest).
JERK_FLOOR = 0.02
# Rounding allowed past a joint limit by the stop check, rad.
LIMIT_SLACK_RAD = 1e-9
# Joints speeding up by more than this share of their speeds (plus
# LEVEL_OFF_RAD_S, rad/s, all joints together) before they could level off
# have that velocity checked against the Cartesian limits.
LEVEL_OFF = 0.02
LEVEL_OFF_RAD_S = 2e-3
# A velocity within this share of a Cartesian limit is near it: the law keeps
# it a little below.
NEAR_LIMIT = 0.02
# ... this much below, so that the hard cap (which costs the jerk limit) does
# not bind on rounding or on the arm's geometry changing under it.
CAP_MARGIN = 5e-3
# A controlled stop is checked against the Cartesian speed limit every this
# many s over its first STOP_CHECK_SPAN_S (where its speed peaks), m/s of slack.
STOP_CHECK_S = 0.004
STOP_CHECK_SPAN_S = 0.12
STOP_SPEED_SLACK_M_S = 1e-4

CommandMode = Literal["none", "position", "velocity"]
State = tuple[np.ndarray, np.ndarray, np.ndarray]  # q, dq, ddq
Reference = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # position, velocity, acceleration, jerk
# The reference over a control cycle, from its start: position (None: a velocity command), velocity,
# acceleration, and jerk over the cycle.
Frame = tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray]


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
        # The last Cartesian clip was the law catching up with a position stream whose own speed is within the
        # limits (the arm a few mrad behind it after a jerk-limited turn): the envelope shaping the tracking,
        # not a planner asking for too much.
        self.catching_up = False
        self.stream_peak = 0.0
        self.limited = 0  # control cycles the Cartesian limits scaled
        self.period_s = period_s  # the control period, s
        n = env.n
        # The commanded joint state (what the backend was last sent).
        self.q = q0.copy()
        self.dq = np.zeros(n)
        self.ddq = np.zeros(n)
        # The command being followed: its target (q, or dq in velocity mode), its
        # time on the stream's timeline, and the reference's velocity and
        # acceleration there (a stream's; a plan has its own).
        self.mode: CommandMode = "none"
        self.target = q0.copy()
        self.v_ff = np.zeros(n)
        self.a_ff = np.zeros(n)
        self.target_ns = now_ns
        # A position stream's jerk at its last target, and its last steps (per period).
        self.j_ff = np.zeros(n)
        self.steps: list[np.ndarray] = []
        # A position command planned ahead: its setpoints (rows, the first at
        # target_ns, one every plan_period_s), their speeds, how long they reach,
        # and the speed of the reference just before its first setpoint.
        self.plan: np.ndarray | None = None
        self.plan_v = np.zeros((0, n))
        self.plan_v_before = np.zeros(n)
        self.plan_c0 = np.zeros(n)
        self._segments = np.zeros((0, 4, n))
        self.plan_period_s = 0.0
        self.covered_ns = 0
        self.periods: deque[float] = deque(maxlen=15)
        self.period_estimate: float | None = None
        # The controlled stop, and the distance and duration of the last one.
        self.stop: Stop | None = None
        self.stop_distance = np.zeros(n)
        self.stop_time_s = 0.0
        self._clip_reported = False  # the tracker's clip of the current command was reported
        self._j = env.j_max.tolist()
        self._zero = np.zeros(n)
        self._v_lim = env.v_max * FEASIBLE
        self._a_lim = env.a_max * FEASIBLE
        self._j_lim = env.j_max * (1.0 - JERK_FLOOR)
        self._otg = Ruckig(n)
        self._trajectory = Trajectory(n)
        # The stop: to rest, every joint ending together.
        self._otg_in = self._input(ControlInterface.Velocity)
        # Following a position: each joint time-optimal on its own (the reference keeps them together).
        self._position_in = self._input(ControlInterface.Position)
        self._position_in.synchronization = Synchronization.No
        self._position_in.target_position = [0.0] * n
        # Following a velocity: the joints' velocity changes in proportion, so a Cartesian
        # withdrawal keeps its direction while it ramps.
        self._velocity_in = self._input(ControlInterface.Velocity)
        self._velocity_in.synchronization = Synchronization.Phase
        self._velocity_in.current_position = [0.0] * n

    def _input(self, interface: ControlInterface) -> InputParameter:
        env, n = self.env, self.env.n
        inp = InputParameter(n)
        inp.control_interface = interface
        inp.max_velocity = env.v_max.tolist()
        inp.max_acceleration = env.a_max.tolist()
        inp.max_jerk = env.j_max.tolist()
        inp.target_velocity = [0.0] * n
        inp.target_acceleration = [0.0] * n
        return inp

    # -- the command followed ------------------------------------------------------------
    def follow_position(self, cmd: m.PositionCommand, q: np.ndarray, now_ns: int, ahead: np.ndarray | None,
                        last_seq: int | None, last_stamp_ns: int) -> Event | None:
        """Follow an accepted position target ``q`` (and its setpoints ``ahead``); a clip to report, if any.

        ``last_seq`` and ``last_stamp_ns`` are those of the command accepted
        before: a stream's targets over its period give its velocity, and its
        velocities its acceleration.
        """
        env = self.env
        self._clip_reported = False
        if ahead is not None:
            return self._follow_plan(cmd, q, ahead, now_ns)
        clipped = None
        zero = np.zeros(env.n)
        v_ff, a_ff, j_ff, target_ns = zero, zero, zero, now_ns
        steps: list[np.ndarray] = []
        gap = cmd.seq - last_seq if last_seq is not None else 0
        if self.mode == "position" and self.plan is not None:
            # After a plan, a stream of one command per cycle (a reflex) carries
            # on at the plan's speed until its own period is measured.
            _, v_ff, a_ff, _ = self.reference(now_ns)
            self._new_stream()
            steps = [v_ff * self.period_s]
        elif self.mode == "position" and 1 <= gap <= 10 and cmd.stamp_ns > last_stamp_ns:
            period = self._period(cmd, gap, last_stamp_ns)
            v, clipped = self._at_the_limit(cmd, ((q - self.target) / (gap * period))[None, :],
                                            "position stream moves")
            # The stream's last steps (per period: its derivatives below do not depend on the period's
            # estimate), one per cycle; after a lost command, from the mean step on.
            steps = [*self.steps[-(STREAM_STEPS - 1):], v[0] * period] if gap == 1 else [v[0] * period]
            d1 = steps[-1]
            d2 = d1 - steps[-2] if len(steps) > 1 else zero
            d3 = d2 - (steps[-2] - steps[-3]) if len(steps) > 2 else zero
            # The derivatives at the newest target of the cubic through the last four (Newton's backward form).
            v_ff = clip((d1 + d2 / 2.0 + d3 / 3.0) / period, -env.v_max, env.v_max)
            a_ff = clip((d2 + d3) / (period * period), -env.a_max, env.a_max)
            j_ff = clip(d3 / (period * period * period), -env.j_max, env.j_max)
            target_ns = self._timeline(now_ns, self.target_ns + round(gap * period * 1e9), gap * period)
        elif self.mode != "position":
            self._new_stream()
        self.mode = "position"
        self.target = q
        self.v_ff, self.a_ff, self.j_ff, self.steps = v_ff, a_ff, j_ff, steps
        self.target_ns = target_ns
        self.plan = None
        self.covered_ns = 0
        return clipped

    def _follow_plan(self, cmd: m.PositionCommand, q: np.ndarray, ahead: np.ndarray, now_ns: int) -> Event | None:
        """A command planned ahead: its setpoints, one every ``cmd.period_s`` from its place on the timeline."""
        plan = np.vstack([q, ahead])
        period = cmd.period_s
        v, clipped = self._at_the_limit(cmd, np.diff(plan, axis=0) / period, "planned to move")
        on = self._on_plan(q, now_ns)
        if on is None:
            target_ns, before, offset = now_ns, v[0], np.zeros(self.env.n)
        else:
            target_ns = self._timeline(now_ns, on[0], len(ahead) * period)
            before, offset = on[1], on[2]
        self._new_stream()
        self.mode = "position"
        self.target = q
        self.v_ff, self.a_ff, self.j_ff, self.steps = v[0], np.zeros(self.env.n), np.zeros(self.env.n), []
        self.target_ns = target_ns
        self.plan, self.plan_v, self.plan_v_before, self.plan_period_s = plan, v, before, period
        self.plan_c0 = offset
        self._segments = self._plan_segments()
        self.covered_ns = round(len(ahead) * period * 1e9)
        return clipped

    def _on_plan(self, q: np.ndarray, now_ns: int) -> tuple[int, np.ndarray, np.ndarray] | None:
        """Where ``q`` lies on the path of the plan followed, if it does: that time (ns), the speed just before
        and the offset of that plan's curve from ``q`` there. Where it lies in several places (the arm held
        still), the one nearest ``now_ns``."""
        plan = self.plan
        if self.mode != "position" or plan is None:
            return None
        gaps = np.max(np.abs(plan - q), axis=1)
        at_points = np.flatnonzero(gaps <= PLAN_MATCH_RAD).astype(float).tolist()
        k = int(np.argmin(gaps))
        for i in (k - 1, k):  # on the segments either side of the nearest setpoint
            if 0 <= i < len(plan) - 1:
                seg = plan[i + 1] - plan[i]
                length = float(seg @ seg)
                u = min(max(float((q - plan[i]) @ seg) / length, 0.0), 1.0) if length > 0.0 else 0.0
                if float(np.max(np.abs(plan[i] + u * seg - q))) <= PLAN_MATCH_RAD:
                    at_points.append(i + u)
        if not at_points:
            return None
        period_ns = self.plan_period_s * 1e9
        at = min(at_points, key=lambda x: abs(self.target_ns + x * period_ns - now_ns))
        t_ns = self.target_ns + round(at * period_ns)
        return t_ns, self.plan_v[min(max(int(at - 0.5), 0), len(self.plan_v) - 1)], self._plan_reference(t_ns)[0] - q

    def _period(self, cmd: m.Command, gap: int, last_stamp_ns: int) -> float:
        """The stream's period, s: the median of its stamp steps (robust to the jitter of both loops), smoothed
        (the median of a jittery stream moves by a few per cent from one command to the next)."""
        self.periods.append((cmd.stamp_ns - last_stamp_ns) / gap / 1e9)
        # statistics.median: the same value as np.median, without its overhead on 15 numbers.
        median = min(max(float(statistics.median(self.periods)), MIN_PERIOD_S), MAX_PERIOD_S)
        estimate = self.period_estimate
        self.period_estimate = median if estimate is None else estimate + (median - estimate) * PERIOD_SMOOTHING
        return self.period_estimate

    def _stream_period(self) -> float:
        return self.period_s if self.period_estimate is None else self.period_estimate

    def _new_stream(self) -> None:
        """Forget the stream's period: the next commands measure their own."""
        self.periods.clear()
        self.period_estimate = None

    @staticmethod
    def _timeline(now_ns: int, expected_ns: int, every_s: float) -> int:
        """Where a command arriving at ``now_ns`` goes on its stream's timeline, which expected it at ``expected_ns``.

        Delays only ever add to a command's trip, so the timeline follows the
        earliest arrivals: a command earlier than expected moves it there; a
        later one moves it later by at most :data:`DRIFT` of the time the
        command's step (``every_s``) covers: a lasting delay (another host's
        clock) is followed, the jitter of the loops hardly moves it; one later
        than :data:`MAX_LATE_S` (the stream stalled) starts it afresh.
        """
        lead = now_ns - expected_ns
        if lead <= 0 or lead > MAX_LATE_S * 1e9:
            return now_ns
        return expected_ns + min(lead, round(DRIFT * every_s * 1e9))

    def follow_velocity(self, dq: np.ndarray, cmd: m.Command | None = None, now_ns: int = 0,
                        last_seq: int | None = None, last_stamp_ns: int = 0) -> None:
        """Follow an accepted joint velocity ``dq`` (of ``cmd``, after the command ``last_seq``, if given)."""
        env = self.env
        self._clip_reported = False
        a_ff, target_ns = np.zeros(env.n), now_ns
        gap = cmd.seq - last_seq if cmd is not None and last_seq is not None else 0
        if cmd is not None and self.mode == "velocity" and 1 <= gap <= 10 and cmd.stamp_ns > last_stamp_ns:
            step_s = gap * self._period(cmd, gap, last_stamp_ns)
            a_ff = clip((dq - self.target) / step_s, -env.a_max, env.a_max)
            target_ns = self._timeline(now_ns, self.target_ns + round(step_s * 1e9), step_s)
        elif self.mode != "velocity":
            self._new_stream()
        self.mode = "velocity"
        self.target = dq
        self.v_ff, self.a_ff, self.j_ff, self.steps = np.zeros(env.n), a_ff, np.zeros(env.n), []
        self.target_ns = target_ns
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

    # -- the reference ---------------------------------------------------------------------
    def reference(self, t_ns: int) -> Reference:
        """The position reference at ``t_ns``: its position, velocity, acceleration and jerk (module docstring)."""
        if self.plan is not None:
            r, v, a = self._plan_reference(t_ns)
            j = np.zeros(self.env.n)
        else:
            r, v, a, j = self._stream_reference(t_ns)
        env = self.env
        held = (r < env.q_min) | (r > env.q_max)
        if held.any():  # a reference at a joint limit stays there
            r = clip(r, env.q_min, env.q_max)
            v, a, j = np.where(held, 0.0, v), np.where(held, 0.0, a), np.where(held, 0.0, j)
        return r, v, a, j

    def _plan_reference(self, t_ns: int) -> State:
        """The plan's curve: its velocity linear between the segments' velocities (at their midpoints).

        Within segment i (``tau`` s after setpoint i, period T), with the
        segments' velocities ``v[i-1], v[i], v[i+1]``, the curve is the
        polyline plus the integral of the velocity's difference from ``v[i]``,
        and an offset ``c_i = c_0 + ((v[i] - v[i-1]) - (v[0] - v[-1])) T / 8`` that
        makes it continuous from segment to segment (``c_0``: where the plan
        before left it, 0 for a plan that continues none; it stays within an
        eighth of the change of acceleration times T^2). ``v[-1]`` is the speed
        before the plan, and past its last segment the speed goes on changing
        as it did there (one more segment), as the next plan will continue it.
        """
        period = self.plan_period_s
        n_seg = len(self.plan_v)
        tau_all = (t_ns - self.target_ns) / 1e9
        half = 0.5 * period
        if tau_all < -half:  # before the plan: on its first half-segment's line, back at the speed before it
            r, _, _ = self._plan_segment(0, -half)
            back = max(tau_all, -MAX_PERIOD_S) + half
            return r + self.plan_v_before * back, self.plan_v_before, np.zeros(self.env.n)
        if tau_all >= n_seg * period:  # past its end (the next command is late): one segment more, then on, briefly
            over = tau_all - n_seg * period
            r, v, a = self._plan_segment(n_seg, min(over, MAX_PERIOD_S))
            return (r, np.zeros(self.env.n), a * 0.0) if over >= MAX_PERIOD_S else (r, v, a)
        i = min(max(int(tau_all / period), 0), n_seg - 1)
        return self._plan_segment(i, tau_all - i * period)

    def _plan_segment(self, i: int, tau: float) -> State:
        """The plan's curve ``tau`` s into segment ``i`` (the one past the last: ``len(plan_v)``)."""
        plan, period = self.plan, self.plan_period_s
        assert plan is not None
        v_i, d1, d2, c = self._segments[i]
        if tau <= 0.5 * period:
            r = plan[i] + v_i * tau + c + d1 * (tau - tau * tau / period)
            return r, v_i + d1 * (1.0 - 2.0 * tau / period), d1 * (-2.0 / period)
        s = tau - 0.5 * period
        r = plan[i] + v_i * tau + c + d1 * (0.25 * period) + d2 * (s * s / period)
        if s > 0.5 * period:  # past the segment (the one beyond the last): on at its speed
            return r, v_i + d2 * (2.0 * s / period), np.zeros(self.env.n)
        return r, v_i + d2 * (2.0 * s / period), d2 * (2.0 / period)

    def _plan_segments(self) -> np.ndarray:
        """Per segment of the plan (and the one past its last): its velocity, the half-differences to the
        velocities before and after it, its offset (see :meth:`_plan_reference`); computed once per plan."""
        v, before, period = self.plan_v, self.plan_v_before, self.plan_period_s
        beyond = 2.0 * v[-1] - (v[-2] if len(v) > 1 else before)  # the segment after the last, extrapolated
        speeds = np.vstack([before, v, beyond, beyond])  # v[-1] .. v[n], and v[n] again: no change after it
        v_i, v_prev, v_next = speeds[1:-1], speeds[:-2], speeds[2:]
        c = self.plan_c0 + ((v_i - v_prev) - (v[0] - before)) * (period / 8.0)
        return np.stack([v_i, 0.5 * (v_prev - v_i), 0.5 * (v_next - v_i), c], axis=1)

    def _stream_reference(self, t_ns: int) -> Reference:
        """A stream's cubic from its last target (its velocity, acceleration and jerk there), extrapolated briefly:
        its jerk for a period, its acceleration for ACCEL_PERIODS, its velocity on to MAX_PERIOD_S."""
        period = self._stream_period()
        zero = np.zeros(self.env.n)
        tau = min(max((t_ns - self.target_ns) / 1e9, -ACCEL_PERIODS * period), MAX_PERIOD_S)
        tj = min(tau, period)
        ta = min(tau, ACCEL_PERIODS * period)
        v, a, j = self.v_ff, self.a_ff, self.j_ff
        a_j = a + j * tj  # the acceleration where the jerk ends
        v_j = v + a * tj + j * (0.5 * tj * tj)
        r = self.target + v * tj + a * (0.5 * tj * tj) + j * (tj * tj * tj / 6.0)
        v_a = v_j + a_j * (ta - tj)
        r = r + v_j * (ta - tj) + a_j * (0.5 * (ta - tj) ** 2) + v_a * (tau - ta)
        if tau >= MAX_PERIOD_S:
            return r, zero, zero, zero
        if tau >= ACCEL_PERIODS * period:
            return r, v_a, zero, zero
        return r, v_a, a_j, j if tau < period else zero

    def _velocity_reference(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """A velocity stream's velocity and its rate of change at ``t_ns`` (the rate for two periods at most)."""
        period = self._stream_period()
        tau = min(max((t_ns - self.target_ns) / 1e9, -ACCEL_PERIODS * period), ACCEL_PERIODS * period)
        v = self.target + self.a_ff * tau
        env = self.env
        if tau >= ACCEL_PERIODS * period:
            return clip(v, -env.v_max, env.v_max), np.zeros(env.n)
        return clip(v, -env.v_max, env.v_max), self.a_ff

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
        """One cycle of ``h`` s ending at ``t_ns`` towards the command of ``active``; a clip to report, if any."""
        env = self.env
        start_ns = t_ns - round(h * 1e9)
        clipped = None
        zero = np.zeros(env.n)
        if self.mode == "position":
            # The reference over the cycle: the cubic that ends where the reference is at its end (a plan
            # that has just arrived starts there).
            r1, v1, a1, jerk = self.reference(t_ns)
            a0 = a1 - jerk * h
            v0 = v1 - a0 * h - jerk * (0.5 * h * h)
            frame: Frame = (r1 - v0 * h - a0 * (0.5 * h * h) - jerk * (h * h * h / 6.0), v0, a0, jerk)
        elif self.mode == "velocity":
            v_ref, a_ref = self._velocity_reference(start_ns)
            frame = (None, v_ref, a_ref, zero)
            jump = np.abs(self.target - self.dq) / (env.a_max * max(h, self.period_s))
            if float(np.max(jump)) > ACCEL_JITTER_CYCLES and not self._clip_reported:
                i = int(np.argmax(jump))
                clipped = self._clip(
                    "command_clipped",
                    f"velocity command from {active!r}: joint {env.joints[i]} asks for {self.target[i]:.3f} rad/s "
                    f"from {self.dq[i]:.3f} rad/s, a_max {env.a_max[i]:.2f} rad/s^2: ramped at the limit",
                )
        else:
            frame = (None, zero, zero, zero)
        state = self._law(frame, h, None)
        if state is None:  # ruckig failed (it does not with valid limits): the acceleration-limited law
            if frame[0] is not None:
                return self._limit(frame[1].tolist(), h, self.reference(t_ns)[0].tolist(), active) or clipped
            return self._limit(frame[1].tolist(), h, None, active) or clipped
        bounded = self._guard(state, h)
        limited = None
        if self.limiter is not None:
            state, limited = self._caps(state, frame, h, t_ns, active)
            again = self._guard(state, h)  # the caps only slow the joints, but the stop check is the last word
            bounded = bounded if bounded >= 0 else again
        q1, v1, a1 = state
        self.q, self.dq, self.ddq = clip(q1, env.q_min, env.q_max), clip(v1, -env.v_max, env.v_max), a1
        if limited is None and bounded >= 0 and not self._clip_reported:
            i = bounded
            limited = self._clip(
                "joint_limit",
                f"{self.mode} command from {active!r}: joint {env.joints[i]} at {self.q[i]:.4f} rad approaches "
                f"its limit [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}]: braking (the jerk-limited stop ends within it)",
            )
        return clipped or limited

    def _law(self, frame: Frame, h: float, cap: np.ndarray | None) -> State | None:
        """One cycle of the jerk-limited law in ``frame``; None if ruckig failed.

        ``frame``: the reference at the start of the cycle (its position, or
        None for a velocity command; its velocity, acceleration, and jerk over
        the cycle). The commanded state relative to it is brought to rest
        time-optimally, within what the envelope leaves once the frame's own
        motion is counted (the jerk: ``j_max`` less the frame's). ``cap``:
        joint speeds not to exceed (the Cartesian limits anticipated).
        """
        env = self.env
        r0, v_ref, a_ref, jerk = frame
        v_max, v_lim = env.v_max, self._v_lim
        if cap is not None:  # a reference beyond the speeds allowed is slowed as a whole: its direction kept
            v_max = np.minimum(v_max, np.maximum(cap, 1e-6))
            v_lim = v_max * FEASIBLE
            slow = min(1.0, float(np.min(v_lim / np.maximum(np.abs(v_ref), 1e-12))))
            v_ref, a_ref, jerk = v_ref * slow, a_ref * slow, jerk * slow
        a_lim = self._a_lim
        a_ref = clip(a_ref, -a_lim, a_lim)
        jerky = r0 is not None and bool(jerk.any())
        if jerky:
            # The frame jerks as the reference does only where the arm is on it: the law then has what the
            # reference leaves of the jerk limit (ruckig's are symmetric), enough to stay on it; farther off,
            # a frame of constant acceleration leaves it the whole limit to get there.
            on = (np.abs(self.q - r0) <= ON_REFERENCE_RAD) & (np.abs(self.dq - v_ref) <= ON_REFERENCE_RAD_S) \
                & (np.abs(self.ddq - a_ref) <= ON_REFERENCE_RAD_S2)
            jerk = clip(clip(np.where(on, jerk, 0.0), -self._j_lim, self._j_lim), (-a_lim - a_ref) / h,
                        (a_lim - a_ref) / h)  # within the floor's share, and feasible on
            a_end = a_ref + jerk * h
        else:
            jerk = self._zero
            a_end = a_ref
        trajectory = self._trajectory
        du = self.ddq - a_ref
        if r0 is not None:
            v_ref = clip(v_ref, -v_lim, v_lim)
            u = self.dq - v_ref
            inp = self._position_in
            inp.current_position = (self.q - r0).tolist()
            inp.max_velocity = (v_max - v_ref).tolist()
            inp.min_velocity = (-v_max - v_ref).tolist()
            inp.max_jerk = (env.j_max - np.abs(jerk)).tolist() if jerky else self._j
        else:
            u = self.dq - v_ref
            inp = self._velocity_in
            # A velocity step keeps its direction (a Cartesian withdrawal's) while it ramps only if the joints
            # stay in proportion: ruckig synchronises their phases when the state is collinear, to its tolerance.
            uu = float(u @ u)
            if uu > 0.0:
                along = u * (float(du @ u) / uu)
                if float(np.abs(du - along).max()) <= COLLINEAR * float(np.abs(du).max()) + 1e-12:
                    du = along
        inp.current_velocity = u.tolist()
        inp.current_acceleration = du.tolist()
        inp.max_acceleration = (env.a_max - a_end).tolist()
        inp.min_acceleration = (-env.a_max - a_end).tolist()
        try:
            result = self._otg.calculate(inp, trajectory)
        except (RuckigError, RuntimeError, ValueError):  # an input it rejects, or an error code it does not name
            result = Result.Error
        if result not in (Result.Working, Result.Finished):
            if r0 is None:
                return None
            # A position it cannot reach within the speeds allowed (a cap close to the reference's
            # own speed): this cycle, the velocity law at the reference's speed.
            return self._law((None, v_ref, a_ref, self._zero), h, cap)
        x, dx, ddx = trajectory.at_time(h)
        if jerky:
            assert r0 is not None
            q1 = r0 + v_ref * h + a_ref * (0.5 * h * h) + jerk * (h * h * h / 6.0) + np.asarray(x)
            return q1, v_ref + a_ref * h + jerk * (0.5 * h * h) + np.asarray(dx), a_end + np.asarray(ddx)
        q1 = (r0 if r0 is not None else self.q) + v_ref * h + a_ref * (0.5 * h * h) + np.asarray(x)
        return q1, v_ref + a_ref * h + np.asarray(dx), a_ref + np.asarray(ddx)

    def _guard(self, state: State, h: float) -> int:
        """Brake the joints whose stop from ``state`` would pass a limit (in place); the first one, or -1.

        A joint brakes along its time-optimal stop from its current state
        instead: from a state that could stop in time, that stop still ends
        within the limits, so the arm always can.
        """
        q1, v1, a1 = state
        bounded = -1
        q0, dq0, ddq0 = self.q, self.dq, self.ddq
        for i, (q_min, q_max, _v_max, a_max, _k) in enumerate(self.env.per_joint):
            q, v, a = float(q1[i]), float(v1[i]), float(a1[i])
            j = self._j[i]
            # Far from both limits no stop reaches them: it lasts at most (|v| + a^2/2j) / a_max + 2 a_max / j
            # + |a| / j at speeds of at most |v| + a^2 / 2j.
            fastest = abs(v) + a * a / (2.0 * j)
            reach = fastest * (fastest / a_max + (2.0 * a_max + abs(a)) / j)
            if q_min + reach < q < q_max - reach:
                continue
            lo, hi = stop_extent(v, a, a_max, j)
            if q + hi <= q_max + LIMIT_SLACK_RAD and q + lo >= q_min - LIMIT_SLACK_RAD:
                continue
            dx, v, a = brake(float(dq0[i]), float(ddq0[i]), h, a_max, j)
            q1[i], v1[i], a1[i] = float(q0[i]) + dx, v, a
            if bounded < 0:
                bounded = i
        return bounded

    def begin_rejoin(self, cap: float | None = None, cycles: int = 0) -> None:
        """Rejoin the stream (when it is a position stream) at no more than its own peak speed, or ``cap`` (m/s).

        After a hold, the stream's own peak so far; after a switch, the
        outgoing stream's (the incoming one's speed is its claim) for at
        least ``cycles`` control cycles, joined or not.
        """
        self.rejoining = True
        self.rejoin_cap = cap
        self.rejoin_cycles = cycles

    def _caps(self, state: State, frame: Frame, h: float, t_ns: int, active: str, *,
              rerun: bool = True) -> tuple[State, Event | None]:
        """The cycle's state within the Cartesian limits and the power limit; a scaling to report, if any.

        First the velocity the joints level off at if their acceleration
        (one more cycle's worth of jerk on) is ramped down at the jerk limit:
        beyond a limit, the law runs again with the joint speeds capped in
        proportion. Then the hard caps: a velocity still beyond a limit is
        scaled down as a whole, the acceleration limited, the power eased.
        """
        limiter = self.limiter
        assert limiter is not None
        env = self.env
        cap = None
        v_ref = frame[1]
        # The stream's own fastest point, m/s (a velocity stream: not a reference to catch up); None: not computed,
        # only needed for a scaling reported below (self.q and v_ref do not change before).
        own: float | None = float("inf")
        if self.mode == "position":
            top = limiter.limits.speed_m_s
            if not v_ref.any():
                own = 0.0
                self.stream_peak = min(max(self.stream_peak, own), top)
            elif self.stream_peak >= top or limiter.within_speed(self.q, v_ref, self.stream_peak):
                # The running peak keeps its value (capped at the limit): own <= stream_peak, or both beyond the limit.
                own = None
                self.stream_peak = min(self.stream_peak, top)
            else:
                own = limiter.top_speed(self.q, v_ref)
                self.stream_peak = min(max(self.stream_peak, own), top)
            if self.rejoining:
                cap = self.rejoin_cap if self.rejoin_cap is not None else max(self.stream_peak, REJOIN_FLOOR_M_S)
        else:
            self.rejoining = False
        if self.withdrawal and not self.reflex and (
                limiter.within_speed(self.q, self.dq, limiter.limits.speed_m_s)
                or limiter.top_speed(self.q, self.dq) <= limiter.limits.speed_m_s):
            self.withdrawal = False
            self.toward = None
        q1, v1, a1 = state
        j = env.j_max
        ramp = np.abs(a1) + j * h
        rising = (a1 * v1 >= 0.0) & (a1 != 0.0)
        level = np.where(rising, v1 + np.sign(a1) * ramp * ramp / (2.0 * j), v1)

        def limits(v: np.ndarray) -> Scaling | None:
            return limiter.scale(self.q, v, withdrawal=self.withdrawal, toward=self.toward, speed_cap=cap)

        hard = scaling = None  # scaling: what changed the motion this cycle, if anything
        if float(np.abs(level - v1).sum()) > LEVEL_OFF * float(np.abs(v1).sum()) + LEVEL_OFF_RAD_S:
            # Speeding up: the velocity the joints level off at, against the limits.
            ahead = limits(level)
            bound = None if ahead is None else np.abs(level) * (ahead.factor * (1.0 - CAP_MARGIN))
            check = True
        else:
            # Not much: the cycle's velocity grown by NEAR_LIMIT. Within every limit (each grows with the
            # velocity), the velocity is within them too; near one, it is held a little below.
            ahead = limits(v1 * (1.0 + NEAR_LIMIT))
            bound = None
            if ahead is not None:  # the speeds at which the velocity would reach the limit, a little below
                factor = ahead.factor * (1.0 + NEAR_LIMIT)
                bound = np.abs(v1) * (factor * (1.0 - CAP_MARGIN))
                ahead = dataclasses.replace(ahead, value=ahead.value / (1.0 + NEAR_LIMIT), factor=min(1.0, factor))
            check = ahead is not None
        if bound is not None and rerun:
            capped = self._law(frame, h, bound)
            if capped is not None:
                self._guard(capped, h)
                if float(np.max(np.abs(capped[1] - v1))) > 1e-9:
                    scaling = ahead
                q1, v1, a1 = capped
        if check:
            hard = limits(v1)
        dq0 = self.dq
        if hard is not None:  # the hard cap: the velocity scaled as a whole, the change attributed to this cycle
            scaled = clip(v1 * hard.factor, dq0 - env.a_max * h, dq0 + env.a_max * h)
            q1 = q1 + (scaled - v1) * (0.5 * h)
            a1 = clip(a1 + (scaled - v1) / h, -env.a_max, env.a_max)
            v1 = scaled
            scaling = hard
        eased = self._power(v1, h)
        if eased is not None:  # eased acceleration: off the jerk-limited path, the cycle's mean acceleration
            v1 = dq0 + eased.factor * (v1 - dq0)
            q1 = self.q + 0.5 * (dq0 + v1) * h
            a1 = (v1 - dq0) / h
            scaling = eased
        self.rejoin_cycles -= 1
        if self.rejoining and self.rejoin_cycles <= 0 and (scaling is None or scaling.what != "rejoin speed") \
                and frame[0] is not None:
            target, speed, _, _ = self.reference(t_ns)
            if float(np.max(np.abs(target - q1))) < REJOIN_TOLERANCE_RAD and \
                    float(np.max(np.abs(speed - v1))) < REJOIN_TOLERANCE_RAD_S:
                self.rejoining = False
        if scaling is None:
            return (q1, v1, a1), None
        self.limited += 1
        if self._clip_reported:
            return (q1, v1, a1), None
        if own is None:
            own = limiter.top_speed(self.q, v_ref)
        self.catching_up = own <= limiter.limits.speed_m_s * (1.0 - CAP_MARGIN)
        return (q1, v1, a1), self._clip("cartesian_limit", f"{self.mode} command from {active!r}: {scaling.describe()}")

    def _power(self, v: np.ndarray, h: float) -> Scaling | None:
        """How much of the cycle's change of velocity (to ``v``) keeps the power within its limit; None: all of it."""
        limiter = self.limiter
        assert limiter is not None
        if not v.any() and not self.dq.any():
            return None
        return limiter.power_scale(self.q, self.dq, v, h)

    def _limit(self, v_des: list[float], h: float, target: list[float] | None, active: str) -> Event | None:
        """One cycle of the acceleration-limited law (per joint, in floats): ruckig's stand-in; a clip, if any.

        Never used while ruckig plans (it does with valid limits): with a
        position ``target``, ``v_des`` is its feed-forward velocity, plus a
        correction that can brake in time at ``a_max``; then the speed limit,
        the braking distance to the joint limits (:meth:`Envelope.braking_speed`,
        the same formula), the acceleration limit; then the Cartesian limits'
        hard caps. It does not limit the jerk.
        """
        q0, dq0 = self.q.tolist(), self.dq.tolist()
        v_ff = np.array(v_des)
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
        v1, q1, a1 = [], [], []
        for i, (q_min, q_max, _v_max, a_max, _k) in enumerate(per_joint):
            q, dq = q0[i], dq0[i]
            v = min(max(bounded_v[i], dq - a_max * h), dq + a_max * h)
            v1.append(v)
            q1.append(min(max(q + 0.5 * (dq + v) * h, q_min), q_max))
            a1.append((v - dq) / h)
        state = np.array(q1), np.array(v1), np.array(a1)
        clipped = None
        if self.limiter is not None:
            # The hard caps (the law cannot be run again under them: it is what failed).
            zero = np.zeros(self.env.n)
            state, clipped = self._caps(state, (None, v_ff, zero, zero), h, 0, active, rerun=False)
            state = clip(state[0], self.env.q_min, self.env.q_max), state[1], state[2]
        if clipped is None and bound_i >= 0 and not self._clip_reported:
            env, i = self.env, bound_i
            clipped = self._clip(
                "joint_limit",
                f"{self.mode} command from {active!r}: joint {env.joints[i]} at {q0[i]:.4f} rad approaches "
                f"its limit [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}] at {v_des[i]:.3f} rad/s: speed bounded to "
                f"{bound_v:.3f} rad/s (the braking distance)",
            )
        self.q, self.dq, self.ddq = state
        return clipped

    def _clip(self, code: str, message: str) -> Event:
        """A clip of the tracker, reported once per command (not per cycle)."""
        self._clip_reported = True
        return Event("warning", code, message)

    # -- the controlled stop -------------------------------------------------------------
    def begin_stop(self, now_ns: int) -> Event | None:
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
        env = self.env
        velocity = clip(self.dq, -env.v_max, env.v_max)
        acceleration = clip(self.ddq, -env.a_max, env.a_max)
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
            result = self._plan_stop(velocity, a0, sync, candidate)
            if result not in (Result.Working, Result.Finished):
                break
            within, faster = self._stop_check(candidate, velocity)
            if first is None:
                first = candidate
            if within and fits_limits is None:
                fits_limits = candidate
            if within and not faster:
                trajectory = candidate
                break
        if trajectory is None:
            trajectory = fits_limits if fits_limits is not None else first
        self._otg_in.synchronization = Synchronization.Time
        failed = None
        if trajectory is not None:
            end, _, _ = trajectory.at_time(trajectory.duration)
            distance = np.asarray(end) - self.q
            duration = float(trajectory.duration)
        else:
            # Constant deceleration at the acceleration limit, per joint: never
            # happens with valid limits, but a stop must never fail.
            distance = self.dq * np.abs(self.dq) / (2.0 * env.a_max)
            duration = float(np.max(np.abs(self.dq) / env.a_max))
            failed = Event("error", "stop_fallback",
                           f"ruckig could not plan the stop ({result}): constant deceleration instead")
        self.stop = Stop(trajectory, now_ns, self.q.copy(), distance, duration)
        self.stop_distance = distance
        self.stop_time_s = duration
        return failed

    def _plan_stop(self, velocity: np.ndarray, acceleration: np.ndarray, sync: Synchronization,
                   trajectory: Trajectory) -> Result:
        inp = self._otg_in
        inp.current_position = self.q.tolist()
        inp.current_velocity = velocity.tolist()
        inp.current_acceleration = acceleration.tolist()
        inp.synchronization = sync
        try:
            return self._otg.calculate(inp, trajectory)
        except (RuckigError, RuntimeError, ValueError):
            return Result.Error

    def _stop_check(self, trajectory: Trajectory, velocity: np.ndarray) -> tuple[bool, bool]:
        """Whether a planned stop stays within the joint limits, and whether any point then moves faster than allowed:
        the Cartesian speed limit of the motion, or the speed at the start if that was faster.

        Sampled every :data:`STOP_CHECK_S` over its first :data:`STOP_CHECK_SPAN_S`
        (its speed peaks while the acceleration ramps down, within ``a_max / j_max``)
        and at its end.
        """
        env, limiter = self.env, self.limiter
        duration = float(trajectory.duration)
        times = np.append(np.arange(STOP_CHECK_S, min(duration, STOP_CHECK_SPAN_S), STOP_CHECK_S), duration)
        allowed = 0.0
        if limiter is not None:
            limit = limiter.limits.withdrawal_speed_m_s if self.withdrawal else limiter.limits.speed_m_s
            allowed = max(limit, float(limiter.speeds(self.q, velocity).max())) + STOP_SPEED_SLACK_M_S
        within, faster = True, False
        for t in times:
            q, dq, _ = trajectory.at_time(float(t))
            q = np.asarray(q)
            if np.any(q < env.q_min - LIMIT_SLACK_RAD) or np.any(q > env.q_max + LIMIT_SLACK_RAD):
                within = False
            if limiter is not None and not faster and float(limiter.speeds(q, np.asarray(dq)).max()) > allowed:
                faster = True
        return within, faster

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
        self._otg = self._otg_in = self._position_in = self._velocity_in = self._trajectory = None
        if self.stop is not None:
            self.stop.trajectory = None
