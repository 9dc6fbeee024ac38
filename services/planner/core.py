"""Reflex planner core: the paper's TASK -> REFLEX -> RETURNING state machine.

- TASK: the arm follows the figure-eight (position commands). Any pad with
  a non-zero gain G(p) saves the current pose (the task's own reference at
  that instant, so the return lands exactly on the task path), pauses the
  task and starts a reflex.
- REFLEX: the strategy's motion runs (:mod:`.strategies`): in position
  mode a jerk-limited trajectory (ruckig) to its joint target, ending when
  the target is reached; in velocity mode its joint velocity stream, for
  the strategy's ``duration_s`` (``reflex_duration_s`` unless it has its own).
  A *new* contact (a pad whose touch begins: no gain for ``restarts.gap_s``) or a
  *stronger* one (gain above the current reflex's by ``update_margin``)
  updates the reflex: new target or direction from the current motion state
  (the trajectory blends, nothing jumps), duration restarted, new number.
  Restarts are rate-limited per pad and overall (:mod:`.restarts`: no
  reflex storm from a flickering pad or a forged stream); a start from the
  task is never delayed.
- HOLDING (``sustained_contact = "hold"``, the default): once the reflex's
  motion is over the arm brakes to rest and stays away while the touch
  lasts. The return begins when the touched pad has not felt a touch (pain
  level 2 or more) for ``release_s`` and no other pad that feels one would
  be brought closer to it by the return. After ``max_hold_s`` the arm
  returns only as far as it can without bringing any pad closer to a touch
  still felt, and holds there. A reflex that cannot move the touched pad
  away from the contact (its retreat check finds under 2 mm of withdrawal)
  stops and holds at once, reported (``ReflexInfo.withdraws``). With
  ``sustained_contact = "paper"`` (the paper's behaviour) there is no
  HOLDING: the return begins as soon as the reflex's motion is over.
- RETURNING: a jerk-limited trajectory (ruckig) from wherever the reflex
  left the arm, velocity included, back to the saved pose, no point of the
  arm faster than ``return_speed_m_s``; its last ``approach_distance_m`` (of
  the touched pad's way back to where it was touched, or of the point that
  travels farthest) at ``approach_speed_m_s``. A retracing strategy's
  (``ReflexStrategy.retraces``: the whole-arm withdrawal) goes back through
  poses on its own withdrawal's path instead of on the straight line in
  joint space, without a stop between the legs. A new or stronger contact
  here starts a new reflex but keeps the saved pose: the arm always goes
  back to where the task paused. In hold mode a touch felt on a pad the
  return brings closer to it stops the return (a jerk-limited brake) and
  the arm holds there. On arrival the task resumes where it paused, easing in.

The core keeps its own commanded state (q, q_dot, q_ddot), integrated at
the nominal control period and within the joint limits, so every command is
consistent with the previous one. It re-synchronises from the robot state
when the two disagree (after the bridge stopped the arm, say).

The reflex path is event driven: :meth:`on_pain` returns the first command
of a reflex at once; :meth:`step` carries the motion on every control cycle.
The retreat check of a reflex (a few ms of kinematics) is split so that it
can run beside both: :meth:`retreat_check` takes what it needs (under the
adapter's lock), :meth:`RetreatCheck.run` computes it on a model of its own,
:meth:`apply_retreat` stores it if the reflex is still the current one.
:meth:`assess` does all three at once.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from ruckig import (
    ControlInterface,
    InputParameter,
    OutputParameter,
    Result,
    Ruckig,
    RuckigError,
    Synchronization,
    Trajectory,
)

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.task import FigureEight, TaskClock, nearest_time
from nwr.services.planner import claims, restarts, retreat, strategies
from nwr.services.planner.strategies import ReflexStrategy

log = logging.getLogger(__name__)

RESYNC_RAD = 0.2  # commanded vs measured pose disagreement that forces a resync
# A refused or contradicting claim of one planner is reported at most this often (per kind), ns.
NOTE_EVERY_NS = 5_000_000_000
# The share of a Cartesian speed limit the planner's own motions plan for (the bridge enforces the whole).
CARTESIAN_MARGIN = 0.9
# A joint that need not move still gets this speed limit, rad/s (ruckig needs one > 0).
MIN_JOINT_SPEED = 1e-3
# A retracing strategy's return passes through this many poses of its withdrawal, evenly along its way in joint
# space, when the arm is within RETRACE_OFF_RAD (every joint) of where the withdrawal ended and it moved more
# than RETRACE_MIN_RAD.
RETRACE_VIAS = 3
RETRACE_OFF_RAD = 0.05
RETRACE_MIN_RAD = 0.01
# The share of the next leg's cruise speed (and this leg's limit) a leg of the return ends at.
HANDOFF = 0.999
# A pad feels a touch from this pain level on (PL 2: above the first threshold, below a reflex's).
FELT_LEVEL = 2
# A reflex whose planned motion withdraws the touched pad less than this times its gain (at least
# MIN_GAIN_SCALE) cannot withdraw it, m: at G = 1 the strategies withdraw a pad they can move by centimetres.
WITHDRAW_MIN_M = 0.002
MIN_GAIN_SCALE = 0.1
# How often a hold checks whether the return may begin, ns (the skin's period is 40 ms).
HOLD_CHECK_NS = 20_000_000


@dataclass
class Reflex:
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
    # A retracing strategy's withdrawal: the commanded poses of its stream, from the onset (one a cycle).
    path: list[np.ndarray] = field(default_factory=list)


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
        return retreat.assess(model, path, dt, self.reflex.contact.pad)


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


class Planner:
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
        self.task = FigureEight(cfg.task, desc.home)
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
        self.reflex_count = 0  # reflex numbers given: started, restarted and shadow ones
        self.started = 0  # reflexes started from the task
        self.restarted = 0  # a reflex started again by a new or stronger contact during a reflex or its return
        self.shadowed = 0  # reflexes planned in shadow, while another planner was active
        self.last_gain = np.zeros(len(desc.pads))
        self.last_level = [1] * len(desc.pads)
        # What counts as a new or stronger contact, and how often one may restart a reflex (reflex storms).
        self.restarts = restarts.Restarts(cfg.restarts, [pad.name for pad in desc.pads])
        self.holds = cfg.sustained_contact == "hold"
        self.felt_ns = np.full(len(desc.pads), np.iinfo(np.int64).min // 2, dtype=np.int64)  # each pad's last touch
        self.hold_since_ns = 0
        self.held_max = False  # this hold has reached max_hold_s (and made its partial return, if any)
        self.partial = False  # the return under way is a partial one after max_hold_s: hold again on arrival
        self.braking = False  # HOLDING: still braking to rest
        self._hold_check_ns = 0
        # The return's legs still to run after the current trajectory: (target, joint speed limits).
        self._legs: list[tuple[np.ndarray, np.ndarray]] = []
        self.trace = m.NO_TRACE
        self.seq = 0
        self.status_seq = 0
        self.decision_seq = 0
        self.changed = True  # a transition not yet published on the status
        self.resyncs = 0
        self._advanced_early = False
        # Task cycles the last command's setpoints ahead still cover; reset
        # wherever the task (re)starts (_resume_task, _take_over).
        self._planned_ahead = 0
        self.active = True  # until the bridge says it follows another planner
        self.peer: m.PlannerStatus | None = None  # the active planner's status, when another one is
        self.peer_ns = 0
        self.shadow: Reflex | None = None  # what this planner would do, while inactive
        self.seen = claims.Seen(n)  # the arm as measured: what a peer's claims are checked against
        # Diagnostics for the adapter to publish (level, code, message), and when each (code, claimant) last was.
        self.notes: list[tuple[str, str, str]] = []
        self._noted: dict[tuple[str, str], int] = {}
        self._otg = Ruckig(n, self.dt)
        self._otg_in = InputParameter(n)
        self._otg_out = OutputParameter(n)
        self._otg_in.max_velocity = self.v_limit.tolist()
        self._otg_in.max_acceleration = self.a_limit.tolist()
        self._otg_in.max_jerk = (cfg.speed_fraction * desc.j_max).tolist()
        if limits is not None:  # the way stays on the straight line the Cartesian caps are computed for
            self._otg_in.synchronization = Synchronization.Phase
        # The hold's brake: from the commanded state to rest, jerk-limited.
        self._brake = Ruckig(n, self.dt)
        self._brake_in = InputParameter(n)
        self._brake_out = OutputParameter(n)
        self._brake_in.control_interface = ControlInterface.Velocity
        self._brake_in.max_velocity = self._otg_in.max_velocity
        self._brake_in.max_acceleration = self._otg_in.max_acceleration
        self._brake_in.max_jerk = self._otg_in.max_jerk
        self._brake_in.target_velocity = [0.0] * n
        self._brake_in.target_acceleration = [0.0] * n
        # Returns and approaches: every point of the arm within this, m/s.
        self.return_speed = cfg.return_speed_m_s if limits is None else min(cfg.return_speed_m_s, limits.speed_m_s)

    @staticmethod
    def _target_order(cfg: PlannerSection, desc: RobotDescription) -> list[int]:
        if cfg.target_order:
            return [desc.pad(name).id for name in cfg.target_order]
        return [int(i) for i in np.random.default_rng(cfg.target_seed).permutation(len(desc.pads))]

    @property
    def target_pad(self) -> int:
        return self.targets[self.target_index % len(self.targets)] if self.targets else -1

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

    # -- inactive: mirror the arm and the active planner, ready to take over -------
    def on_peer_status(self, status: m.PlannerStatus, now_ns: int) -> None:
        """Another planner's status: mirrored while this one is inactive, if the bridge does follow that planner.

        A status is a claim: one that contradicts the bridge's measured state
        (active while the bridge follows another planner, a phase or a task
        pose other than the arm's, a saved pose outside every pose measured in
        the session) is reported, naming the claimant, and never mirrored.
        """
        if status.name == self.name:
            return
        seen = self.seen
        settled = seen.settled(now_ns)
        if status.name != seen.owner:
            if status.active and settled:
                self._note("claim_contradicted", status.name, now_ns,
                           f"planner {status.name!r} claims to be the active planner; the bridge follows "
                           f"{seen.owner!r}: its status is ignored")
            return
        if not status.active:
            return
        problem = self._contradiction(status, now_ns) if settled else None
        if problem is not None:
            self._note("claim_contradicted", status.name, now_ns,
                       f"planner {status.name!r}'s status contradicts the bridge's measured state: {problem}; "
                       "it is not mirrored")
            return
        self.peer = status
        self.peer_ns = now_ns
        if not self.active:
            if status.target_pad in self.targets:  # one study target, whoever is active
                self.target_index = self.targets.index(status.target_pad)
            self.mode = status.mode
            self.clock.s = self._peer_task_time(now_ns)

    def _contradiction(self, status: m.PlannerStatus, now_ns: int) -> str | None:
        """What in the active planner's status disagrees with the arm as measured, if anything."""
        seen = self.seen
        assert seen.q is not None
        if status.saved_pose is not None:
            saved = np.asarray(status.saved_pose, dtype=float)
            if saved.shape != seen.q.shape:
                return f"a saved pose of {saved.size} joints"
            outside = seen.outside_range(saved)
            if outside is not None:
                i, by = outside
                return (f"its saved pose puts joint {self.desc.joints[i]} {by:.3f} rad outside the range measured "
                        "in this session")
        if (status.mode == "TASK") != (seen.phase == "TASK"):  # a return ends a withdrawal: either may show
            return (f"mode {status.mode} while the bridge has followed its {seen.phase} commands for over "
                    f"{claims.SETTLE_S} s")
        if status.mode == "TASK":
            claimed = status.task_time_s  # as of just now: it was published on receipt
            off = claims.distance(self.task.position(claimed), seen.q)
            if off > claims.TASK_TIME_RAD:
                return f"task time {claimed:.3f} s puts the task {off:.3f} rad from the measured arm"
        return None

    def _note(self, code: str, claimant: str, now_ns: int, message: str) -> None:
        """A diagnostic about a claimant; a contradiction at most every NOTE_EVERY_NS per claimant."""
        last = self._noted.get((code, claimant))
        if code == "claim_contradicted" and last is not None and now_ns - last < NOTE_EVERY_NS:
            return
        self._noted[(code, claimant)] = now_ns
        log.warning("%s", message)
        self.notes.append(("warning", code, message))

    def drain_notes(self) -> list[tuple[str, str, str]]:
        notes, self.notes = self.notes + self.restarts.notes + self.strategy.notes, []
        self.strategy.notes = []
        self.restarts.notes = []
        return notes

    def _peer_task_time(self, now_ns: int) -> float:
        peer = self.peer
        if peer is None:
            return self.clock.s
        # The status is up to one status period old; the task runs at rate 1 in TASK.
        ahead = (now_ns - self.peer_ns) / 1e9 if peer.mode == "TASK" else 0.0
        return peer.task_time_s + max(0.0, ahead)

    def _mirror(self, q: np.ndarray, dq: np.ndarray | None, now_ns: int) -> None:
        if self.active and self.initialized:
            log.info("planner %r is no longer active: mirroring the arm and the active planner", self.name)
        self.active = False
        self.initialized = True
        self.q = q.copy()
        self.dq = np.zeros_like(q) if dq is None else dq.copy()
        self.ddq[:] = 0.0
        self.saved = None
        self.reflex = None
        self._advanced_early = False
        if self.peer is not None:
            self.mode = self.peer.mode
            self.clock.s = self._peer_task_time(now_ns)

    def _take_over(self, q: np.ndarray, dq: np.ndarray | None, now_ns: int) -> None:
        """Become the active planner, continuing the motion of the outgoing one from what this planner verified.

        The bridge switches between two task commands, so if it was following
        a task the arm is on the task's path: the task continues at the time
        whose pose is the arm's (the outgoing planner's claimed time if it
        fits). If the outgoing planner died mid-reflex, the arm goes back to
        where this planner saw it leave the task (the outgoing planner's
        claimed saved pose only if it is that pose), else to the task's path.
        """
        self.q = q.copy()
        self.dq = np.zeros_like(q) if dq is None else dq.copy()
        self.ddq[:] = 0.0
        self.shadow = None
        self._planned_ahead = 0
        self.changed = True
        peer, seen = self.peer, self.seen
        claimant = peer.name if peer is not None else ""
        claimed_s = self._peer_task_time(now_ns)
        if seen.phase == "TASK":
            if peer is not None and peer.mode != "TASK":
                self._note("claim_refused", claimant, now_ns,
                           f"planner {claimant!r} claimed mode {peer.mode}, but the bridge was following its task: "
                           f"planner {self.name!r} continues the task from the measured arm")
            s, off = self._task_time_at(q, self.dq, claimed_s, claimant, now_ns)
            self.clock.s = s
            log.info("planner %r takes over at task time %.3f s (outgoing planner %r in %s)", self.name, s,
                     claimant, peer.mode if peer is not None else "unknown mode")
            if off <= claims.TASK_TIME_RAD:
                self.mode = "TASK"  # the arm is on the task path at this task time: carry on at full speed
                self.clock.since_resume = self.clock.ramp_s
                self.saved = None
                return
            self.saved = self.task.position(s)  # off the path: back to its nearest point first
            self._begin_return()
            return
        # Taken over mid-reflex (the outgoing planner died): go back where the arm left its task.
        saved = seen.left_task
        if peer is not None and peer.saved_pose:
            claim = np.asarray(peer.saved_pose, dtype=float)
            if saved is not None and claim.shape == saved.shape and claims.distance(claim, saved) <= claims.CONFIRM_RAD:
                saved = claim
            else:
                where = ("this planner never saw the arm leave its task" if saved is None else
                         f"it is {claims.distance(claim, saved):.3f} rad from where this planner saw the arm leave "
                         "its task" if claim.shape == saved.shape else f"it has {claim.size} joints")
                self._note("claim_refused", claimant, now_ns,
                           f"planner {claimant!r}'s saved pose refused: {where}")
        if saved is None:
            s, _ = nearest_time(self.task, q, self.dq, claimed_s)  # nothing seen: the task's nearest point
            saved = self.task.position(s)
        else:
            s, _ = self._task_time_at(saved, None, claimed_s, claimant, now_ns)
        self.clock.s = s
        self.saved = saved
        if self.holds:
            log.info("planner %r takes over mid-reflex at task time %.3f s: holding until no touch is felt, then "
                     "returning to the saved pose", self.name, s)
            self._begin_hold(now_ns)
            return
        log.info("planner %r takes over mid-reflex at task time %.3f s: returning to the saved pose", self.name, s)
        self._begin_return()

    def _task_time_at(self, q: np.ndarray, dq: np.ndarray | None, claimed_s: float, claimant: str,
                      now_ns: int) -> tuple[float, float]:
        """The task time at pose ``q``: the claimed one if its pose is there, else the nearest; and the distance."""
        off = claims.distance(self.task.position(claimed_s), q)
        if off <= claims.TASK_TIME_RAD:
            return claimed_s, off
        s, nearest = nearest_time(self.task, q, dq, claimed_s)
        if claimant:
            self._note("claim_refused", claimant, now_ns,
                       f"planner {claimant!r}'s task time {claimed_s:.3f} s puts the task {off:.3f} rad from the "
                       f"arm; the task's own nearest time is {s:.3f} s ({nearest:.3f} rad)")
        return s, nearest

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
        if len(pain.level) == len(self.felt_ns):
            self.felt_ns[np.asarray(pain.level) >= FELT_LEVEL] = now_ns
        contact = pain.strongest
        if not self.active:
            self._on_pain_inactive(contact, new, pain.trace, now_ns)
            return None
        if not self.initialized:
            return None
        if contact is None or not contact.gain > 0 or not self._reacts_to(contact, new, now_ns):
            if self.holds and self.mode == "RETURNING" and not self.partial:
                ahead = self._felt_ahead(now_ns)
                if ahead:
                    names = ", ".join(self.desc.pads[i].name for i in ahead)
                    log.info("the return would press on a touch felt on %s: stopping it there", names)
                    self._begin_hold(now_ns)
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

    def _on_pain_inactive(self, contact: m.Contact | None, new: np.ndarray, trace: m.Trace, now_ns: int) -> None:
        """Shadow mode: what this planner would do on the same touch, from the arm's pose now."""
        if not self.initialized:
            return
        if contact is None or not contact.gain > 0:
            if self.shadow is not None and self.mode == "TASK":
                self.shadow = None
                self.changed = True
            return
        current = self.shadow.contact.gain if self.shadow is not None else 0.0
        fresh = bool(new[contact.pad] or self.restarts.pending[contact.pad])
        if not (fresh or contact.gain > current + self.cfg.update_margin):
            return
        if not self.restarts.admit(contact.pad, contact.gain, current, now_ns, new=fresh, force=self.shadow is None):
            return
        self.reflex_count += 1
        self.shadowed += 1
        shadow = Reflex(self.reflex_count, contact, trace, now_ns)
        self._onset(shadow)
        if shadow.target is not None:
            path, dt = self._preview_to(shadow.target, contact)
        else:
            path, dt = self._integrate_stream(self.q, 0.0)
        assessment = retreat.assess(self.model, path, dt, contact.pad)
        shadow.retreat = assessment.to_message(contact.pad, shadow.corrected or self.strategy.corrections > 0)
        shadow.withdraws = self._withdraws(shadow, assessment)
        self.shadow = shadow
        self.changed = True

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

    # -- transitions --------------------------------------------------------
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
        """The strategy starts ``reflex`` from the commanded pose: its target (position mode) or direction."""
        onset = self.strategy.start(self.q, reflex.contact)
        reflex.target, reflex.direction, reflex.corrected = onset.target, onset.direction, onset.corrected
        reflex.reason = onset.reason

    def _withdrawal_speeds(self, target: np.ndarray, contact: m.Contact | None) -> np.ndarray:
        """Joint speed limits of a joint-space withdrawal to ``target``: every point within the withdrawal
        speed, and within the collaborative speed toward ``contact`` (along the touched pad's outward
        normal, toward the finger)."""
        if self.limits is None:
            return self.v_limit
        toward = self.model.pad_normal(self.q, contact.pad) if contact is not None else None
        return self._joint_speeds_for(target, self.limits.withdrawal_speed_m_s, toward, self.limits.speed_m_s)

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

    def _begin_return(self, target: np.ndarray | None = None) -> None:
        """Back to the saved pose (or ``target``, a partial return), the last stretch at the approach speed; a
        retracing strategy's withdrawal back along its own path (:meth:`_retrace`)."""
        assert self.saved is not None
        vias = self._retrace() if target is None else []
        self._legs = self._return_legs(self.saved if target is None else target, vias)
        self._next_leg()
        self.braking = False
        self.mode = "RETURNING"
        self.changed = True

    def _next_leg(self) -> None:
        """Start the return's next leg, arriving at the following leg's start at that leg's cruise velocity:
        no stop between the legs."""
        goal, speeds = self._legs.pop(0)
        velocity = None
        if self._legs:
            after, slow = self._legs[0]
            d = after - goal
            moving = np.abs(d) > 1e-9
            if moving.any():  # within this leg's speed limits too (ruckig refuses a target on the limit)
                velocity = d * float(np.min(np.minimum(slow, speeds)[moving] / np.abs(d[moving]))) * HANDOFF
        self._ruckig_to(goal, speeds=speeds, velocity=velocity)

    def _retrace(self) -> list[np.ndarray]:
        """Poses on the current reflex's withdrawal, last to first, that a retracing strategy's return passes
        through (none when the arm is no longer where that withdrawal ended)."""
        reflex = self.reflex
        if not self.strategy.retraces or reflex is None or len(reflex.path) < 2:
            return []
        path = np.asarray(reflex.path)
        if np.max(np.abs(path[-1] - self.q)) > RETRACE_OFF_RAD:
            return []
        steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
        length = np.concatenate([[0.0], np.cumsum(steps)])
        if length[-1] <= RETRACE_MIN_RAD:
            return []
        marks = length[-1] * np.arange(RETRACE_VIAS, 0, -1) / (RETRACE_VIAS + 1)
        return [path[int(np.searchsorted(length, mark))].copy() for mark in marks]

    def _return_legs(self, target: np.ndarray, vias: list[np.ndarray] | None = None
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The return's legs on the straight lines to ``target`` (through ``vias``): (end, joint speed limits)
        each.

        Every point of the arm within the return speed; over the last
        ``approach_distance_m`` of the approaching point's way (the touched
        pad's, back to where it was touched; without a reflex, the pad or
        flange that travels farthest) that point within the approach speed.
        """
        cfg = self.cfg
        approach = min(cfg.approach_speed_m_s, self.return_speed)
        row, at = self._approaching_point(self.q, target)
        goal = at(target)

        def near(q: np.ndarray) -> bool:
            return bool(np.linalg.norm(at(q) - goal) <= cfg.approach_distance_m)

        legs = []
        corners = [self.q.copy(), *(vias or []), target]
        for q0, q1 in zip(corners, corners[1:]):
            if near(q0):
                legs.append((q1, self._joint_speeds_for(q1, self.return_speed, start=q0, point=row,
                                                        point_m_s=approach)))
                continue
            if not near(q1):
                legs.append((q1, self._joint_speeds_for(q1, self.return_speed, start=q0)))
                continue
            d = q1 - q0
            lo, hi = 0.0, 1.0  # the fraction of the way where the approach begins (bisection: the distance shrinks)
            for _ in range(14):
                mid = 0.5 * (lo + hi)
                if not near(q0 + mid * d):
                    lo = mid
                else:
                    hi = mid
            start = q0 + lo * d
            slow = self._joint_speeds_for(q1, self.return_speed, start=start, point=row, point_m_s=approach)
            fast = self._joint_speeds_for(start, self.return_speed, start=q0)
            legs += [(start, np.maximum(fast, slow)), (q1, slow)]
        return legs

    def _approaching_point(self, q0: np.ndarray, target: np.ndarray) -> tuple[int, Any]:
        """The point whose approach is slowed (its row in the speed Jacobians, and its position function):
        the touched pad; without a reflex, the pad or the flange that travels farthest to ``target``."""
        model = self.model
        if self.reflex is not None:
            pad = self.reflex.contact.pad
            return pad, lambda q: model.pad_point(q, pad)
        ends = np.linalg.norm(model.pad_points(target) - model.pad_points(q0), axis=1)
        far = int(np.argmax(ends))
        if np.linalg.norm(model.tool_position(target) - model.tool_position(q0)) > ends[far]:
            return len(model.speed_points) - 1, model.tool_position  # the flange: the last speed point
        return far, lambda q: model.pad_point(q, far)

    def _withdrawal_over(self, now_ns: int) -> None:
        """The reflex's motion is over: hold while the touch lasts, or (the paper) return at once."""
        if self.holds:
            self._begin_hold(now_ns)
        else:
            self._begin_return()

    def _begin_hold(self, now_ns: int, *, keep_since: bool = False) -> None:
        """Brake to rest (jerk-limited) and hold there: HOLDING."""
        self._legs = []
        self.partial = False
        if not keep_since or self.mode != "HOLDING":
            self.hold_since_ns = now_ns
            self.held_max = False
        self._hold_check_ns = now_ns + HOLD_CHECK_NS
        inp = self._brake_in
        inp.current_position = self.q.tolist()
        inp.current_velocity = self.dq.tolist()
        inp.current_acceleration = self.ddq.tolist()
        self._brake.reset()
        self.braking = bool(np.any(self.dq != 0.0) or np.any(self.ddq != 0.0))
        if self.mode != "HOLDING":
            self.changed = True
        self.mode = "HOLDING"

    def _hold_step(self, now_ns: int) -> m.PositionCommand | None:
        """One cycle of HOLDING: brake, hold, or (None) begin the return."""
        if self.braking:
            if self._ruckig_step(self._brake, self._brake_in, self._brake_out):
                self.braking = False
                self.dq[:] = 0.0
                self.ddq[:] = 0.0
            return self._position_command(now_ns)
        if now_ns < self._hold_check_ns:
            return self._position_command(now_ns)
        self._hold_check_ns = now_ns + HOLD_CHECK_NS
        assert self.saved is not None
        blocking = self._blocking(self.saved, now_ns)
        if not blocking:
            self._begin_return()
            return None
        if not self.held_max and now_ns - self.hold_since_ns >= round(self.cfg.max_hold_s * 1e9):
            self.held_max = True
            self._partial_return(blocking)
            if self.mode == "RETURNING":
                return None
        return self._position_command(now_ns)

    def _partial_return(self, blocking: list[int]) -> None:
        """After max_hold_s: return as far as no pad in ``blocking`` comes closer to its touch, and hold there."""
        assert self.saved is not None
        delta = self.saved - self.q
        for _ in range(2):  # correcting for one pad may move another: once more
            for pad in blocking:
                delta, _ = retreat.guard_displacement(self.model, self.q, delta, pad, self.desc.q_min,
                                                      self.desc.q_max)
        names = ", ".join(self.desc.pads[i].name for i in blocking)
        moved = float(np.max(np.abs(delta)))
        if moved < 1e-3:
            message = (f"touch still felt on {names} after {self.cfg.max_hold_s:g} s (planner.max_hold_s): no "
                       "return moves away from it; holding until it ends")
        else:
            message = (f"touch still felt on {names} after {self.cfg.max_hold_s:g} s (planner.max_hold_s): "
                       f"returning {moved:.3f} rad of the way, only along directions that approach no touch, "
                       "then holding until it ends")
        log.warning("%s", message)
        self.notes.append(("warning", "max_hold", message))
        if moved >= 1e-3:
            self._begin_return(self.q + delta)
            self.partial = True

    def _blocking(self, target: np.ndarray, now_ns: int) -> list[int]:
        """The pads that keep the arm holding: the touched pad while it feels the touch (within release_s),
        and any other pad feeling one that the way to ``target`` would bring closer to it."""
        within = np.flatnonzero(now_ns - self.felt_ns < round(self.cfg.release_s * 1e9)).tolist()
        recent: list[int] = sorted(set(within) | {i for i, level in enumerate(self.last_level) if level >= FELT_LEVEL})
        touched = self.reflex.contact.pad if self.reflex is not None else -1
        out = []
        for pad in recent:
            if pad == touched or retreat.toward_along_path(self.model, self.q, target - self.q, pad)[0] > \
                    retreat.TOLERANCE_M:
                out.append(pad)
        return out

    def _felt_ahead(self, now_ns: int) -> list[int]:
        """The pads feeling a touch now that the rest of the return brings closer to it."""
        assert self.saved is not None
        felt = [i for i, level in enumerate(self.last_level) if level >= FELT_LEVEL]
        if not felt:
            return []
        d = self.saved - self.q
        return [pad for pad in felt if float((self.model.pad_jacobian(self.q, pad)[:3] @ d)
                                             @ self.model.pad_normal(self.q, pad)) > retreat.TOLERANCE_M]

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
            if self._legs:  # on to the next leg, at the speed this leg arrived with
                self._next_leg()
                self._ruckig_step()
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

    # -- the retreat check ------------------------------------------------------
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

    def _position_command(self, now_ns: int) -> m.PositionCommand:
        msg = m.PositionCommand(
            seq=self.seq, stamp_ns=now_ns, owner=self.name, q=self.q.tolist(), trace=self.trace,
            reflex_seq=self.reflex.seq if self.reflex is not None else 0, phase=self.mode,
        )
        self.seq += 1
        return msg

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
                shadow=not self.active, withdraws=r.withdraws, reason=r.reason,
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
