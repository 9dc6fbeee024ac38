"""Reflex planner core: the paper's TASK -> REFLEX -> RETURNING state machine.

- TASK: the arm follows the figure-eight (position commands). Any pad with
  a non-zero gain G(p) saves the current pose (the task's own reference at
  that instant, so the return lands exactly on the task path), pauses the
  task and starts a reflex.
- REFLEX: the strategy's motion runs (:mod:`.strategies`), as a jerk-limited
  trajectory to its joint target or as its joint velocity stream. A *new*
  or *stronger* contact updates the reflex from the current motion state,
  within the restarts' rate limits (:mod:`.restarts`); a start from the task
  is never delayed. Its start, updates, motion and retreat check:
  :mod:`.reflex`.
- HOLDING (``sustained_contact = "hold"``, the default): once the reflex's
  motion is over the arm brakes to rest and stays away while the touch
  lasts, then returns (:mod:`.holding`). With ``sustained_contact = "paper"``
  (the paper's behaviour) there is no HOLDING: the return begins as soon as
  the reflex's motion is over.
- RETURNING: a jerk-limited trajectory back to the saved pose, the last
  stretch at the approach speed (:mod:`.returning`). A new or stronger
  contact here starts a new reflex but keeps the saved pose. On arrival the
  task resumes where it paused, easing in.

A planner the bridge does not follow mirrors the active one and takes over
from it when the bridge switches (:mod:`.standby`, :mod:`.claims`).

The core keeps its own commanded state (q, q_dot, q_ddot), integrated at
the nominal control period and within the joint limits, so every command is
consistent with the previous one (:mod:`.motion`). It re-synchronises from
the robot state when the two disagree (after the bridge stopped the arm, say).

The reflex path is event driven: :meth:`Planner.on_pain` returns the first
command of a reflex at once; :meth:`Planner.step` carries the motion on
every control cycle. The retreat check of a reflex runs beside both
(:mod:`.reflex`).

:class:`Planner` is built in layers, one concern each: :class:`.motion.Motion`
(the shared state and the trajectory generator) <- :class:`.returning.Returning`
<- :class:`.holding.Holding` <- :class:`.reflex.ReflexControl` <-
:class:`.standby.Standby` <- :class:`Planner` (the inputs, the control cycle,
the status). A layer calls only its own methods and those of the layers
below it.
"""

from __future__ import annotations

import copy
import logging

import numpy as np

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.standby import Standby

log = logging.getLogger(__name__)

RESYNC_RAD = 0.2  # commanded vs measured pose disagreement that forces a resync


class Planner(Standby):
    """One planner: its inputs (robot states, pain, the peers' statuses), its control cycle and its status."""

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, *,
                 limits: CartesianLimits | None = None) -> None:
        super().__init__(cfg, desc, model, limits=limits)
        self.status_seq = 0
        self.decision_seq = 0
        self.resyncs = 0

    # -- inputs -------------------------------------------------------------
    def on_state(self, q: np.ndarray, following: bool, *, dq: np.ndarray | None = None,
                 owner: str | None = None, now_ns: int = 0, phase: m.Mode = "TASK", ok: bool = True,
                 streaming: bool = False) -> None:
        """Measured joints from the bridge, whether it follows this planner, whom it follows, in which phase;
        ``streaming``: the bridge follows a position stream (it tracks the stream's own setpoints)."""
        self.seen.observe(q, phase, ok, self.name if owner is None else owner, now_ns)
        if owner is not None and owner != self.name:
            self._mirror(q, dq, now_ns)
            return
        if not self.active:
            self.active = True
            if self.initialized:  # this planner was mirroring another one: take over from it
                self._take_over(q, dq, now_ns)
                return
        if not self.initialized:
            self._start_from(q)
            return
        error = float(np.max(np.abs(q - self.q)))
        # The bridge tracks the commands within a cycle or two; a large gap, or
        # a bridge that stopped following (stale input, another owner), means
        # the arm is not where this planner believes: start again from there.
        # Not while the bridge follows this planner's position stream: it
        # continues the stream from the stream's own setpoints (the arm may lag
        # them while its limits slow it), and refuses a jump back to the arm.
        if (error > RESYNC_RAD and not (following and streaming)) or (not following and error > 1e-3):
            self.resyncs += 1
            # A bridge that holds the arm (stale input, a switch, its shutdown)
            # reports why itself: here that is expected, said now and then. A
            # bridge that follows with the arm elsewhere is a fault.
            if following:
                log.warning("the arm is %.3f rad from the commanded pose while the bridge follows: "
                            "resynchronising (%d times so far)", error, self.resyncs)
            elif self.resyncs == 1 or self.resyncs % 250 == 0:
                log.info("the bridge holds the arm %.3f rad from the commanded pose: resynchronising from it "
                         "(%d times so far)", error, self.resyncs)
            self.q = q.copy()
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            if self.mode == "TASK":
                self.saved = self.task.position(self.clock.s)
            if self.mode == "HOLDING" or (self.mode == "RETURNING" and self.partial):
                self._begin_hold(now_ns, keep_since=True)
            elif self.mode != "REFLEX":
                self._begin_return()

    def _felt_pose(self) -> np.ndarray:
        """Where the arm was as the skin felt it, for the places of new touches: the measured pose, which the
        skin feels (the commanded one leads it by the arm's tracking lag: a millimetre or more at the task's
        speed), where the bridge's last state was fine and near the command; else the commanded pose."""
        seen = self.seen.q
        if seen is not None and self.seen.ok and seen.shape == self.q.shape and \
                float(np.max(np.abs(seen - self.q))) <= RESYNC_RAD:
            return seen
        return self.q

    def on_pain(self, pain: m.SkinPain, now_ns: int) -> m.Command | None:
        """A pain message; returns the first command of a reflex if one starts."""
        gains = np.asarray(pain.gain, dtype=float)
        if gains.shape != self.last_gain.shape:
            raise ValueError(f"pain message {pain.seq} has {gains.size} pads, the skin has {self.last_gain.size}")
        previous = self.last_gain
        self.last_gain = np.where(np.isfinite(gains), gains, 0.0)
        new = self.restarts.observe(previous, self.last_gain, now_ns)
        self.trace = pain.trace
        target = self.target_pad
        if 0 <= target < len(pain.level) and pain.level[target] >= 2 and self.last_level[target] < 2:
            self.target_index += 1  # the study's target was touched: the next pad lights up
            self.changed = True
        self.last_level = list(pain.level)
        self.light_touch = [pad for pad in pain.light_touch if 0 <= pad < len(self.last_gain)]
        begun = self.contacts.observe(self._felt_pose(), self.last_level, self.last_gain, now_ns, self.light_touch) \
            if len(pain.level) == len(self.last_gain) else []
        if len(pain.level) == len(self.felt_ns):
            self.felt_ns[self._felt()] = now_ns
        contact = pain.strongest
        if not self.active:
            self._on_pain_inactive(contact, new, pain.trace, now_ns)
            return None
        if not self.initialized:
            return None
        if contact is None or not contact.gain > 0 or not (self._reacts_to(contact, new, now_ns)
                                                           or self._new_elsewhere(contact, new, now_ns)):
            if self.mode == "REFLEX" and self.reflex is not None:
                main = self.reflex.contact.pad
                self.strategy.set_contacts(self.q, self.given_contacts(now_ns, main), main)
            if self.holds and self.mode == "TASK" and self.initialized:
                pressed = self._task_presses(now_ns)
                if pressed:  # the task would push into a touch felt below a reflex's level, or one just gone
                    names = ", ".join(self.desc.pads[i].name for i in pressed)
                    log.info("the task would press into a touch felt on %s (below a reflex's level), or through "
                             "where it just was: pausing it there until the touch is gone and no longer recent",
                             names)
                    self.saved = self.q.copy()
                    self._planned_ahead = 0
                    self._begin_hold(now_ns)
                    self._advanced_early = True
                    return self._hold_step(now_ns)
            if self.holds and self.mode == "RETURNING" and not self.partial:
                ahead = self._felt_ahead(now_ns)
                if ahead:
                    names = ", ".join(self.desc.pads[i].name for i in ahead)
                    log.info("the return would press on a touch felt on %s: stopping it there", names)
                    self._begin_hold(now_ns)
            if self.mode == "RETURNING" and begun and self.initialized:
                self._replan_return()  # slowed near the new touch's place too
            return None
        if self.mode == "TASK":
            self.saved = self.q.copy()
            self.started += 1
        else:
            self.restarted += 1
        self._start_reflex(contact, pain.trace, now_ns)
        # This command is the reflex's first cycle: the control loop skips its
        # next tick rather than advancing the motion twice in one period.
        self._advanced_early = True
        return self._advance_reflex(now_ns)

    def drain_notes(self) -> list[tuple[str, str, str]]:
        notes, self.notes = self.notes + self.restarts.notes + self.strategy.notes, []
        self.strategy.notes = []
        self.restarts.notes = []
        return notes

    def restart(self) -> None:
        """After a failed cycle: forget the motion, start again from the arm's next measured state."""
        self.initialized = False
        self.reflex = None
        self.shadow = None
        self._planned_ahead = 0
        self._advanced_early = False
        self.mode = "RETURNING"
        self.changed = True

    def _start_from(self, q: np.ndarray) -> None:
        """First contact with the arm: return to the task's start, then run it."""
        self.initialized = True
        self.q = q.copy()
        self.saved = self.task.position(self.clock.s)
        self._begin_return()

    def _resume_task(self) -> None:
        assert self.saved is not None
        self.q = self.saved.copy()
        self.dq[:] = 0.0
        self.ddq[:] = 0.0
        self.saved = None
        self.reflex = None
        self.clock.resume()
        self.mode = "TASK"
        self._planned_ahead = 0
        self.changed = True

    # -- the control cycle ----------------------------------------------------
    @property
    def quiet_cycles(self) -> int:
        """The coming cycles whose setpoints the bridge already has (the task's plan).

        Stepping them only advances the task, deterministically and without a
        command: a loop may sleep through them and step them when it wakes, or
        when an event needs this planner's state of the moment.
        """
        if self.mode != "TASK" or not self.active or not self.initialized or self._advanced_early:
            return 0
        return self._planned_ahead

    def step(self, now_ns: int) -> m.Command | None:
        """One control cycle: advance the motion and return its command."""
        if not self.initialized or not self.active:
            return None
        if self._advanced_early:
            self._advanced_early = False
            return None
        if self.mode == "REFLEX":
            command = self._advance_reflex(now_ns)
            if command is not None:
                return command
        if self.mode == "HOLDING":
            hold = self._hold_step(now_ns)
            if hold is not None:
                return hold
        if self.mode == "RETURNING":
            if not self._ruckig_step():
                return self._position_command(now_ns)
            if self._legs:  # on to the next leg, at the speed this leg arrived with (from the next cycle: this
                self._next_leg()  # cycle's setpoint is this leg's end, which the step above reached)
                return self._position_command(now_ns)
            if self.partial:
                self._begin_hold(now_ns, keep_since=True)
                return self._position_command(now_ns)
            self._resume_task()
        rate = self.clock.advance(self.dt)
        q_new = self.task.position(self.clock.s)
        dq_new = rate * self.task.velocity(self.clock.s)
        self.ddq = (dq_new - self.dq) / self.dt
        self.q, self.dq = q_new, dq_new
        if self._planned_ahead > 0:
            self._planned_ahead -= 1  # the bridge has this cycle's setpoint already
            return None
        command = self._position_command(now_ns)
        cycles = self.cfg.task_ahead_cycles
        if cycles > 1:
            # The task is known ahead: this command carries the setpoints of the
            # cycles until the next one, and one more (the overlap absorbs jitter).
            clock = copy.copy(self.clock)
            ahead = []
            for _ in range(cycles):
                clock.advance(self.dt)
                ahead.append(self.task.position(clock.s).tolist())
            command.ahead = ahead
            command.period_s = self.dt
            self._planned_ahead = cycles - 1
        return command

    def decision(self, pain: m.SkinPain, received_ns: int, decided_ns: int,
                 command: m.Command | None) -> m.PlannerDecision:
        """The note of when this planner acted on ``pain`` (``decided_ns``), for the sample latency."""
        msg = m.PlannerDecision(
            seq=self.decision_seq, stamp_ns=decided_ns, name=self.name, trace=pain.trace, pain_seq=pain.seq,
            pain_stamp_ns=pain.stamp_ns, received_ns=received_ns,
            reflex_seq=command.reflex_seq if command is not None else 0, active=self.active,
        )
        self.decision_seq += 1
        return msg

    # -- status ---------------------------------------------------------------
    def status(self, now_ns: int) -> m.PlannerStatus:
        reflex = None
        r = self.reflex if self.active else self.shadow
        if r is not None:
            duration = self.strategy.duration_s if self.strategy.mode == "velocity" or not self.active \
                else self._otg_out.trajectory.duration
            reflex = m.ReflexInfo(
                reflex_seq=r.seq, strategy=self.strategy.name, contact=r.contact, trace=r.trace,
                started_ns=r.started_ns, duration_s=float(duration), direction=r.direction,
                target=r.target.tolist() if r.target is not None else [], retreat=r.retreat,
                shadow=not self.active, withdraws=r.withdraws, reason=r.reason, reach_m=r.reach_m,
            )
        msg = m.PlannerStatus(
            seq=self.status_seq, stamp_ns=now_ns, name=self.name, strategy=self.strategy.name,
            mode=self.mode, task_time_s=self.clock.s,
            saved_pose=self.saved.tolist() if self.saved is not None else None, reflex=reflex,
            target_pad=self.target_pad, active=self.active,
        )
        self.status_seq += 1
        self.changed = False
        return msg
