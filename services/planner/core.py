"""Reflex planner core: the paper's TASK -> REFLEX -> RETURNING state machine.

- TASK: the arm follows the figure-eight (position commands). Any pad with
  a non-zero gain G(p) saves the current pose (the task's own reference at
  that instant, so the return lands exactly on the task path), pauses the
  task and starts a reflex.
- REFLEX: the strategy's motion runs for its duration. A *new* contact (a pad
  that had no gain in the previous pain message) or a *stronger* one (gain
  above the current reflex's by ``update_margin``) updates the reflex: new
  direction, duration restarted, new reflex number.
- RETURNING: a jerk-limited trajectory (ruckig) from wherever the reflex
  left the arm, velocity included, back to the saved pose. A new or stronger
  contact here starts a new reflex but keeps the saved pose: the arm always
  goes back to where the task paused. On arrival the task resumes where it
  paused, easing in.

The core keeps its own commanded state (q, q_dot, q_ddot), integrated at
the nominal control period and within the joint limits, so every command is
consistent with the previous one. It re-synchronises from the robot state
when the two disagree (after the bridge stopped the arm, say).

The reflex path is event driven: :meth:`on_pain` returns the first command
of a reflex at once; :meth:`step` carries the motion on every control cycle.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from ruckig import InputParameter, OutputParameter, Result, Ruckig

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.reflexes import CartesianReflex
from nwr.services.planner.task import FigureEight, TaskClock

log = logging.getLogger(__name__)

RESYNC_RAD = 0.2  # commanded vs measured pose disagreement that forces a resync


@dataclass
class Reflex:
    seq: int
    contact: m.Contact
    trace: m.Trace
    started_ns: int
    elapsed_s: float = 0.0
    direction: list[float] = field(default_factory=list)


class Planner:
    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.desc = desc
        self.dt = 1.0 / cfg.rate_hz
        n = len(desc.joints)
        self.v_limit = cfg.speed_fraction * desc.v_max
        self.a_limit = cfg.speed_fraction * desc.a_max
        self.task = FigureEight(cfg.task, desc.home)
        self.clock = TaskClock(cfg.task.ramp_s)
        self.strategy = CartesianReflex(
            model, cfg.v_max_m_s, cfg.reflex_duration_s, cfg.damping_max, cfg.singular_threshold, self.v_limit,
            hold_orientation=cfg.hold_orientation,
        )
        self.mode: m.Mode = "TASK"
        self.q = np.zeros(n)
        self.dq = np.zeros(n)
        self.ddq = np.zeros(n)
        self.initialized = False
        self.saved: np.ndarray | None = None
        self.reflex: Reflex | None = None
        self.reflex_count = 0
        self.last_gain = np.zeros(len(desc.pads))
        self.trace = m.Trace(-1, 0)
        self.seq = 0
        self.status_seq = 0
        self.changed = True  # a transition not yet published on the status
        self.resyncs = 0
        self._otg = Ruckig(n, self.dt)
        self._otg_in = InputParameter(n)
        self._otg_out = OutputParameter(n)
        self._otg_in.max_velocity = self.v_limit.tolist()
        self._otg_in.max_acceleration = self.a_limit.tolist()
        self._otg_in.max_jerk = (cfg.speed_fraction * desc.j_max).tolist()

    # -- inputs -------------------------------------------------------------
    def on_state(self, q: np.ndarray, following: bool) -> None:
        """Measured joint positions from the bridge, and whether it follows this planner."""
        if not self.initialized:
            self._start_from(q)
            return
        error = float(np.max(np.abs(q - self.q)))
        # The bridge tracks the commands within a cycle or two; a large gap, or
        # a bridge that stopped following (stale input, another owner), means
        # the arm is not where this planner believes: start again from there.
        if error > RESYNC_RAD or (not following and error > 1e-3):
            self.resyncs += 1
            log.warning("the arm is %.3f rad from the commanded pose: resynchronising", error)
            self.q = q.copy()
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            if self.mode == "TASK":
                self.saved = self.task.position(self.clock.s)
            if self.mode != "REFLEX":
                self._begin_return()

    def _start_from(self, q: np.ndarray) -> None:
        """First contact with the arm: return to the task's start, then run it."""
        self.initialized = True
        self.q = q.copy()
        self.saved = self.task.position(self.clock.s)
        self._begin_return()

    def on_pain(self, pain: m.SkinPain, now_ns: int) -> m.Command | None:
        """A pain message; returns the first command of a reflex if one starts."""
        gains = np.asarray(pain.gain, dtype=float)
        if gains.shape != self.last_gain.shape:
            raise ValueError(f"pain message {pain.seq} has {gains.size} pads, the skin has {self.last_gain.size}")
        previous = self.last_gain
        self.last_gain = np.where(np.isfinite(gains), gains, 0.0)
        self.trace = pain.trace
        contact = pain.strongest
        if not self.initialized or contact is None or not contact.gain > 0:
            return None
        if self.mode == "TASK":
            self.saved = self.q.copy()
        else:
            current = self.reflex.contact.gain if self.reflex is not None else 0.0
            new_pad = previous[contact.pad] <= 0.0
            stronger = contact.gain > current + self.cfg.update_margin
            if not (new_pad or stronger):
                return None
        self._start_reflex(contact, pain.trace, now_ns)
        return self._reflex_command(now_ns, advance=False)

    # -- transitions --------------------------------------------------------
    def _start_reflex(self, contact: m.Contact, trace: m.Trace, now_ns: int) -> None:
        self.reflex_count += 1
        v_c = self.strategy.start(self.q, contact.pad, contact.gain)
        self.reflex = Reflex(self.reflex_count, contact, trace, now_ns, direction=v_c.tolist())
        self.mode = "REFLEX"
        self.changed = True

    def _begin_return(self) -> None:
        assert self.saved is not None
        inp = self._otg_in
        inp.current_position = self.q.tolist()
        inp.current_velocity = self.dq.tolist()
        inp.current_acceleration = self.ddq.tolist()
        inp.target_position = self.saved.tolist()
        inp.target_velocity = [0.0] * len(self.q)
        inp.target_acceleration = [0.0] * len(self.q)
        self._otg.reset()
        self.mode = "RETURNING"
        self.changed = True

    def _resume_task(self) -> None:
        assert self.saved is not None
        self.q = self.saved.copy()
        self.dq[:] = 0.0
        self.ddq[:] = 0.0
        self.saved = None
        self.reflex = None
        self.clock.resume()
        self.mode = "TASK"
        self.changed = True

    # -- the control cycle ----------------------------------------------------
    def step(self, now_ns: int) -> m.Command | None:
        """One control cycle: advance the motion and return its command."""
        if not self.initialized:
            return None
        if self.mode == "REFLEX":
            assert self.reflex is not None
            self.reflex.elapsed_s += self.dt
            if self.reflex.elapsed_s >= self.strategy.duration_s:
                self._begin_return()
            else:
                return self._reflex_command(now_ns, advance=True)
        if self.mode == "RETURNING":
            result = self._otg.update(self._otg_in, self._otg_out)
            out = self._otg_out
            self.q = np.asarray(out.new_position)
            self.dq = np.asarray(out.new_velocity)
            self.ddq = np.asarray(out.new_acceleration)
            out.pass_to_input(self._otg_in)
            if result == Result.Finished:
                self._resume_task()
            elif result != Result.Working:
                log.error("return trajectory failed (%s): holding the saved pose", result)
                self._resume_task()
            else:
                return self._position_command(now_ns)
        rate = self.clock.advance(self.dt)
        q_new = self.task.position(self.clock.s)
        dq_new = rate * self.task.velocity(self.clock.s)
        self.ddq = (dq_new - self.dq) / self.dt
        self.q, self.dq = q_new, dq_new
        return self._position_command(now_ns)

    def _reflex_command(self, now_ns: int, *, advance: bool) -> m.VelocityCommand:
        """Velocity command of the reflex, acceleration-limited from the current velocity."""
        target = self.strategy.joint_velocity(self.q)
        delta = target - self.dq
        ratio = float(np.max(np.abs(delta) / (self.a_limit * self.dt)))
        dq = self.dq + (delta / ratio if ratio > 1.0 else delta)
        if advance:
            q = self.q + dq * self.dt
            # Never command past a joint limit: stop that joint at the limit.
            low, high = q < self.desc.q_min, q > self.desc.q_max
            if low.any() or high.any():
                q = np.clip(q, self.desc.q_min, self.desc.q_max)
                dq[low | high] = 0.0
            self.ddq = (dq - self.dq) / self.dt
            self.q, self.dq = q, dq
        assert self.reflex is not None
        msg = m.VelocityCommand(
            seq=self.seq, stamp_ns=now_ns, owner=self.name, dq=dq.tolist(), trace=self.trace,
            reflex_seq=self.reflex.seq, phase="REFLEX",
        )
        self.seq += 1
        return msg

    def _position_command(self, now_ns: int) -> m.PositionCommand:
        msg = m.PositionCommand(
            seq=self.seq, stamp_ns=now_ns, owner=self.name, q=self.q.tolist(), trace=self.trace,
            reflex_seq=self.reflex.seq if self.reflex is not None else 0, phase=self.mode,
        )
        self.seq += 1
        return msg

    # -- status ---------------------------------------------------------------
    def status(self, now_ns: int) -> m.PlannerStatus:
        reflex = None
        if self.reflex is not None:
            r = self.reflex
            reflex = m.ReflexInfo(
                reflex_seq=r.seq, strategy=self.strategy.strategy, contact=r.contact, trace=r.trace,
                started_ns=r.started_ns, duration_s=self.strategy.duration_s, direction=r.direction,
            )
        msg = m.PlannerStatus(
            seq=self.status_seq, stamp_ns=now_ns, name=self.name, strategy=self.strategy.strategy,
            mode=self.mode, task_time_s=self.clock.s,
            saved_pose=self.saved.tolist() if self.saved is not None else None, reflex=reflex,
        )
        self.status_seq += 1
        self.changed = False
        return msg
