"""The tracker's limits, each cycle: the joint limits and the Cartesian limits of the law's next state.

:class:`JointLimits` brakes a joint whose next state could not stop (its
time-optimal jerk-limited stop, :func:`~.envelope.stop_extent`) before its
limits along that stop instead (:func:`~.envelope.brake`): by induction the
arm can always stop within them.

:class:`CartesianCaps` owns what the Cartesian limits depend on (whether the
command is a withdrawal, the direction into the contact, a rejoin after a
hold or a handover, the stream's own peak speed) and applies them with the
limiter (:class:`~.cartesian.CartesianLimiter`): every point's speed, the
speed toward a contact, the momentum, the stopping time and distance, a
rejoin's speed. They are anticipated: where the joints, their acceleration
ramped down from the next cycle on, would level off beyond them, or the
velocity is within :data:`NEAR_LIMIT` of them, the law (:mod:`.law`) runs
again with the joint speeds capped in proportion, a little below
(:data:`CAP_MARGIN`): the arm levels off at the limit within the jerk limit.
They remain hard caps: a velocity still beyond them is scaled down as a
whole, within ``a_max``; then the power limit eases the acceleration. Only
these hard caps (never in the demo sessions: a stream beyond the limits), a
fault's hold, and a stop begun while accelerating too close to the speed limit
(:mod:`.stop`) make a cycle's jerk exceed ``j_max``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from nwr.services.bridge.cartesian import CartesianLimiter, Scaling
from nwr.services.bridge.envelope import Envelope, brake, clip, stop_extent
from nwr.services.bridge.law import Frame, Joints, Law, State
from nwr.services.bridge.reference import Reference

# Rejoining a position stream after a hold ends once the arm is on the stream:
# this close to its reference (rad, every joint) and its velocity (rad/s), with
# the rejoin speed no longer binding. Closer than that, what is left to catch up
# adds next to nothing to the stream's own speed (the law closes a gap
# time-optimally: 10 mrad would take a point 0.1 m/s beyond the stream).
REJOIN_TOLERANCE_RAD = 1e-5
REJOIN_TOLERANCE_RAD_S = 1e-3
# The slowest a rejoin may be capped at, m/s (a stream that has not moved yet).
REJOIN_FLOOR_M_S = 0.05
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


class JointLimits:
    """The stop check against the joint limits of the commanded state's next value."""

    def __init__(self, env: Envelope, joints: Joints) -> None:
        self.env = env
        self.joints = joints
        self.j = env.j_max.tolist()

    def guard(self, state: State, h: float) -> int:
        """Brake the joints whose stop from ``state`` would pass a limit (in place); the first one, or -1.

        A joint brakes along its time-optimal stop from its current state
        instead: from a state that could stop in time, that stop still ends
        within the limits, so the arm always can.
        """
        q1, v1, a1 = state
        bounded = -1
        # The joints' values as floats, read once (an array's items one by one cost more than the checks).
        for i, (q_min, q_max, _v_max, a_max, _k), q, v, a, j in zip(range(len(self.j)), self.env.per_joint,
                                                                    q1.tolist(), v1.tolist(), a1.tolist(), self.j):
            # Far from both limits no stop reaches them: it lasts at most (|v| + a^2/2j) / a_max + 2 a_max / j
            # + |a| / j at speeds of at most |v| + a^2 / 2j.
            fastest = abs(v) + a * a / (2.0 * j)
            reach = fastest * (fastest / a_max + (2.0 * a_max + abs(a)) / j)
            if q_min + reach < q < q_max - reach:
                continue
            lo, hi = stop_extent(v, a, a_max, j)
            if q + hi <= q_max + LIMIT_SLACK_RAD and q + lo >= q_min - LIMIT_SLACK_RAD:
                continue
            joints = self.joints
            dx, v, a = brake(float(joints.dq[i]), float(joints.ddq[i]), h, a_max, j)
            q1[i], v1[i], a1[i] = float(joints.q[i]) + dx, v, a
            if bounded < 0:
                bounded = i
        return bounded

class CartesianCaps:
    """The Cartesian and power limits of each cycle, and what they depend on (module docstring)."""

    def __init__(self, env: Envelope, limiter: CartesianLimiter | None, joints: Joints, law: Law,
                 joint_limits: JointLimits, reference: Reference) -> None:
        self.env = env
        self.joints = joints
        self.law = law  # run again under the anticipated caps
        self.joint_limits = joint_limits
        self.reference = reference  # read: its mode, where it is (a rejoin's end)
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

    def begin_rejoin(self, cap: float | None = None, cycles: int = 0) -> None:
        """Rejoin the stream (when it is a position stream) at no more than its own peak speed, or ``cap`` (m/s).

        After a hold, the stream's own peak so far; after a switch, the
        outgoing stream's (the incoming one's speed is its claim) for at
        least ``cycles`` control cycles, joined or not.
        """
        self.rejoining = True
        self.rejoin_cap = cap
        self.rejoin_cycles = cycles

    def apply(self, state: State, frame: Frame, h: float, t_ns: int, active: str, reported: bool, *,
              rerun: bool = True) -> tuple[State, str | None]:
        """The cycle's state within the Cartesian limits and the power limit; a scaling to report, if any
        (none once the command's clip was ``reported``).

        First the velocity the joints level off at if their acceleration
        (one more cycle's worth of jerk on) is ramped down at the jerk limit:
        beyond a limit, the law runs again with the joint speeds capped in
        proportion. Then the hard caps: a velocity still beyond a limit is
        scaled down as a whole, the acceleration limited, the power eased.
        """
        limiter = self.limiter
        assert limiter is not None
        env, joints = self.env, self.joints
        cap = None
        v_ref = frame[1]
        # The stream's own fastest point, m/s (a velocity stream: not a reference to catch up); None: not computed,
        # only needed for a scaling reported below (joints.q and v_ref do not change before).
        own: float | None = float("inf")
        if self.reference.mode == "position":
            top = limiter.limits.speed_m_s
            if not v_ref.any():
                own = 0.0
                self.stream_peak = min(max(self.stream_peak, own), top)
            elif self.stream_peak >= top or limiter.within_speed(joints.q, v_ref, self.stream_peak):
                # The running peak keeps its value (capped at the limit): own <= stream_peak, or both beyond the limit.
                own = None
                self.stream_peak = min(self.stream_peak, top)
            else:
                own = limiter.top_speed(joints.q, v_ref)
                self.stream_peak = min(max(self.stream_peak, own), top)
            if self.rejoining:
                cap = self.rejoin_cap if self.rejoin_cap is not None else max(self.stream_peak, REJOIN_FLOOR_M_S)
        else:
            self.rejoining = False
        if self.withdrawal and not self.reflex and (
                limiter.within_speed(joints.q, joints.dq, limiter.limits.speed_m_s)
                or limiter.top_speed(joints.q, joints.dq) <= limiter.limits.speed_m_s):
            self.withdrawal = False
            self.toward = None
        q1, v1, a1 = state
        j = env.j_max
        ramp = np.abs(a1) + j * h
        rising = (a1 * v1 >= 0.0) & (a1 != 0.0)
        level = np.where(rising, v1 + np.sign(a1) * ramp * ramp / (2.0 * j), v1)

        def limits(v: np.ndarray) -> Scaling | None:
            return limiter.scale(joints.q, v, withdrawal=self.withdrawal, toward=self.toward, speed_cap=cap)

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
            capped = self.law.step(frame, h, bound)
            if capped is not None:
                self.joint_limits.guard(capped, h)
                if float(np.max(np.abs(capped[1] - v1))) > 1e-9:
                    scaling = ahead
                q1, v1, a1 = capped
        if check:
            hard = limits(v1)
        dq0 = joints.dq
        if hard is not None:  # the hard cap: the velocity scaled as a whole, the change attributed to this cycle
            scaled = clip(v1 * hard.factor, dq0 - env.a_max * h, dq0 + env.a_max * h)
            q1 = q1 + (scaled - v1) * (0.5 * h)
            a1 = clip(a1 + (scaled - v1) / h, -env.a_max, env.a_max)
            v1 = scaled
            scaling = hard
        eased = self._power(v1, h)
        if eased is not None:  # eased acceleration: off the jerk-limited path, the cycle's mean acceleration
            v1 = dq0 + eased.factor * (v1 - dq0)
            q1 = joints.q + 0.5 * (dq0 + v1) * h
            a1 = (v1 - dq0) / h
            scaling = eased
        self.rejoin_cycles -= 1
        if self.rejoining and self.rejoin_cycles <= 0 and (scaling is None or scaling.what != "rejoin speed") \
                and frame[0] is not None:
            target, speed, _, _ = self.reference.at(t_ns)
            if float(np.max(np.abs(target - q1))) < REJOIN_TOLERANCE_RAD and \
                    float(np.max(np.abs(speed - v1))) < REJOIN_TOLERANCE_RAD_S:
                self.rejoining = False
        if scaling is None:
            return (q1, v1, a1), None
        self.limited += 1
        if reported:
            return (q1, v1, a1), None
        if own is None:
            own = limiter.top_speed(joints.q, v_ref)
        self.catching_up = own <= limiter.limits.speed_m_s * (1.0 - CAP_MARGIN)
        return (q1, v1, a1), f"{self.reference.mode} command from {active!r}: {scaling.describe()}"

    def _power(self, v: np.ndarray, h: float) -> Scaling | None:
        """How much of the cycle's change of velocity (to ``v``) keeps the power within its limit; None: all of it."""
        limiter = self.limiter
        assert limiter is not None
        joints = self.joints
        if not v.any() and not joints.dq.any():
            return None
        return limiter.power_scale(joints.q, joints.dq, v, h)
