"""Standby and takeover: a planner the bridge does not follow mirrors the one it does, ready to take over.

While another planner is active, this one follows the arm as measured and
the active planner's status (:meth:`Standby.on_peer_status`), so that it
holds the same mode, task time and study target; a touch here plans the
reflex it would run, in shadow, without commanding it. When the bridge
starts following it, it takes over (:meth:`Standby._take_over`), continuing
the outgoing planner's motion from what it verified itself: a status is a
claim, checked against the bridge's measured states (:mod:`.claims`);
a refused or contradicting claim is reported, naming the claimant.

:class:`Standby` owns whether this planner is active, the active planner's
status and when it came, the shadow reflex, the arm as measured
(:class:`.claims.Seen`) and when each claimant's notes were last given.
"""

from __future__ import annotations

import logging

import numpy as np

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.task import nearest_time
from nwr.services.planner import claims, retreat
from nwr.services.planner.motion import Reflex
from nwr.services.planner.reflex import ReflexControl

log = logging.getLogger(__name__)

# A refused or contradicting claim of one planner is reported at most this often (per kind), ns.
NOTE_EVERY_NS = 5_000_000_000


class Standby(ReflexControl):
    """Mirroring the active planner while inactive, the shadow reflex, and taking over."""

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, *,
                 limits: CartesianLimits | None = None) -> None:
        super().__init__(cfg, desc, model, limits=limits)
        self.active = True  # until the bridge says it follows another planner
        self.peer: m.PlannerStatus | None = None  # the active planner's status, when another one is
        self.peer_ns = 0
        self.shadow: Reflex | None = None  # what this planner would do, while inactive
        self.seen = claims.Seen(len(desc.joints))  # the arm as measured: what a peer's claims are checked against
        self._noted: dict[tuple[str, str], int] = {}  # when each (code, claimant) was last noted
        self._claimed_mode: dict[str, tuple[str, int]] = {}  # each claimant's mode, and since when

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
        mode, since = self._claimed_mode.get(status.name, ("", 0))
        if status.mode != mode:
            self._claimed_mode[status.name] = (status.mode, now_ns)
            since = now_ns
        mode_settled = now_ns - since > claims.SETTLE_S * 1e9
        problem = claims.contradiction(status, seen, self.task, self.desc.joints,
                                       mode_settled=mode_settled) if settled else None
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

    def _note(self, code: str, claimant: str, now_ns: int, message: str) -> None:
        """A diagnostic about a claimant; a contradiction at most every NOTE_EVERY_NS per claimant."""
        last = self._noted.get((code, claimant))
        if code == "claim_contradicted" and last is not None and now_ns - last < NOTE_EVERY_NS:
            return
        self._noted[(code, claimant)] = now_ns
        log.warning("%s", message)
        self.notes.append(("warning", code, message))

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
        assessment = retreat.assess(self.model, path, dt, contact.pad, shadow.others)
        shadow.retreat = assessment.to_message(contact.pad, shadow.corrected or self.strategy.corrections > 0)
        shadow.withdraws = self._withdraws(shadow, assessment)
        self.shadow = shadow
        self.changed = True
