"""RETURNING: the way back from wherever the reflex left the arm to the saved pose.

A jerk-limited trajectory (ruckig) from wherever the reflex left the arm,
velocity included, back to the saved pose, no point of the arm faster than
``return_speed_m_s``; its last ``approach_distance_m`` (of the touched pad's
way back to where it was touched, or of the point that travels farthest) at
``approach_speed_m_s``. A retracing strategy's (``ReflexStrategy.retraces``:
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
from nwr.services.planner.motion import Motion

# A retracing strategy's return passes through this many poses of its withdrawal, evenly along its way in joint
# space, when the arm is within RETRACE_OFF_RAD (every joint) of where the withdrawal ended and it moved more
# than RETRACE_MIN_RAD.
RETRACE_VIAS = 3
RETRACE_OFF_RAD = 0.05
RETRACE_MIN_RAD = 0.01
# The share of the next leg's cruise speed (and this leg's limit) a leg of the return ends at.
HANDOFF = 0.999


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
