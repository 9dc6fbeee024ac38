"""HOLDING: after the reflex's motion, brake to rest and stay away while the touch lasts.

With ``sustained_contact = "hold"`` (the default), once the reflex's motion
is over the arm brakes to rest (a jerk-limited brake, ruckig in velocity
mode) and stays away while the touch lasts. The return begins when the
touched pad has not felt a touch (pain level 2 or more) for ``release_s``
and no other pad that feels one would be brought closer to it by the return.
After ``max_hold_s`` the arm returns only as far as it can without bringing
any pad closer to a touch still felt, and holds there (a partial return). A
reflex that cannot move the touched pad away from the contact (its retreat
check finds under 2 mm of withdrawal, :mod:`.reflex`) stops and holds at
once. During a return, a touch felt on a pad the return brings closer to it
stops the return (the same brake) and the arm holds there. With
``sustained_contact = "paper"`` (the paper's behaviour) there is no HOLDING:
the return begins as soon as the reflex's motion is over.

:class:`Holding` owns the brake, when each pad last felt a touch, and the
hold's own state (since when, whether it reached ``max_hold_s``, whether
the return under way is a partial one).
"""

from __future__ import annotations

import logging

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Ruckig

from nwr.common import messages as m
from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner import retreat
from nwr.services.planner.contacts import FELT_LEVEL, ContactPoint, passes_through, past, straight
from nwr.services.planner.returning import Returning

log = logging.getLogger(__name__)

# How often a hold checks whether the return may begin, ns (the skin's period is 40 ms).
HOLD_CHECK_NS = 20_000_000
# The task after a return is checked against a recent touch at poses this far apart in its own time, s: the
# task moves a pad at up to about 0.2 m/s, so a few millimetres apart, and no way past the place falls between
# two of them (0.12 s apart, a way 11.4 mm past a touch did, at the edge of where the person was).
TASK_STEP_S = 0.02
# How far ahead the task is checked for a touch felt in its way (PL 2, no reflex yet), s.
TASK_AHEAD_S = 1.0
# How far past where a touch felt now (PL 2, no reflex yet) met its pad the task may take that pad, m: the
# person is there now, not a moment ago (planner.contact_margin_m is for recent touches).
FELT_MARGIN_M = 0.001


class Holding(Returning):
    """The hold after a withdrawal: the brake, the hold, the partial return, the touches felt ahead."""

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, *,
                 limits: CartesianLimits | None = None) -> None:
        super().__init__(cfg, desc, model, limits=limits)
        n = len(desc.joints)
        self.holds = cfg.sustained_contact == "hold"
        self.last_level = [1] * len(desc.pads)  # each pad's pain level in the last pain message
        self.light_touch: list[int] = []  # the pads in contact below PL 2 in the last pain message
        self.felt_ns = np.full(len(desc.pads), np.iinfo(np.int64).min // 2, dtype=np.int64)  # each pad's last touch
        self.hold_since_ns = 0
        self.held_max = False  # this hold has reached max_hold_s (and made its partial return, if any)
        self.partial = False  # the return under way is a partial one after max_hold_s: hold again on arrival
        self.braking = False  # HOLDING: still braking to rest
        self._hold_check_ns = 0
        self._waiting: set[int] = set()  # the recent touches this hold's return waits for (said once each)
        # How far the way back from the hold's pose, and the task after it, take a recent touch's pad past its
        # place, by touch (pad, onset, place): the same while the arm holds (its pose and the task's clock stand still).
        self._ways: dict[tuple[int, int, bytes], tuple[float, np.ndarray]] = {}
        self._ways_of: tuple[bytes, bytes, float] | None = None
        # The task's times at which it takes a recent touch's pad past its place, by touch (_task_past).
        self._task_ways: dict[tuple[int, int, bytes], np.ndarray] = {}
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
            self._waiting = set()
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
        """The pads that keep the arm holding: the touched pad while it feels the touch (within release_s), any
        other pad feeling one that the way to ``target`` (the saved pose, where the task resumes) would bring
        closer to it, and any recent touch the way back or the task after it would go through."""
        within = np.flatnonzero(now_ns - self.felt_ns < round(self.cfg.release_s * 1e9)).tolist()
        recent: list[int] = sorted(set(within) | set(self._felt()))
        touched = self.reflex.contact.pad if self.reflex is not None else -1
        out = []
        for pad in recent:
            if pad == touched or retreat.toward_along_path(self.model, self.q, target - self.q, pad)[0] > \
                    retreat.TOLERANCE_M:
                out.append(pad)
        # A touch no longer felt but recent: neither the way back nor the task after it, while the touch is
        # recent, may take its pad through where it met it.
        for contact in self.contacts.recent(now_ns):
            if contact.pad in out:
                continue
            back, task = self._way_past(contact, target)
            left_s = (contact.felt_ns + self.contacts.recent_ns - now_ns) / 1e9
            steps = max(0, min(len(task), int(np.floor(left_s / TASK_STEP_S + 1e-9))))
            depth = max(back, float(task[:steps].max(initial=0.0)))
            if depth > 0.0:
                out.append(contact.pad)
                if contact.pad not in self._waiting:
                    self._waiting.add(contact.pad)
                    log.info("the return (or the task after it) would take pad %s %.0f mm past where a touch met it "
                             "%.1f s ago: waiting "
                             "until that touch is %g s old (planner.recent_contact_s)",
                             self.desc.pads[contact.pad].name, 1e3 * (depth + self.cfg.contact_margin_m),
                             (now_ns - contact.felt_ns) / 1e9, self.cfg.recent_contact_s)
        return sorted(out)

    def _way_past(self, contact: ContactPoint, target: np.ndarray) -> tuple[float, np.ndarray]:
        """How far the straight way from the pose to ``target`` (the saved pose, where the task resumes) takes
        ``contact``'s pad past where it was touched beyond the margin (:func:`passes_through`), and the task after
        it at each TASK_STEP_S of its time while the touch may be recent, m; once per touch and hold."""
        key = (self.q.tobytes(), target.tobytes(), self.clock.s)
        if key != self._ways_of:
            self._ways, self._ways_of = {}, key
        touch = (contact.pad, contact.onset_ns, contact.point.tobytes())
        if touch not in self._ways:
            back = passes_through(self.model, straight(self.q, target), contact, self.cfg.contact_margin_m)
            self._ways[touch] = (back, np.maximum(0.0, self._task_beyond(contact)[1]))
        return self._ways[touch]

    def _task_beyond(self, contact: ContactPoint) -> tuple[np.ndarray, np.ndarray]:
        """The task's times every TASK_STEP_S from now for ``recent_contact_s``, and how far it takes ``contact``'s
        pad past where the touch met it at each, beyond ``contact_margin_m`` (:func:`past`; -inf away from
        where the person was), m."""
        times = self.clock.s + TASK_STEP_S * np.arange(1, int(np.ceil(self.cfg.recent_contact_s / TASK_STEP_S)) + 1)
        depth = np.array([past(self.model, self.task.position(s), contact) for s in times])
        return times, depth - self.cfg.contact_margin_m

    def _felt(self) -> list[int]:
        """The pads feeling a touch in the last pain message: PL 2 or more, or a light touch below it."""
        return sorted({i for i, level in enumerate(self.last_level) if level >= FELT_LEVEL} | set(self.light_touch))

    def _task_presses(self, now_ns: int) -> list[int]:
        """The pads feeling a touch without a gain (PL 2 or a light touch: no reflex) that the task, within
        TASK_AHEAD_S, would take more than FELT_MARGIN_M past where the touch met them (a slow press the task
        would push into), and those of recent touches no longer felt that the task, while they are recent,
        would take more than ``contact_margin_m`` past where they met them (a hand that has just let go)."""
        recent = self.contacts.recent(now_ns)
        if not recent:  # every pain message in the task asks: nothing to compute without a touch
            self._task_ways = {}
            return []
        felt = [c for c in recent if c.pad in self.contacts.touched and c.gain <= 0.0]
        out = []
        if felt:
            poses = [self.task.position(self.clock.s + s) for s in np.linspace(0.0, TASK_AHEAD_S, 11)[1:]]
            margin = min(FELT_MARGIN_M, self.cfg.contact_margin_m)
            out = [c.pad for c in felt if passes_through(self.model, poses, c, margin) > 0.0]
        for c in recent:
            if c.pad in self.contacts.touched:
                continue
            left_s = (c.felt_ns + self.contacts.recent_ns - now_ns) / 1e9
            times = self._task_past(c)
            if np.any((times > self.clock.s) & (times <= self.clock.s + left_s)):
                out.append(c.pad)
        return sorted(set(out))

    def _task_past(self, contact: ContactPoint) -> np.ndarray:
        """The task's times, every TASK_STEP_S from where it was when first asked for ``contact`` to
        ``recent_contact_s`` after, at which it takes the contact's pad more than ``contact_margin_m`` past
        where the touch met it; once per touch (the task's clock and the touch's recency only run on, so what
        is left to check stays within them)."""
        touch = (contact.pad, contact.onset_ns, contact.point.tobytes())
        if touch not in self._task_ways:
            times, beyond = self._task_beyond(contact)
            self._task_ways = {key: way for key, way in self._task_ways.items() if key[0] != contact.pad}
            self._task_ways[touch] = times[beyond > 0.0]
        return self._task_ways[touch]

    def _felt_ahead(self, now_ns: int) -> list[int]:
        """The pads feeling a touch now that the rest of the return brings closer to it."""
        assert self.saved is not None
        felt = self._felt()
        if not felt:
            return []
        d = self.saved - self.q
        return [pad for pad in felt if float((self.model.pad_jacobian(self.q, pad)[:3] @ d)
                                             @ self.model.pad_normal(self.q, pad)) > retreat.TOLERANCE_M]
