"""The tracker's control law: one cycle of the commanded joint state towards the reference, jerk-limited.

:class:`Law` owns the trajectory generator (ruckig) and its inputs; it reads
the commanded joint state (:class:`Joints`, the tracker's) and returns the
next one, leaving the limits (:mod:`.limits`) and the bookkeeping to the
tracker (:mod:`.tracking`).

The commanded state relative to the reference (moving over the cycle as the
reference does) is brought to rest along ruckig's time-optimal jerk-limited
trajectory, each joint on its own (a velocity step's joints in proportion),
sampled one cycle in; the relative limits are what ``v_max``, ``a_max`` and
``j_max`` leave once the reference's own motion is counted, so the absolute
jerk of every cycle is within ``j_max``. A step is reached without overshoot;
a smooth stream is followed to rounding. The reference's jerk is counted only
where the joint is on it (:data:`ON_REFERENCE_RAD` ...): farther off, the law
needs the whole jerk limit to get there. Where ruckig fails (it does not with
valid limits), :meth:`Law.accelerate` is its acceleration-limited stand-in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, RuckigError, Synchronization, Trajectory

from nwr.services.bridge.envelope import Envelope, clip

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

State = tuple[np.ndarray, np.ndarray, np.ndarray]  # q, dq, ddq
# The reference over a control cycle, from its start: position (None: a velocity command), velocity,
# acceleration, and jerk over the cycle.
Frame = tuple[np.ndarray | None, np.ndarray, np.ndarray, np.ndarray]


@dataclass
class Joints:
    """The commanded joint state (what the backend was last sent): the tracker's, read by its parts."""

    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray


def ruckig_input(env: Envelope, interface: ControlInterface) -> InputParameter:
    """A ruckig input within the envelope's limits, to rest (zero target velocity and acceleration)."""
    n = env.n
    inp = InputParameter(n)
    inp.control_interface = interface
    inp.max_velocity = env.v_max.tolist()
    inp.max_acceleration = env.a_max.tolist()
    inp.max_jerk = env.j_max.tolist()
    inp.target_velocity = [0.0] * n
    inp.target_acceleration = [0.0] * n
    return inp


class Law:
    """One cycle of the jerk-limited law from the commanded joint state (module docstring)."""

    def __init__(self, env: Envelope, joints: Joints) -> None:
        self.env = env
        self.joints = joints
        n = env.n
        self.j = env.j_max.tolist()
        self.zero = np.zeros(n)
        self.v_lim = env.v_max * FEASIBLE
        self.a_lim = env.a_max * FEASIBLE
        self.j_lim = env.j_max * (1.0 - JERK_FLOOR)
        self.otg = Ruckig(n)
        self.trajectory = Trajectory(n)
        # Following a position: each joint time-optimal on its own (the reference keeps them together).
        self.position_in = ruckig_input(env, ControlInterface.Position)
        self.position_in.synchronization = Synchronization.No
        self.position_in.target_position = [0.0] * n
        # Following a velocity: the joints' velocity changes in proportion, so a Cartesian
        # withdrawal keeps its direction while it ramps.
        self.velocity_in = ruckig_input(env, ControlInterface.Velocity)
        self.velocity_in.synchronization = Synchronization.Phase
        self.velocity_in.current_position = [0.0] * n
        # A velocity step whose state is along one direction (a Cartesian withdrawal's ramp): one scalar along
        # it (:meth:`_along`), so that the joints stay in proportion by construction, not by ruckig's check of
        # collinearity (ten machine epsilons: a rounding the machine's vector arithmetic decides breaks it).
        self.line_otg = Ruckig(1)
        self.line_trajectory = Trajectory(1)
        self.line_in = InputParameter(1)
        self.line_in.control_interface = ControlInterface.Velocity
        self.line_in.current_position = [0.0]
        self.line_in.target_velocity = [0.0]
        self.line_in.target_acceleration = [0.0]

    def step(self, frame: Frame, h: float, cap: np.ndarray | None) -> State | None:
        """One cycle of the jerk-limited law in ``frame``; None if ruckig failed.

        ``frame``: the reference at the start of the cycle (its position, or
        None for a velocity command; its velocity, acceleration, and jerk over
        the cycle). The commanded state relative to it is brought to rest
        time-optimally, within what the envelope leaves once the frame's own
        motion is counted (the jerk: ``j_max`` less the frame's). ``cap``:
        joint speeds not to exceed (the Cartesian limits anticipated).
        """
        env, joints = self.env, self.joints
        r0, v_ref, a_ref, jerk = frame
        v_max, v_lim = env.v_max, self.v_lim
        if cap is not None:  # a reference beyond the speeds allowed is slowed as a whole: its direction kept
            v_max = np.minimum(v_max, np.maximum(cap, 1e-6))
            v_lim = v_max * FEASIBLE
            slow = min(1.0, float(np.min(v_lim / np.maximum(np.abs(v_ref), 1e-12))))
            v_ref, a_ref, jerk = v_ref * slow, a_ref * slow, jerk * slow
        a_lim = self.a_lim
        a_ref = clip(a_ref, -a_lim, a_lim)
        jerky = r0 is not None and bool(jerk.any())
        if jerky:
            # The frame jerks as the reference does only where the arm is on it: the law then has what the
            # reference leaves of the jerk limit (ruckig's are symmetric), enough to stay on it; farther off,
            # a frame of constant acceleration leaves it the whole limit to get there.
            on = (np.abs(joints.q - r0) <= ON_REFERENCE_RAD) & (np.abs(joints.dq - v_ref) <= ON_REFERENCE_RAD_S) \
                & (np.abs(joints.ddq - a_ref) <= ON_REFERENCE_RAD_S2)
            jerk = clip(clip(np.where(on, jerk, 0.0), -self.j_lim, self.j_lim), (-a_lim - a_ref) / h,
                        (a_lim - a_ref) / h)  # within the floor's share, and feasible on
            a_end = a_ref + jerk * h
        else:
            jerk = self.zero
            a_end = a_ref
        trajectory = self.trajectory
        du = joints.ddq - a_ref
        if r0 is not None:
            v_ref = clip(v_ref, -v_lim, v_lim)
            u = joints.dq - v_ref
            inp = self.position_in
            inp.current_position = (joints.q - r0).tolist()
            inp.max_velocity = (v_max - v_ref).tolist()
            inp.min_velocity = (-v_max - v_ref).tolist()
            inp.max_jerk = (env.j_max - np.abs(jerk)).tolist() if jerky else self.j
        else:
            u = joints.dq - v_ref
            line = self._along(u, du, a_end, h)
            if line is not None:
                x, dx, ddx = line
                return joints.q + v_ref * h + a_ref * (0.5 * h * h) + x, v_ref + a_ref * h + dx, a_ref + ddx
            inp = self.velocity_in
        inp.current_velocity = u.tolist()
        inp.current_acceleration = du.tolist()
        inp.max_acceleration = (env.a_max - a_end).tolist()
        inp.min_acceleration = (-env.a_max - a_end).tolist()
        try:
            result = self.otg.calculate(inp, trajectory)
        except (RuckigError, RuntimeError, ValueError):  # an input it rejects, or an error code it does not name
            result = Result.Error
        if result not in (Result.Working, Result.Finished):
            if r0 is None:
                return None
            # A position it cannot reach within the speeds allowed (a cap close to the reference's
            # own speed): this cycle, the velocity law at the reference's speed.
            return self.step((None, v_ref, a_ref, self.zero), h, cap)
        x, dx, ddx = trajectory.at_time(h)
        if jerky:
            assert r0 is not None
            q1 = r0 + v_ref * h + a_ref * (0.5 * h * h) + jerk * (h * h * h / 6.0) + np.asarray(x)
            return q1, v_ref + a_ref * h + jerk * (0.5 * h * h) + np.asarray(dx), a_end + np.asarray(ddx)
        q1 = (r0 if r0 is not None else joints.q) + v_ref * h + a_ref * (0.5 * h * h) + np.asarray(x)
        return q1, v_ref + a_ref * h + np.asarray(dx), a_ref + np.asarray(ddx)

    def _along(self, u: np.ndarray, du: np.ndarray, a_end: np.ndarray, h: float) -> State | None:
        """A velocity step from a state along one direction (``du`` a multiple of ``u``, to COLLINEAR): the
        cycle's offsets (position, velocity, acceleration) of one jerk-limited scalar ``s`` from 1 to rest,
        times ``u``, every joint within its limits (``s``'s are the tightest joint's); None when the state is
        not along one direction or ruckig fails (the joints' own law then)."""
        uu = float(u @ u)
        if uu <= 0.0:
            return None
        ratio = float(du @ u) / uu
        if float(np.abs(du - ratio * u).max()) > COLLINEAR * float(np.abs(du).max()) + 1e-12:
            return None
        env = self.env
        moving = u != 0.0
        d = u[moving]
        hi, lo = env.a_max[moving] - a_end[moving], -env.a_max[moving] - a_end[moving]
        a_hi = float(np.min(np.where(d > 0.0, hi / d, lo / d)))
        a_lo = float(np.max(np.where(d > 0.0, lo / d, hi / d)))
        inp = self.line_in
        inp.current_velocity = [1.0]
        inp.current_acceleration = [min(max(ratio, a_lo), a_hi)]  # a state at its limit, rounded past it: at it
        inp.max_acceleration = [a_hi]
        inp.min_acceleration = [a_lo]
        inp.max_jerk = [float(np.min(env.j_max[moving] / np.abs(d)))]
        try:
            result = self.line_otg.calculate(inp, self.line_trajectory)
        except (RuckigError, RuntimeError, ValueError):
            return None
        if result not in (Result.Working, Result.Finished):
            return None
        x, dx, ddx = self.line_trajectory.at_time(h)
        return x[0] * u, dx[0] * u, ddx[0] * u

    def accelerate(self, v_des: list[float], h: float,
                   target: list[float] | None) -> tuple[State, np.ndarray, tuple[int, float, float] | None]:
        """One cycle of the acceleration-limited law (per joint, in floats): ruckig's stand-in.

        With a position ``target``, ``v_des`` is its feed-forward velocity, plus
        a correction that can brake in time at ``a_max``; then the speed limit,
        the braking distance to the joint limits (:meth:`Envelope.braking_speed`,
        the same formula), the acceleration limit. It does not limit the jerk.
        ``v_des`` is left as each joint asked (corrected, within ``v_max``).
        Returns the next state, ``v_des`` as given (an array), and the joint the
        braking distance bounds most, if any: its index, position and bounded speed.
        """
        q0, dq0 = self.joints.q.tolist(), self.joints.dq.tolist()
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
        bound = (bound_i, q0[bound_i], bound_v) if bound_i >= 0 else None
        return (np.array(q1), np.array(v1), np.array(a1)), v_ff, bound

    def release(self) -> None:
        """Drop the trajectory generator at shutdown (its objects must not outlive their module)."""
        self.otg = self.position_in = self.velocity_in = self.trajectory = None
        self.line_otg = self.line_in = self.line_trajectory = None
