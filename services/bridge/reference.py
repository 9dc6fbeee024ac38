"""The tracker's reference: the command it follows, as a position, velocity, acceleration and jerk at any time.

:class:`Reference` owns the accepted command (a position target with the
feed-forward velocity of its stream, a plan of setpoints ahead, or a joint
velocity), its place on its stream's timeline, and the stream's period; it
reads no joint state. The tracker (:mod:`.tracking`) hands it each accepted
command (:meth:`Reference.follow_position`, :meth:`Reference.follow_velocity`)
and asks it, each cycle, where the reference is (:meth:`Reference.at`,
:meth:`Reference.velocity_at`).

A command becomes a reference with a velocity, an acceleration and a jerk: a
plan's setpoints the curve whose velocity runs linearly between its segments'
velocities (continuous in velocity, within nanoradians of the setpoints); a
stream of one command per cycle the cubic through its last four targets (its
derivatives at the newest), a velocity stream its velocity and rate of
change. Each command goes on its stream's own timeline, where the previous one
puts it (a plan's first setpoint on the previous plan's path, a stream's next
target one period on); the timeline follows the commands' earliest arrivals
and drifts later by at most :data:`DRIFT`, so the jitter of the planner's and
the bridge's loops does not make the reference jump back and forth (it did,
and the task ran 20-30 % faster than planned). A handover between planners is
the supervisor's (:mod:`.core`); the tracker rejoins the incoming stream under
the Cartesian limits (:mod:`.limits`).
"""

from __future__ import annotations

import statistics
from collections import deque
from typing import Literal

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.checks import MAX_PERIOD_S, MIN_PERIOD_S, Event, command_name
from nwr.services.bridge.envelope import Envelope, clip

# Relative tolerance before an implied speed counts as a clip (rounding).
SPEED_TOLERANCE = 1.01
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
# The median of a stream's stamp steps is smoothed by this share per command, once it is the median of this
# many steps: a new stream's first step can be a reflex's onset, sent at once on its pain message and followed
# by a skipped cycle (one cycle's motion over two periods); smoothed from there, the stream's speed was
# underestimated by up to 40 % for 100 ms, the arm fell behind it and caught up beyond the speed limits.
PERIOD_SMOOTHING = 0.05
PERIOD_SEED = 3
# A stream's acceleration is extrapolated this many periods past its last
# command (a late command), its velocity on to MAX_PERIOD_S.
ACCEL_PERIODS = 2.0

CommandMode = Literal["none", "position", "velocity"]
State = tuple[np.ndarray, np.ndarray, np.ndarray]  # position, velocity, acceleration
Sample = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # position, velocity, acceleration, jerk


class Reference:
    """The command followed, and the reference it makes: where, how fast, accelerating and jerking, and when."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, period_s: float) -> None:
        self.env = env
        self.period_s = period_s  # the control period, s
        n = env.n
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
        self.segments = np.zeros((0, 4, n))
        self.plan_period_s = 0.0
        self.covered_ns = 0
        self.periods: deque[float] = deque(maxlen=15)
        self.period_estimate: float | None = None

    def follow_position(self, cmd: m.PositionCommand, q: np.ndarray, now_ns: int, ahead: np.ndarray | None,
                        last_seq: int | None, last_stamp_ns: int) -> Event | None:
        """Follow an accepted position target ``q`` (and its setpoints ``ahead``); a clip to report, if any.

        ``last_seq`` and ``last_stamp_ns`` are those of the command accepted
        before: a stream's targets over its period give its velocity, and its
        velocities its acceleration.
        """
        env = self.env
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
            _, v_ff, a_ff, _ = self.at(now_ns)
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
        self.segments = self._plan_segments()
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
        once it has :data:`PERIOD_SEED` of them (the median of a jittery stream moves by a few per cent from one
        command to the next)."""
        self.periods.append((cmd.stamp_ns - last_stamp_ns) / gap / 1e9)
        # statistics.median: the same value as np.median, without its overhead on 15 numbers.
        median = min(max(float(statistics.median(self.periods)), MIN_PERIOD_S), MAX_PERIOD_S)
        estimate = self.period_estimate
        if estimate is None or len(self.periods) <= PERIOD_SEED:
            self.period_estimate = median
        else:
            self.period_estimate = estimate + (median - estimate) * PERIOD_SMOOTHING
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
    def at(self, t_ns: int) -> Sample:
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
        v_i, d1, d2, c = self.segments[i]
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

    def _stream_reference(self, t_ns: int) -> Sample:
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

    def velocity_at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """A velocity stream's velocity and its rate of change at ``t_ns`` (the rate for two periods at most)."""
        period = self._stream_period()
        tau = min(max((t_ns - self.target_ns) / 1e9, -ACCEL_PERIODS * period), ACCEL_PERIODS * period)
        v = self.target + self.a_ff * tau
        env = self.env
        if tau >= ACCEL_PERIODS * period:
            return clip(v, -env.v_max, env.v_max), np.zeros(env.n)
        return clip(v, -env.v_max, env.v_max), self.a_ff
