"""RETURNING: the way back from wherever the reflex left the arm to the saved pose.

A jerk-limited trajectory (ruckig) from wherever the reflex left the arm,
velocity included, back to the saved pose, no point of the arm faster than
``return_speed_m_s``; its last ``approach_distance_m`` (of the touched pad's
way back to where it was touched, or of the point that travels farthest) at
``approach_speed_m_s``. Wherever a pad or the flange comes within
``approach_distance_m`` of a recent contact (any touch felt in the last
``recent_contact_s``, :mod:`.contacts`), it moves toward that contact at
``approach_speed_m_s`` at most: the leg is split where the arm enters and
leaves those places, and the stretch between is capped. A retracing strategy's (``ReflexStrategy.retraces``:
the whole-arm withdrawal) goes back through poses on its own withdrawal's
path instead of on the straight line in joint space, without a stop between
the legs. A new or stronger contact here starts a new reflex but keeps the
saved pose: the arm always goes back to where the task paused. On arrival
the task resumes where it paused, easing in (:mod:`.core`); a partial return
(:mod:`.holding`) holds again instead.

:class:`Returning` owns the return's legs (each a target and its joint
speed limits) and the return speed; the control cycle (:meth:`.core.Planner.step`)
runs them one after the other.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common.config import CartesianLimits, PlannerSection
from nwr.common.robot import RobotDescription, RobotModel
from nwr.services.planner.contacts import FELT_LEVEL, Contacts
from nwr.services.planner.motion import CARTESIAN_MARGIN, MIN_JOINT_SPEED, Motion

# A retracing strategy's return passes through this many poses of its withdrawal, evenly along its way in joint
# space, when the arm is within RETRACE_OFF_RAD (every joint) of where the withdrawal ended and it moved more
# than RETRACE_MIN_RAD.
RETRACE_VIAS = 3
RETRACE_OFF_RAD = 0.05
RETRACE_MIN_RAD = 0.01
# The share of the next leg's cruise speed (and this leg's limit) a leg of the return ends at.
HANDOFF = 0.999
# A leg of the return begins no faster than it can brake from to its end within this share of its length at the
# joints' acceleration limits (the rest for the jerk limit's ramps).
BRAKE_SHARE = 0.5
# A leg is searched for the places near recent contacts at poses this far apart in any point's travel, as a
# share of 2 * approach_distance_m * approach_speed_m_s / return_speed_m_s: a way between two poses into a place
# and out again is then so shallow that it approaches the place at under this share of the approach speed (a
# chord h of a sphere of radius R goes h^2 / 8R deep, and meets it at h / 2R of its speed); further from every
# place, as far apart as the nearest point is from its nearest place.
PLACE_STEP = 0.9
# A point's travel along a leg, per unit of its way in joint space, is taken as this many times its straight
# distance between the leg's ends (a joint turning a point 1.5 rad travels 1.13 times that distance).
TRAVEL_SLACK = 1.5
# A stretch near a recent contact is capped at this many poses along it (and its ends).
TOWARD_SAMPLES = 9
# A point counts as near a contact at these times approach_distance_m at those poses (the poses between them).
NEAR_SLACK = 1.2


class Returning(Motion):
    """The return to the saved pose: its legs, the retracing of a withdrawal, the slowed approach."""

    braking: bool  # HOLDING's brake (:mod:`.holding`), which a return ends

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, *,
                 limits: CartesianLimits | None = None) -> None:
        super().__init__(cfg, desc, model, limits=limits)
        # The return's legs still to run after the current trajectory: (target, joint speed limits).
        self._legs: list[tuple[np.ndarray, np.ndarray]] = []
        # Returns and approaches: every point of the arm within this, m/s.
        self.return_speed = cfg.return_speed_m_s if limits is None else min(cfg.return_speed_m_s, limits.speed_m_s)
        # Every touch felt now and in the last recent_contact_s, where it met its pad (:mod:`.contacts`).
        self.contacts = Contacts(model, cfg.recent_contact_s, cfg.restarts.gap_s, FELT_LEVEL)

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

    def _replan_return(self) -> None:
        """A touch began during the return: the rest of its legs split and slowed near every recent contact
        (:meth:`_near_contacts`), from the commanded state (velocity included); unchanged if none is near."""
        rest = [(np.asarray(self._otg_in.target_position), np.asarray(self._otg_in.max_velocity)), *self._legs]
        legs = self._near_contacts(rest, min(self.cfg.approach_speed_m_s, self.return_speed))
        if len(legs) == len(rest) and all(np.array_equal(a[1], b[1]) for a, b in zip(legs, rest)):
            return
        self._legs = legs
        self._next_leg()

    def _next_leg(self) -> None:
        """Start the return's next leg, arriving at the following leg's start at that leg's cruise velocity:
        no stop between the legs."""
        goal, speeds = self._legs.pop(0)
        self._ruckig_to(goal, speeds=speeds, velocity=self._handover(goal, speeds, self._legs))

    def _handover(self, goal: np.ndarray, speeds: np.ndarray, legs: list[tuple[np.ndarray, np.ndarray]]
                  ) -> np.ndarray | None:
        """The velocity to reach ``goal`` at, ``legs`` following (None: at rest, the last): the next leg's
        cruise velocity, within this leg's limits too (ruckig refuses a target on the limit), and no faster
        than that next leg can brake from to its own handover within its length (BRAKE_SHARE of the distance
        each joint needs at its acceleration limit): a short leg into a slow stretch would otherwise overshoot
        into it and back."""
        if not legs:
            return None
        after, slow = legs[0]
        d = after - goal
        moving = np.abs(d) > 1e-9
        if not moving.any():
            return None
        velocity = d * float(np.min(np.minimum(slow, speeds)[moving] / np.abs(d[moving]))) * HANDOFF
        end = self._handover(after, slow, legs[1:])
        end = np.zeros_like(d) if end is None else np.where(np.sign(end) == np.sign(d), end, 0.0)
        room = np.sqrt(end ** 2 + 2.0 * BRAKE_SHARE * np.asarray(self.a_limit, dtype=float) * np.abs(d))
        fast = np.abs(velocity) > room
        if fast.any():
            velocity = velocity * float(np.min(room[fast] / np.abs(velocity[fast])))
        return velocity

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
        return self._near_contacts(legs, approach, own=(row, goal))

    def _points(self, q: np.ndarray) -> np.ndarray:
        """The points kept slow near a recent contact at ``q``: every pad and the flange (base frame, m)."""
        return np.vstack([self.model.pad_points(q), self.model.tool_position(q)])

    def _near_contacts(self, legs: list[tuple[np.ndarray, np.ndarray]], approach: float,
                       own: tuple[int, np.ndarray] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """``legs`` split where a pad or the flange comes within ``approach_distance_m`` of a recent contact, the
        stretches near one capped so that no such point moves toward it faster than ``approach``; a stretch
        whose caps that leaves as they were stays part of its leg.

        ``own``: the approaching point (its speed-Jacobian row) and where the
        return takes it, whose last ``approach_distance_m`` :meth:`_return_legs`
        already slows (speed, not only toward): a place there is left to that.
        """
        places = self.contacts.places()
        reach = self.cfg.approach_distance_m
        if not len(places) or reach <= 0.0:
            return legs
        step = PLACE_STEP * 2.0 * reach * approach / self.return_speed
        npads = len(self.desc.pads)
        exempt = np.zeros((npads + 1, len(places)), dtype=bool)  # (point, place) pairs the approach already slows
        if own is not None:
            row = own[0] if own[0] < npads else npads  # the flange: the last of the points
            exempt[row] = np.linalg.norm(places - own[1], axis=1) <= 1e-9

        def gaps(q: np.ndarray) -> np.ndarray:
            """How far each point is outside each place's reach, m (points x places; <= 0: within it)."""
            return np.where(exempt, np.inf, np.linalg.norm(self._points(q)[:, None, :] - places[None], axis=2) - reach)

        def near(q: np.ndarray) -> bool:
            return bool(np.min(gaps(q)) <= 0.0)

        out: list[tuple[np.ndarray, np.ndarray]] = []
        q0 = self.q.copy()
        for q1, speeds in legs:
            d = q1 - q0
            # Each point's travel per unit of the way, at most (about): from a pose, no point comes within a
            # place's reach before it has travelled its distance outside it, nor is a way in and out missed
            # within `step` of travel.
            rate = TRAVEL_SLACK * np.linalg.norm(self._points(q1) - self._points(q0), axis=1)[:, None] + 1e-12
            x, g = 0.0, gaps(q0)
            s, flags = [0.0], [bool(g.min() <= 0.0)]
            while x < 1.0:
                x = min(1.0, x + float(np.min(np.maximum(step, g) / rate)))
                g = gaps(q0 + x * d)
                s.append(x)
                flags.append(bool(g.min() <= 0.0))
            if not any(flags):
                out.append((q1, speeds))
                q0 = q1
                continue
            cuts = [0.0]
            for k in range(1, len(s)):
                if flags[k] != flags[k - 1]:  # a way into or out of a place: where, by bisection
                    lo, hi = s[k - 1], s[k]
                    for _ in range(6):
                        mid = 0.5 * (lo + hi)
                        if near(q0 + mid * d) == flags[k - 1]:
                            lo = mid
                        else:
                            hi = mid
                    cuts.append(lo if flags[k] else hi)  # the near stretch takes in both its ends
            cuts.append(1.0)
            slow = flags[0]
            pieces: list[tuple[np.ndarray, np.ndarray]] = []
            for a, b in zip(cuts, cuts[1:]):
                if b > a:
                    end = q0 + b * d if b < 1.0 else q1
                    caps = speeds
                    if slow:
                        caps = np.minimum(speeds, self._toward_speeds(q0 + a * d, end, places, approach, exempt))
                    if pieces and np.array_equal(pieces[-1][1], caps):
                        pieces[-1] = (end, caps)  # no slower than the stretch before: one leg
                    else:
                        pieces.append((end, caps))
                slow = not slow
            out += pieces
            q0 = q1
        return out

    def _toward_speeds(self, q0: np.ndarray, q1: np.ndarray, places: np.ndarray, approach: float,
                       exempt: np.ndarray) -> np.ndarray:
        """Joint speed limits under which, on the straight way from ``q0`` to ``q1``, no pad nor the flange within
        ``approach_distance_m`` of a place in ``places`` moves toward it faster than ``approach`` (as
        :meth:`.motion.Motion._joint_speeds_for`: at TOWARD_SAMPLES poses along the way, within its margin), but
        for the (point, place) pairs ``exempt`` says."""
        d = q1 - q0
        rows = [*range(len(self.desc.pads)), len(self.model.speed_points) - 1]  # the pads, the flange
        rate = 0.0
        for x in np.linspace(0.0, 1.0, TOWARD_SAMPLES):
            q = q0 + x * d
            to = places[None] - self._points(q)[:, None, :]  # (points, places, 3)
            dist = np.linalg.norm(to, axis=2)
            close = (dist <= NEAR_SLACK * self.cfg.approach_distance_m) & (dist > 1e-9) & ~exempt
            if not close.any():
                continue
            v = self.model.speed_jacobians(q)[rows] @ d  # (points, 3) per unit of the way
            toward = np.einsum("pk,pck->pc", v, to) / np.where(close, dist, 1.0)
            rate = max(rate, float(np.max(np.where(close, toward, 0.0))) / approach)
        if rate <= 0.0:
            return self.v_limit
        return np.minimum(self.v_limit, np.maximum(CARTESIAN_MARGIN * np.abs(d) / rate, MIN_JOINT_SPEED))

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
