"""What a planner may believe of another planner's status: claims checked against its own observations.

A status is a claim, not a measurement. A planner that takes over the arm
(or mirrors the active one while on standby) starts from what it can verify
itself: the bridge's measured robot states, which it observes all along
(:class:`Seen`), and the task's own definition. A peer's claimed saved pose
is used only if it is where this planner saw the arm leave its task; a
claimed task time only if the task's pose at that time is where the arm is.
Anything else is refused and reported, naming the claimant. While standing
by, an active planner's status that contradicts the arm as measured
(:func:`contradiction`) is not mirrored (:mod:`.standby`).
"""

from __future__ import annotations

import numpy as np

from nwr.common import messages as m
from nwr.common.task import FigureEight

# A claimed pose this close (every joint, rad) to the pose the planner measured counts as confirmed.
CONFIRM_RAD = 0.05
# A claimed task time is confirmed when the task's pose at that time is this close to the measured arm (rad): the
# status is up to a status period old and the task may run ahead of the arm by what a command plans ahead.
TASK_TIME_RAD = 0.1
# A saved pose may lie this far (rad) beyond the range each joint was measured in during the session.
RANGE_MARGIN_RAD = 0.1
# A status may disagree with the bridge's phase or owner this long after either changed (s): the two are
# published by different processes, a status period apart.
SETTLE_S = 0.5


class Seen:
    """The arm as this planner measured it, from the bridge's robot states."""

    def __init__(self, n: int) -> None:
        self.owner = ""
        self.phase: m.Mode = "TASK"
        self.ok = False
        self.q: np.ndarray | None = None
        self.left_task: np.ndarray | None = None  # where the arm last left its task, measured
        self.last_task: np.ndarray | None = None  # the last pose measured while the bridge followed a task
        self.lo = np.full(n, np.inf)  # the range each joint was measured in during the session
        self.hi = np.full(n, -np.inf)
        self.changed_ns = 0  # when the owner, the phase or the status last changed

    def observe(self, q: np.ndarray, phase: m.Mode, ok: bool, owner: str, now_ns: int) -> None:
        if (owner, phase, ok) != (self.owner, self.phase, self.ok):
            self.changed_ns = now_ns
        if self.phase == "TASK" and phase != "TASK" and self.last_task is not None:
            self.left_task = self.last_task
        if phase == "TASK" and ok:
            self.last_task = q.copy()
        self.owner, self.phase, self.ok, self.q = owner, phase, ok, q
        np.minimum(self.lo, q, out=self.lo)
        np.maximum(self.hi, q, out=self.hi)

    def settled(self, now_ns: int) -> bool:
        """The owner, phase and status have held long enough for a status to agree with them."""
        return self.q is not None and self.ok and now_ns - self.changed_ns > SETTLE_S * 1e9

    def outside_range(self, pose: np.ndarray) -> tuple[int, float] | None:
        """The joint of ``pose`` farthest outside the measured range, and by how much (rad); None if within."""
        if self.q is None:
            return None
        beyond = np.maximum(self.lo - pose, pose - self.hi)
        i = int(np.argmax(beyond))
        return (i, float(beyond[i])) if beyond[i] > RANGE_MARGIN_RAD else None


def distance(a: np.ndarray, b: np.ndarray) -> float:
    """The largest joint difference, rad."""
    return float(np.max(np.abs(a - b)))


def contradiction(status: m.PlannerStatus, seen: Seen, task: FigureEight, joints: tuple[str, ...], *,
                  mode_settled: bool = True) -> str | None:
    """What in the active planner's status disagrees with the arm as measured (``seen``), if anything.

    ``mode_settled``: the status's mode has held for :data:`SETTLE_S` (a planner's status goes out the moment
    its mode changes, the bridge's state with the new phase up to a state period later: until then the two
    disagree honestly)."""
    assert seen.q is not None
    if status.saved_pose is not None:
        saved = np.asarray(status.saved_pose, dtype=float)
        if saved.shape != seen.q.shape:
            return f"a saved pose of {saved.size} joints"
        outside = seen.outside_range(saved)
        if outside is not None:
            i, by = outside
            return (f"its saved pose puts joint {joints[i]} {by:.3f} rad outside the range measured "
                    "in this session")
    # A return ends a withdrawal: either may show.
    if mode_settled and (status.mode == "TASK") != (seen.phase == "TASK"):
        return (f"mode {status.mode} while the bridge has followed its {seen.phase} commands for over "
                f"{SETTLE_S} s")
    if status.mode == "TASK":
        claimed = status.task_time_s  # as of just now: it was published on receipt
        off = distance(task.position(claimed), seen.q)
        if off > TASK_TIME_RAD:
            return f"task time {claimed:.3f} s puts the task {off:.3f} rad from the measured arm"
    return None
