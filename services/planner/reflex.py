"""REFLEX: a reflex's start, its updates, its motion, and the check that it withdraws the touched pad.

Not to be confused with :mod:`.reflexes` (the strategies' shared pieces):
this module runs whichever strategy (:mod:`.strategies`) the planner has.

The strategy's motion runs: in position mode a jerk-limited trajectory
(ruckig) to its joint target, ending when the target is reached; in
velocity mode its joint velocity stream, for the strategy's ``duration_s``
(``reflex_duration_s`` unless it has its own). A *new* contact (a pad whose
touch begins: no gain for ``restarts.gap_s``) or a *stronger* one (gain
above the current reflex's by ``update_margin``) updates the reflex: new
target or direction from the current motion state (the trajectory blends,
nothing jumps), duration restarted, new number. The strategy is given every
recent contact first (``planner.contacts = "every"``; the paper's strongest
only with ``"strongest"``), and the retreat check judges the pad of every
other active contact as well as the reflex's own. Restarts are rate-limited
per pad and overall (:mod:`.restarts`: no reflex storm from a flickering
pad or a forged stream); a start from the task is never delayed. Once the
motion is over the arm holds or returns (:mod:`.holding`).

The retreat check of a reflex (a few ms of kinematics, :mod:`.retreat`) is
split so that it can run beside the event path (:meth:`.core.Planner.on_pain`)
and the control cycle: :meth:`ReflexControl.retreat_check` takes what it
needs (under the adapter's lock), :meth:`RetreatCheck.run` computes it on a
model of its own, :meth:`ReflexControl.apply_retreat` stores it if the
reflex is still the current one. :meth:`ReflexControl.assess` does all
three at once. A reflex whose check finds it cannot move the touched pad
away from the contact (under 2 mm of withdrawal at G = 1) is reported
(``ReflexInfo.withdraws``) and, in hold mode, stops and holds at once.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from ruckig import InputParameter, Ruckig, Trajectory

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.skin import contact_normal
from nwr.services.planner import restarts, retreat
from nwr.services.planner.contacts import ContactPoint
from nwr.services.planner.holding import Holding
from nwr.services.planner.motion import Reflex
from nwr.services.planner.strategies import ReflexStrategy, others

log = logging.getLogger(__name__)

# A reflex whose planned motion withdraws the touched pad less than this times its gain (at least
# MIN_GAIN_SCALE) cannot withdraw it, m: at G = 1 the strategies withdraw a pad they can move by centimetres.
WITHDRAW_MIN_M = 0.002
MIN_GAIN_SCALE = 0.1


@dataclass
class RetreatCheck:
    """The retreat check of one reflex, taken from the planner; :meth:`run` needs nothing else.

    A position-mode reflex's path is sampled from its trajectory when the
    check is taken (cheap); a velocity stream is integrated in :meth:`run`
    (the expensive part) from a snapshot of the strategy's state.
    """

    reflex: Reflex
    path: np.ndarray | None  # position mode: the planned positions
    dt: float
    stream: ReflexStrategy | None  # velocity mode: a snapshot of the strategy
    q0: np.ndarray
    t0: float
    duration_s: float
    q_min: np.ndarray
    q_max: np.ndarray

    def run(self, model: RobotModel) -> retreat.Assessment:
        """The retreat figures, computed on ``model`` (one that no other thread is using)."""
        path, dt = self.path, self.dt
        if path is None:
            assert self.stream is not None
            self.stream.model = model
            path, dt = integrate_stream(self.stream, self.q0, self.t0, self.duration_s, self.q_min, self.q_max)
        return retreat.assess(model, path, dt, self.reflex.contact.pad, self.reflex.others)


def integrate_stream(stream: ReflexStrategy, q0: np.ndarray, t0: float, duration_s: float, q_min: np.ndarray,
                     q_max: np.ndarray, samples: int = 40) -> tuple[np.ndarray, float]:
    """A velocity stream from ``t0`` to its end, integrated from ``q0``."""
    dt = duration_s / samples
    q = q0.copy()
    path = [q.copy()]
    t = t0
    for _ in range(samples):
        q = np.clip(q + stream.velocity(q, t, count=False) * dt, q_min, q_max)
        path.append(q.copy())
        t += dt
    return np.array(path), dt


class ReflexControl(Holding):
    """The reflex: when a contact (re)starts one, its onset, its motion cycle by cycle, its retreat check."""

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, *,
                 limits: CartesianLimits | None = None) -> None:
        super().__init__(cfg, desc, model, limits=limits)
        self.reflex_count = 0  # reflex numbers given: started, restarted and shadow ones
        self.started = 0  # reflexes started from the task
        self.restarted = 0  # a reflex started again by a new or stronger contact during a reflex or its return
        self.shadowed = 0  # reflexes planned in shadow, while another planner was active
        self.last_gain = np.zeros(len(desc.pads))
        # What counts as a new or stronger contact, and how often one may restart a reflex (reflex storms).
        self.restarts = restarts.Restarts(cfg.restarts, [pad.name for pad in desc.pads])

    def _reacts_to(self, contact: m.Contact, new: np.ndarray, now_ns: int) -> bool:
        """Whether a contact with a gain starts a reflex: always from the task (at its first sample); else a new
        touch (``new``, or one a rate limit kept waiting) or a stronger one, within the restarts' rate limits."""
        pad = contact.pad
        if self.mode == "TASK":
            self.restarts.admit(pad, contact.gain, 0.0, now_ns, new=True, force=True)
            return True
        current = self.reflex.contact.gain if self.reflex is not None else 0.0
        fresh = bool(new[pad] or self.restarts.pending[pad])
        if not (fresh or contact.gain > current + self.cfg.update_margin):
            return False
        return self.restarts.admit(pad, contact.gain, current, now_ns, new=fresh)

    def _new_elsewhere(self, strongest: m.Contact, new: np.ndarray, now_ns: int) -> bool:
        """Whether a new touch on a pad other than the strongest one's (re)starts the reflex, within the restarts'
        rate limits: every contact counts, not only the strongest (the reflex then takes the strongest)."""
        if self.mode == "TASK":
            return False  # a start from the task takes the strongest at once (_reacts_to)
        current = self.reflex.contact.gain if self.reflex is not None else 0.0
        for pad in np.flatnonzero(self.last_gain > 0.0).tolist():
            if pad == strongest.pad or not (new[pad] or self.restarts.pending[pad]):
                continue
            if self.restarts.admit(pad, float(self.last_gain[pad]), current, now_ns, new=True):
                return True
        return False

    def _start_reflex(self, contact: m.Contact, trace: m.Trace, now_ns: int) -> None:
        self.braking = self.partial = self.held_max = False
        self._legs = []
        self.reflex_count += 1
        reflex = Reflex(self.reflex_count, contact, trace, now_ns)
        self._onset(reflex)
        if reflex.target is not None:
            self._ruckig_to(reflex.target, speeds=self._withdrawal_speeds(reflex.target, contact))
        self.reflex = reflex
        self.mode = "REFLEX"
        self.changed = True

    def _onset(self, reflex: Reflex) -> None:
        """The strategy starts ``reflex`` from the commanded pose: its target (position mode) or direction; every
        other active contact given first (:meth:`ReflexStrategy.set_contacts`)."""
        contacts = self.given_contacts(reflex.started_ns, reflex.contact.pad)
        self.strategy.set_contacts(self.q, contacts, reflex.contact.pad)
        reflex.others = tuple(contact.pad for contact in others(contacts, reflex.contact.pad))
        onset = self.strategy.start(self.q, reflex.contact)
        reflex.target, reflex.direction, reflex.corrected = onset.target, onset.direction, onset.corrected
        reflex.reason, reflex.reach_m = onset.reason, onset.reach_m

    def given_contacts(self, now_ns: int, main: int) -> list[ContactPoint]:
        """The recent contacts the strategy is given for a reflex on pad ``main`` (``planner.contacts``: every
        one, or the reflex's own only, the paper's)."""
        recent = self.contacts.recent(now_ns)
        return recent if self.cfg.contacts == "every" else [contact for contact in recent if contact.pad == main]

    def _withdrawal_speeds(self, target: np.ndarray, contact: m.Contact | None) -> np.ndarray:
        """Joint speed limits of a joint-space withdrawal to ``target``: every point within the withdrawal
        speed, and within the collaborative speed toward ``contact`` (along the touched pad's outward
        normal, toward the finger)."""
        if self.limits is None:
            return self.v_limit
        toward = contact_normal(self.model, self.q, contact) if contact is not None else None
        return self._joint_speeds_for(target, self.limits.withdrawal_speed_m_s, toward, self.limits.speed_m_s)

    def _preview_to(self, target: np.ndarray, contact: m.Contact, samples: int = 40) -> tuple[np.ndarray, float]:
        """The jerk-limited path from the current state to ``target``, computed offline."""
        n = len(self.q)
        inp = InputParameter(n)
        inp.max_velocity = self._withdrawal_speeds(target, contact).tolist()
        inp.max_acceleration = self._otg_in.max_acceleration
        inp.max_jerk = self._otg_in.max_jerk
        inp.synchronization = self._otg_in.synchronization
        inp.current_position = self.q.tolist()
        inp.current_velocity = self.dq.tolist()
        inp.current_acceleration = [0.0] * n
        inp.target_position = target.tolist()
        traj = Trajectory(n)
        Ruckig(n).calculate(inp, traj)
        times = np.linspace(0.0, max(traj.duration, self.dt), samples + 1)
        return np.array([traj.at_time(t)[0] for t in times]), float(times[1] - times[0])

    def _advance_reflex(self, now_ns: int) -> m.Command | None:
        """One cycle of the reflex; None (and RETURNING) once it is over."""
        reflex = self.reflex
        assert reflex is not None
        if reflex.stop_at_s is not None and reflex.elapsed_s >= reflex.stop_at_s:
            self._withdrawal_over(now_ns)  # furthest from the contact: the rest of the motion would go back
            return None
        if self.strategy.mode == "position":
            if self._ruckig_step():
                self._withdrawal_over(now_ns)
                return None
            reflex.elapsed_s += self.dt
            return self._position_command(now_ns)
        if reflex.elapsed_s >= self.strategy.duration_s:
            self._withdrawal_over(now_ns)
            return None
        return self._velocity_command(now_ns)

    def _velocity_command(self, now_ns: int) -> m.VelocityCommand:
        """The strategy's velocity stream, acceleration-limited from the current velocity."""
        assert self.reflex is not None
        target = self.strategy.velocity(self.q, self.reflex.elapsed_s)
        if self.strategy.retraces and not self.reflex.path:
            self.reflex.path.append(self.q.copy())
        self.reflex.elapsed_s += self.dt
        delta = target - self.dq
        ratio = float(np.max(np.abs(delta) / (self.a_limit * self.dt)))
        dq = self.dq + (delta / ratio if ratio > 1.0 else delta)
        q = self.q + dq * self.dt
        # Never command past a joint limit: stop that joint at the limit.
        low, high = q < self.desc.q_min, q > self.desc.q_max
        if low.any() or high.any():
            q = np.clip(q, self.desc.q_min, self.desc.q_max)
            dq[low | high] = 0.0
        self.ddq = (dq - self.dq) / self.dt
        self.q, self.dq = q, dq
        if self.strategy.retraces:
            self.reflex.path.append(q)
        msg = m.VelocityCommand(
            seq=self.seq, stamp_ns=now_ns, owner=self.name, dq=dq.tolist(), trace=self.trace,
            reflex_seq=self.reflex.seq, phase="REFLEX",
        )
        self.seq += 1
        return msg

    def assess(self) -> m.Retreat | None:
        """Retreat figures of the current reflex's planned motion (off the event path)."""
        check = self.retreat_check()
        if check is None:
            return None
        self.apply_retreat(check, check.run(self.model))
        return check.reflex.retreat

    def retreat_check(self) -> RetreatCheck | None:
        """What the retreat check of the current reflex needs (None outside a reflex)."""
        reflex = self.reflex
        if reflex is None or self.mode != "REFLEX":
            return None
        if self.strategy.mode == "position":
            path, dt = self.planned_path()
            return RetreatCheck(reflex, path, dt, None, self.q.copy(), 0.0, self.cfg.reflex_duration_s,
                                self.desc.q_min, self.desc.q_max)
        return RetreatCheck(reflex, None, 0.0, self.strategy.snapshot(), self.q.copy(), reflex.elapsed_s,
                            self.strategy.duration_s, self.desc.q_min, self.desc.q_max)

    def apply_retreat(self, check: RetreatCheck, assessment: retreat.Assessment) -> bool:
        """Store a check's figures on its reflex; False if a newer reflex has replaced it meanwhile."""
        reflex = check.reflex
        if reflex is not self.reflex:
            return False
        reflex.retreat = assessment.to_message(reflex.contact.pad, reflex.corrected or self.strategy.corrections > 0)
        reflex.withdraws = self._withdraws(reflex, assessment)
        if self.holds and reflex.withdraws and assessment.furthest_m - assessment.withdrawal_m > retreat.TOLERANCE_M:
            # A joint-space motion whose pad swings away and back: it ends where the pad is furthest away.
            start = check.t0 if check.path is None else 0.0
            reflex.stop_at_s = start + assessment.furthest_at_s
        self.changed = True
        if not reflex.withdraws:
            pad = self.desc.pads[reflex.contact.pad].name
            if self.holds and self.mode == "REFLEX":
                # Info: a property of the pose and the strategy, reported on the status, not a fault.
                log.info("reflex %d cannot move pad %s away from the contact (%.1f mm): holding still",
                            reflex.seq, pad, 1e3 * assessment.furthest_m)
                self._begin_hold(reflex.started_ns)
            else:
                log.info("reflex %d cannot move pad %s away from the contact (%.1f mm)", reflex.seq, pad,
                            1e3 * assessment.furthest_m)
        return True

    @staticmethod
    def _withdraws(reflex: Reflex, assessment: retreat.Assessment) -> bool:
        """Whether the reflex's motion moves the touched pad away from the contact at all (for its gain)."""
        moved = max(assessment.furthest_m, assessment.leaves_m) if reflex.reason == "sideways" \
            else assessment.furthest_m
        return moved >= WITHDRAW_MIN_M * max(reflex.contact.gain, MIN_GAIN_SCALE)

    def planned_path(self, samples: int = 40) -> tuple[np.ndarray, float]:
        """Joint positions over the rest of the current reflex, from its planned motion."""
        assert self.reflex is not None
        if self.strategy.mode == "position":
            traj = self._otg_out.trajectory
            duration = max(traj.duration, self.dt)
            times = np.linspace(0.0, duration, samples + 1)
            return np.array([traj.at_time(t)[0] for t in times]), float(times[1] - times[0])
        return self._integrate_stream(self.q, self.reflex.elapsed_s, samples)

    def _integrate_stream(self, q0: np.ndarray, t0: float, samples: int = 40) -> tuple[np.ndarray, float]:
        """The strategy's velocity stream from ``t0`` to its end, integrated from ``q0``."""
        return integrate_stream(self.strategy, q0, t0, self.strategy.duration_s, self.desc.q_min,
                                self.desc.q_max, samples)
