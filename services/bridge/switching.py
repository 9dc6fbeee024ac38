"""The active planner: its liveliness, and switching to another one.

The bridge obeys one planner, the active one. Its liveliness token says
whether it is there: a planner that loses it is ``planner_lost`` (the arm is
brought to rest and held), and one that (re)appears counts its commands
afresh. A switch (``nwr switch``: ``control/active``) to a running planner
never cuts a reflex or its return short: it waits until the outgoing
planner commands its task again, or is not commanding at all, and happens
between two commands; the outgoing planner's commands are then dropped
quietly for :data:`PREVIOUS_OWNER_GRACE_NS`. The incoming planner's first
motion (a handover) is followed no faster than the outgoing stream moved
the arm and only within the range the arm covered in the session
(:class:`~.checks.Reach`), for at least :data:`HANDOVER_S` and until the arm
has joined its stream (:mod:`.commands`, :mod:`.core`).

:class:`Switching` owns the planners alive, the switch pending, the last
handover, and the handover's reach and speed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.checks import Event, Reach
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.limits import REJOIN_FLOOR_M_S
from nwr.services.bridge.skin import SkinValidity

# After a switch, the outgoing planner's commands are dropped quietly this long
# (it learns of the switch from the next robot state), ns.
PREVIOUS_OWNER_GRACE_NS = 200_000_000
# A handover's first motion, s: the incoming planner's stream is followed no
# faster than the outgoing one moved the arm, and only within the range the arm
# covered in the session, for at least this long and until the arm has joined it.
HANDOVER_S = 1.0


class Switching(SkinValidity):
    """The planners alive, the active one's liveliness, and the switch from one to another."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *,
                 task_range: tuple[np.ndarray, np.ndarray] | None, task_peak_m_s: float, **below: Any) -> None:
        super().__init__(env, q0, now_ns, **below)
        # Switching the active planner.
        self.alive_planners: set[str] = set()
        self.pending: m.SwitchRequest | None = None
        self.handover: m.Handover | None = None
        self.previous_owner = ""
        self.previous_until_ns = 0
        # Where a handover's first motion may go, and whether it is under way:
        # from the switch until the arm has joined the incoming planner's stream
        # (no faster than the task's fastest point, or than the outgoing stream
        # moved the arm if that was faster: no catch-up, no lunge).
        self.reach = Reach(q0, env.joints, task_range)
        self.task_peak_m_s = task_peak_m_s  # the task's own fastest point, m/s (0: unknown)
        self.joining = False
        self.joining_cap = REJOIN_FLOOR_M_S

    def on_planner_alive(self, alive: bool, now_ns: int) -> None:
        """The active planner's liveliness token appeared (True) or vanished (False)."""
        if alive == self.planner_alive:
            return
        self.planner_alive = alive
        if alive:
            self.planner_seen = True
            # A (re)started planner counts its seq from 0 and has sent nothing yet.
            self.last_seq = None
            self.last_command_ns = 0
            if self.tracker.stop is None:
                self.tracker.mode = "none"
            self.events.append(Event("info", "planner_alive", f"planner {self.active!r} is alive"))
        else:
            self.events.append(Event(
                "error", "planner_lost",
                f"planner {self.active!r} lost its liveliness token: decelerating to rest and holding until it is back",
            ))
        self._evaluate(now_ns)

    def on_planner_token(self, name: str, alive: bool, now_ns: int) -> None:
        """Any planner's liveliness token (``name`` is the planner's name)."""
        if alive:
            self.alive_planners.add(name)
        else:
            self.alive_planners.discard(name)
        if name == self.active:
            self.on_planner_alive(alive, now_ns)

    def request_switch(self, request: m.SwitchRequest, now_ns: int) -> bool:
        """Make ``request.name`` the active planner; True if the switch happened now.

        The switch never drops a reflex or its return to the saved pose: it
        waits until the outgoing planner commands its task again (or is not
        commanding at all), then happens between two commands. The incoming
        planner mirrors the arm and the task while inactive, so its first
        command continues the motion.
        """
        name = request.name
        if name == self.active:
            self.pending = None
            self.events.append(Event("info", "switch_noop", f"planner {name!r} is already the active one"))
            return False
        if name not in self.alive_planners:
            self.events.append(Event(
                "warning", "switch_rejected",
                f"switch to planner {name!r} refused: it is not running (alive: {sorted(self.alive_planners)})",
            ))
            return False
        self.pending = request
        self.events.append(Event("info", "switch_requested", f"switch from {self.active!r} to {name!r} requested"
                                 + (f" by {request.requested_by}" if request.requested_by else "")))
        return self._maybe_switch(now_ns)

    def _maybe_switch(self, now_ns: int) -> bool:
        request = self.pending
        if request is None:
            return False
        if request.name not in self.alive_planners:
            self.pending = None
            self.events.append(Event("warning", "switch_rejected",
                                     f"switch to planner {request.name!r} abandoned: it stopped running"))
            return False
        if self.status == "ok" and self.phase != "TASK":
            return False  # a reflex or its return is under way: hand over after it
        previous = self.active
        self.active = request.name
        self.pending = None
        self.handover = m.Handover(previous=previous, owner=request.name, requested_ns=request.stamp_ns,
                                   switched_ns=now_ns)
        self.previous_owner = previous
        self.previous_until_ns = now_ns + PREVIOUS_OWNER_GRACE_NS
        # The incoming planner counts its own seq; its first position target is
        # checked against the stream so far, so the commanded pose cannot jump.
        self.last_seq = None
        self.planner_alive = True
        self.planner_seen = True
        self.joining = True
        self.joining_cap = max(self.tracker.stream_peak, self.task_peak_m_s, REJOIN_FLOOR_M_S)
        self.events.append(Event("info", "switched", f"active planner is now {request.name!r} (was {previous!r})"))
        self.publish_now = True
        return True
