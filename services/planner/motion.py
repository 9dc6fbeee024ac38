"""What every concern of the reflex planner shares, and its motion primitives.

:class:`Motion` is the base of :class:`~.core.Planner`: the configuration,
the robot, the task and its clock, the study's targets, the mode, the
commanded state (q, q_dot, q_ddot), the saved pose, the current reflex
(:class:`Reflex`), the command counter, and the jerk-limited trajectory generator (ruckig) that the
reflex, the return and the approach all run on. Its primitives start a
trajectory to a target (:meth:`Motion._ruckig_to`), advance it one cycle
(:meth:`Motion._ruckig_step`), cap the joint speeds so that no point of the
arm exceeds a Cartesian speed on the way (:meth:`Motion._joint_speeds_for`),
and turn the commanded state into a position command.

The concerns build on it, each in its own module and each a layer of the
planner's class: :mod:`.returning`, :mod:`.holding`, :mod:`.reflex`,
:mod:`.standby`, then :mod:`.core`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from ruckig import InputParameter, OutputParameter, Result, Ruckig, RuckigError, Synchronization

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.task import FigureEight, TaskClock
from nwr.services.planner import strategies

log = logging.getLogger(__name__)

# The share of a Cartesian speed limit the planner's own motions plan for (the bridge enforces the whole).
CARTESIAN_MARGIN = 0.9
# A joint that need not move still gets this speed limit, rad/s (ruckig needs one > 0).
MIN_JOINT_SPEED = 1e-3


@dataclass
class Reflex:
    """One reflex, as every concern reads it (started and run by :mod:`.reflex`)."""

    seq: int
    contact: m.Contact
    trace: m.Trace
    started_ns: int
    elapsed_s: float = 0.0
    direction: list[float] = field(default_factory=list)
    target: np.ndarray | None = None
    corrected: bool = False
    retreat: m.Retreat | None = None
    withdraws: bool = True  # False: its retreat check found the touched pad cannot move away from the contact
    # Hold mode: the motion ends here (s from its start), where the touched pad is furthest from the contact,
    # when the strategy's motion would bring it back toward the contact afterwards.
    stop_at_s: float | None = None
    # ReflexInfo.reason: why the motion is not the strategy's plain withdrawal; "sideways": the pad withdraws
    # across its normal (its joints cannot move it along it), judged by its distance from the contact point.
    reason: str = ""
    reach_m: float = 0.0  # ReflexInfo.reach_m
    # A retracing strategy's withdrawal: the commanded poses of its stream, from the onset (one a cycle).
    path: list[np.ndarray] = field(default_factory=list)
    # The pads of the other active contacts with a gain at its onset: the retreat check judges each too.
    others: tuple[int, ...] = ()


class Motion:
    """The planner's shared state and the trajectory generator its motions run on."""

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, *,
                 limits: CartesianLimits | None = None) -> None:
        # The bridge's Cartesian limits, which the planner's own trajectories
        # (a joint-space reflex, every return) plan within; None: joint limits only.
        self.limits = limits
        self.cfg = cfg
        self.name = cfg.name
        self.desc = desc
        self.dt = 1.0 / cfg.rate_hz
        n = len(desc.joints)
        self.v_limit = cfg.speed_fraction * desc.v_max
        self.a_limit = cfg.speed_fraction * desc.a_max
        self.task = FigureEight(cfg.task, desc)
        self.clock = TaskClock(cfg.task.ramp_s)
        self.model = model
        self.strategy = strategies.build(cfg, desc, model, self.v_limit)
        self.targets = self._target_order(cfg, desc)
        self.target_index = 0
        self.mode: m.Mode = "TASK"
        self.q = np.zeros(n)
        self.dq = np.zeros(n)
        self.ddq = np.zeros(n)
        self.initialized = False
        self.saved: np.ndarray | None = None
        self.reflex: Reflex | None = None
        self.trace = m.NO_TRACE
        self.seq = 0
        self.changed = True  # a transition not yet published on the status
        # The control cycle's: the reflex's first cycle was commanded from its pain message (skip the next step).
        self._advanced_early = False
        # Task cycles the last command's setpoints ahead still cover; reset
        # wherever the task (re)starts (_resume_task, _take_over).
        self._planned_ahead = 0
        # Diagnostics for the adapter to publish (level, code, message).
        self.notes: list[tuple[str, str, str]] = []
        self._otg = Ruckig(n, self.dt)
        self._otg_in = InputParameter(n)
        self._otg_out = OutputParameter(n)
        self._otg_in.max_velocity = self.v_limit.tolist()
        self._otg_in.max_acceleration = self.a_limit.tolist()
        self._otg_in.max_jerk = (cfg.speed_fraction * desc.j_max).tolist()
        if limits is not None:  # the way stays on the straight line the Cartesian caps are computed for
            self._otg_in.synchronization = Synchronization.Phase

    @staticmethod
    def _target_order(cfg: PlannerSection, desc: RobotDescription) -> list[int]:
        if cfg.target_order:
            return [desc.pad(name).id for name in cfg.target_order]
        return [int(i) for i in np.random.default_rng(cfg.target_seed).permutation(len(desc.pads))]

    @property
    def target_pad(self) -> int:
        return self.targets[self.target_index % len(self.targets)] if self.targets else -1

    def _ruckig_to(self, target: np.ndarray, speed_m_s: float | None = None, *,
                   speeds: np.ndarray | None = None, velocity: np.ndarray | None = None) -> None:
        """Start a jerk-limited trajectory from the current commanded state to ``target`` (at rest, or at
        ``velocity``).

        ``speed_m_s``: no point of the arm (pads, elbow, flange) may move faster
        (:meth:`_joint_speeds_for`), so that the bridge's Cartesian limits hold
        the motion as planned instead of slowing it down behind the plan.
        """
        inp = self._otg_in
        inp.max_velocity = (self._joint_speeds_for(target, speed_m_s) if speeds is None else speeds).tolist()
        inp.current_position = self.q.tolist()
        inp.current_velocity = self.dq.tolist()
        inp.current_acceleration = self.ddq.tolist()
        inp.target_position = target.tolist()
        inp.target_velocity = [0.0] * len(self.q) if velocity is None else velocity.tolist()
        inp.target_acceleration = [0.0] * len(self.q)
        self._otg.reset()

    def _joint_speeds_for(self, target: np.ndarray, speed_m_s: float | None, toward: np.ndarray | None = None,
                          toward_m_s: float = 0.0, start: np.ndarray | None = None, point: int | None = None,
                          point_m_s: float = 0.0) -> np.ndarray:
        """Joint speed limits under which no point moves faster than ``speed_m_s`` on the way to ``target``.

        On a straight line in joint space, at joint velocity ``k * d`` (``d`` the
        displacement), point p moves at ``k * |J_p d|``: joint speeds capped at
        ``margin * speed * |d_i| / max_p |J_p d|`` keep every point within
        ``margin * speed`` (J_p at the start, the middle and the end of the way;
        margin: the pose between them, and a start at speed off the line).
        With ``toward``, the component of every point's velocity along it is
        held to ``toward_m_s`` the same way; with ``point`` (a row of the
        speed Jacobians), that point's speed to ``point_m_s``; ``start``: the
        way's start, if not the commanded pose. The trajectory is
        phase-synchronised, so it follows that line.
        """
        if speed_m_s is None:
            return self.v_limit
        q0 = self.q if start is None else start
        d = target - q0
        rate = 0.0  # the largest speed over limit ratio per unit of k
        for q in (q0, 0.75 * q0 + 0.25 * target, 0.5 * (q0 + target), 0.25 * q0 + 0.75 * target, target):
            v = self.model.speed_jacobians(q) @ d
            rate = max(rate, float(np.linalg.norm(v, axis=1).max()) / speed_m_s)
            if toward is not None:
                rate = max(rate, float((v @ toward).max()) / toward_m_s)
            if point is not None:
                rate = max(rate, float(np.linalg.norm(v[point])) / point_m_s)
        if rate <= 0.0:
            return self.v_limit
        caps = CARTESIAN_MARGIN * np.abs(d) / rate
        return np.minimum(self.v_limit, np.maximum(caps, MIN_JOINT_SPEED))

    def _ruckig_step(self, otg: Ruckig | None = None, inp: InputParameter | None = None,
                     out: OutputParameter | None = None) -> bool:
        """Advance the trajectory (or the brake: ``otg``, ``inp``, ``out``) one cycle; True once it has arrived."""
        otg, inp, out = otg or self._otg, inp or self._otg_in, out or self._otg_out
        try:
            result = otg.update(inp, out)
        except RuckigError as exc:  # an input ruckig cannot work from: stop this motion where it is
            log.error("trajectory generation failed (%s): stopping this motion where it is", exc)
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            return True
        self.q = np.asarray(out.new_position)
        self.dq = np.asarray(out.new_velocity)
        self.ddq = np.asarray(out.new_acceleration)
        out.pass_to_input(inp)
        if result not in (Result.Working, Result.Finished):
            log.error("trajectory generation failed (%s): stopping this motion where it is", result)
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            return True
        return result == Result.Finished

    def _position_command(self, now_ns: int) -> m.PositionCommand:
        msg = m.PositionCommand(
            seq=self.seq, stamp_ns=now_ns, owner=self.name, q=self.q.tolist(), trace=self.trace,
            reflex_seq=self.reflex.seq if self.reflex is not None else 0, phase=self.mode,
        )
        self.seq += 1
        return msg
