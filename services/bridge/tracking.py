"""The bridge's tracker: the commanded joint state, one setpoint per cycle within the envelope, pure.

:class:`Tracker` owns the joint state the bridge commands (``q``, ``dq``,
``ddq``: a :class:`~.law.Joints` its parts share) and composes four parts,
each in its own module:

- :mod:`.reference` (:class:`~.reference.Reference`): the accepted command it
  follows (a position target with the feed-forward velocity of its stream, a
  plan of setpoints ahead, or a joint velocity) and the reference it makes;
- :mod:`.law` (:class:`~.law.Law`): one cycle of the jerk-limited law towards
  that reference (ruckig), and its acceleration-limited stand-in;
- :mod:`.limits` (:class:`~.limits.JointLimits`,
  :class:`~.limits.CartesianCaps`): the stop before the joint limits, and the
  Cartesian and power limits of each cycle, with what they depend on (a
  withdrawal, the direction into the contact, a rejoin);
- :mod:`.stop` (:class:`~.stop.ControlledStop`): the jerk-limited stop to rest,
  whose distance and duration it keeps.

Each control cycle (:meth:`Tracker.track`) moves the commanded state towards
the command within the envelope (speed, acceleration, jerk, the stop before
the joint limits, the Cartesian limits), or along the stop to rest. When to
follow, stop or hold is the supervisor's decision
(:class:`~nwr.services.bridge.core.BridgeCore`); a clip the tracker makes
comes back as an :class:`~nwr.services.bridge.checks.Event` for the supervisor
to count and report, once per command.
"""

from __future__ import annotations

import operator
from typing import Generic, TypeVar

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.cartesian import CartesianLimiter
from nwr.services.bridge.checks import Event
from nwr.services.bridge.envelope import Envelope, clip
from nwr.services.bridge.law import Frame, Joints, Law, State
from nwr.services.bridge.limits import CartesianCaps, JointLimits
from nwr.services.bridge.reference import CommandMode, Reference, Sample
from nwr.services.bridge.stop import ControlledStop, Stop

# The bridge's and the planner's loops are not synchronised: a velocity
# step of up to this many control cycles' worth of acceleration is jitter,
# not a clip worth reporting (the tracker shapes it all the same).
ACCEL_JITTER_CYCLES = 2.0

T = TypeVar("T")


class _Part(Generic[T]):
    """An attribute of the tracker that one of its parts keeps, under the same name: read and written there."""

    def __init__(self, part: str) -> None:
        self.part = part
        self.name = ""
        self.get = operator.attrgetter(part)

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name
        self.get = operator.attrgetter(f"{self.part}.{name}")  # both lookups in one call (read every cycle)

    def __get__(self, obj: object, owner: type | None = None) -> T:
        value: T = self.get(obj)
        return value

    def __set__(self, obj: object, value: T) -> None:
        setattr(getattr(obj, self.part), self.name, value)


class Tracker:
    """The commanded joint state and the command it follows within the envelope."""

    # The commanded joint state (what the backend was last sent).
    q: _Part[np.ndarray] = _Part("joints")
    dq: _Part[np.ndarray] = _Part("joints")
    ddq: _Part[np.ndarray] = _Part("joints")
    # The command followed (the reference's).
    mode: _Part[CommandMode] = _Part("ref")
    target: _Part[np.ndarray] = _Part("ref")
    v_ff: _Part[np.ndarray] = _Part("ref")
    plan: _Part[np.ndarray | None] = _Part("ref")
    plan_v: _Part[np.ndarray] = _Part("ref")
    covered_ns: _Part[int] = _Part("ref")
    # The Cartesian limits and what they depend on (the caps').
    limiter: _Part[CartesianLimiter | None] = _Part("caps")
    reflex: _Part[bool] = _Part("caps")
    withdrawal: _Part[bool] = _Part("caps")
    toward: _Part[np.ndarray | None] = _Part("caps")
    rejoining: _Part[bool] = _Part("caps")
    catching_up: _Part[bool] = _Part("caps")
    stream_peak: _Part[float] = _Part("caps")
    limited: _Part[int] = _Part("caps")
    # The controlled stop, and the distance and duration of the last one (the stop's).
    stop: _Part[Stop | None] = _Part("stopping")
    stop_distance: _Part[np.ndarray] = _Part("stopping")
    stop_time_s: _Part[float] = _Part("stopping")

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, period_s: float = 0.002,
                 limiter: CartesianLimiter | None = None) -> None:
        self.env = env
        self.period_s = period_s  # the control period, s
        n = env.n
        self.joints = Joints(q0.copy(), np.zeros(n), np.zeros(n))
        self.ref = Reference(env, q0, now_ns, period_s)
        self.law = Law(env, self.joints)
        self.joint_limits = JointLimits(env, self.joints)
        self.caps = CartesianCaps(env, limiter, self.joints, self.law, self.joint_limits, self.ref)
        self.stopping = ControlledStop(env, self.joints)
        self._clip_reported = False  # the tracker's clip of the current command was reported

    # -- the command followed ------------------------------------------------------------
    def follow_position(self, cmd: m.PositionCommand, q: np.ndarray, now_ns: int, ahead: np.ndarray | None,
                        last_seq: int | None, last_stamp_ns: int) -> Event | None:
        """Follow an accepted position target ``q`` (and its setpoints ``ahead``); a clip to report, if any
        (:meth:`.Reference.follow_position`)."""
        self._clip_reported = False
        return self.ref.follow_position(cmd, q, now_ns, ahead, last_seq, last_stamp_ns)

    def follow_velocity(self, dq: np.ndarray, cmd: m.Command | None = None, now_ns: int = 0,
                        last_seq: int | None = None, last_stamp_ns: int = 0) -> None:
        """Follow an accepted joint velocity ``dq`` (of ``cmd``, after the command ``last_seq``, if given)."""
        self._clip_reported = False
        self.ref.follow_velocity(dq, cmd, now_ns, last_seq, last_stamp_ns)

    def planned(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The plan's target and feed-forward velocity at ``t_ns``: interpolated, or extrapolated past its end."""
        return self.ref.planned(t_ns)

    def reference(self, t_ns: int) -> Sample:
        """The position reference at ``t_ns``: its position, velocity, acceleration and jerk."""
        return self.ref.at(t_ns)

    def begin_rejoin(self, cap: float | None = None, cycles: int = 0) -> None:
        """Rejoin the stream (when it is a position stream) at no more than its own peak speed, or ``cap`` (m/s)
        (:meth:`.CartesianCaps.begin_rejoin`)."""
        self.caps.begin_rejoin(cap, cycles)

    def observe(self, q: np.ndarray) -> None:
        """The measured pose; in velocity mode (not stopping) the integrated command follows it."""
        if self.ref.mode == "velocity" and self.stopping.stop is None:
            self.joints.q = np.asarray(q, dtype=float).copy()

    def restart(self, q: np.ndarray) -> None:
        """Start over at rest from the measured pose ``q``, following nothing (after a fault)."""
        joints = self.joints
        joints.q = np.asarray(q, dtype=float).copy()
        joints.dq[:] = 0.0
        joints.ddq[:] = 0.0
        self.stopping.stop = None
        self.ref.mode = "none"

    # -- one control cycle -------------------------------------------------------------
    def hold(self) -> None:
        """Stay where the arm is commanded, at rest."""
        self.joints.dq[:] = 0.0
        self.joints.ddq[:] = 0.0

    def track(self, h: float, t_ns: int, active: str) -> Event | None:
        """One cycle of ``h`` s ending at ``t_ns`` towards the command of ``active``; a clip to report, if any.

        The law (:mod:`.law`) towards the reference over the cycle (:mod:`.reference`), then the joint and
        the Cartesian limits (:mod:`.limits`)."""
        env, ref, joints = self.env, self.ref, self.joints
        start_ns = t_ns - round(h * 1e9)
        clipped = None
        zero = np.zeros(env.n)
        if ref.mode == "position":
            # The reference over the cycle: the cubic that ends where the reference is at its end (a plan
            # that has just arrived starts there).
            r1, v1, a1, jerk = ref.at(t_ns)
            a0 = a1 - jerk * h
            v0 = v1 - a0 * h - jerk * (0.5 * h * h)
            frame: Frame = (r1 - v0 * h - a0 * (0.5 * h * h) - jerk * (h * h * h / 6.0), v0, a0, jerk)
        elif ref.mode == "velocity":
            v_ref, a_ref = ref.velocity_at(start_ns)
            frame = (None, v_ref, a_ref, zero)
            jump = np.abs(ref.target - joints.dq) / (env.a_max * max(h, self.period_s))
            if float(np.max(jump)) > ACCEL_JITTER_CYCLES and not self._clip_reported:
                i = int(np.argmax(jump))
                clipped = self._clip(
                    "command_clipped",
                    f"velocity command from {active!r}: joint {env.joints[i]} asks for {ref.target[i]:.3f} rad/s "
                    f"from {joints.dq[i]:.3f} rad/s, a_max {env.a_max[i]:.2f} rad/s^2: ramped at the limit",
                )
        else:
            frame = (None, zero, zero, zero)
        state = self.law.step(frame, h, None)
        if state is None:  # ruckig failed (it does not with valid limits): the acceleration-limited law
            if frame[0] is not None:
                return self._limit(frame[1].tolist(), h, ref.at(t_ns)[0].tolist(), active) or clipped
            return self._limit(frame[1].tolist(), h, None, active) or clipped
        bounded = self.joint_limits.guard(state, h)
        limited = None
        if self.caps.limiter is not None:
            state, limited = self._caps(state, frame, h, t_ns, active)
            # The caps only slow the joints, but the stop check is the last word.
            again = self.joint_limits.guard(state, h)
            bounded = bounded if bounded >= 0 else again
        q1, v1, a1 = state
        joints.q, joints.dq, joints.ddq = clip(q1, env.q_min, env.q_max), clip(v1, -env.v_max, env.v_max), a1
        if limited is None and bounded >= 0 and not self._clip_reported:
            i = bounded
            limited = self._clip(
                "joint_limit",
                f"{ref.mode} command from {active!r}: joint {env.joints[i]} at {joints.q[i]:.4f} rad approaches "
                f"its limit [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}]: braking (the jerk-limited stop ends within it)",
            )
        return clipped or limited

    def _caps(self, state: State, frame: Frame, h: float, t_ns: int, active: str, *,
              rerun: bool = True) -> tuple[State, Event | None]:
        """The cycle's state within the Cartesian and power limits (:meth:`.CartesianCaps.apply`); a clip, if any."""
        state, scaled = self.caps.apply(state, frame, h, t_ns, active, self._clip_reported, rerun=rerun)
        return state, None if scaled is None else self._clip("cartesian_limit", scaled)

    def _limit(self, v_des: list[float], h: float, target: list[float] | None, active: str) -> Event | None:
        """One cycle of the acceleration-limited law (:meth:`.Law.accelerate`), ruckig's stand-in, then the
        Cartesian limits' hard caps; a clip, if any."""
        state, v_ff, bound = self.law.accelerate(v_des, h, target)
        clipped = None
        if self.caps.limiter is not None:
            # The hard caps (the law cannot be run again under them: it is what failed).
            zero = np.zeros(self.env.n)
            state, clipped = self._caps(state, (None, v_ff, zero, zero), h, 0, active, rerun=False)
            state = clip(state[0], self.env.q_min, self.env.q_max), state[1], state[2]
        if clipped is None and bound is not None and not self._clip_reported:
            env, (i, q_i, bound_v) = self.env, bound
            clipped = self._clip(
                "joint_limit",
                f"{self.ref.mode} command from {active!r}: joint {env.joints[i]} at {q_i:.4f} rad approaches "
                f"its limit [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}] at {v_des[i]:.3f} rad/s: speed bounded to "
                f"{bound_v:.3f} rad/s (the braking distance)",
            )
        self.joints.q, self.joints.dq, self.joints.ddq = state
        return clipped

    def _clip(self, code: str, message: str) -> Event:
        """A clip of the tracker, reported once per command (not per cycle)."""
        self._clip_reported = True
        return Event("warning", code, message)

    # -- the controlled stop -------------------------------------------------------------
    def begin_stop(self, now_ns: int) -> Event | None:
        """Plan a jerk-limited stop to rest from the commanded state; an error to report if ruckig failed
        (:meth:`.ControlledStop.begin`)."""
        return self.stopping.begin(now_ns, self.caps.limiter, self.caps.withdrawal)

    def stop_step(self, now_ns: int, h: float) -> None:
        """One cycle of ``h`` s of the stop at ``now_ns``; at rest once it is done."""
        self.stopping.step(now_ns, h)

    def release(self) -> None:
        """Drop the trajectory generators at shutdown (their objects must not outlive their module)."""
        self.law.release()
        self.stopping.release()
