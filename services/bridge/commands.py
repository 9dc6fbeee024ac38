"""Command acceptance: a planner's command checked, and followed if accepted.

Every command passes the command check
(:func:`~.checks.check_command`: the owner, the seq, the joints, the jump,
the envelope) against the pose it must continue from: a running position
stream's own last target, otherwise where the bridge has the arm. Refused
besides: a command whose owner field names another planner than the key it
came on (``command_spoofed``), a handover's first motion toward a pose the
arm was never at (``handover_refused``: :mod:`.switching`), and, quietly,
the outgoing planner's commands just after a switch. Nothing is sent while
the robot is in a fault (:mod:`.faults`). The first command of a new reflex
is the onset: sent to the backend at once and published with its trace.

:class:`Commands` owns the seq and stamp of the last command accepted, the
reflex followed and its onset, and the counts of the commands rejected and
clipped; a limit met is reported as a warning, or as info where the
envelope shapes the motion as designed (:meth:`Commands._limit_level`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.checks import CheckContext, Event, check_command, command_name
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.faults import Faults
from nwr.services.bridge.switching import HANDOVER_S

# Reports of a limit the bridge held a command to (a warning, but info in a withdrawal: see _limit_level).
LIMIT_CODES = frozenset({"command_clipped", "joint_limit", "cartesian_limit"})


@dataclass(frozen=True)
class Verdict:
    accepted: bool
    onset: bool  # the first command of a new reflex: send it to the backend now
    switched: bool = False  # a pending switch of the active planner happened: publish the state now


class Commands(Faults):
    """The commands: checked, followed or refused, counted; the reflex followed and its onset."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, seq_restart_gap: int, **below: Any) -> None:
        super().__init__(env, q0, now_ns, **below)
        self.seq_restart_gap = seq_restart_gap
        self.last_stamp_ns = 0  # of the last command accepted (its seq: ``last_seq``)
        self.rejected = 0
        self.clipped = 0
        self.clipped_expected = 0  # of them, in a withdrawal or while rejoining a stream (see _limit_level)
        self.reflex_seq = 0
        self.accepted: m.Trace | None = None
        self.accepted_ns = 0

    def on_command(self, cmd: m.Command, now_ns: int, *, publisher: str | None = None) -> Verdict:
        """A command from robot/command/<publisher>: checked, and followed if accepted.

        ``publisher`` is the planner whose key the command came on (only that
        planner's certificate may put there); a command whose owner field
        names another planner is refused, whoever it names. None: an
        in-process caller (lockstep, tests), where the owner field is all
        there is.
        """
        if publisher is not None and cmd.owner != publisher:
            return self._reject("command_spoofed",
                                f"{command_name(cmd)} rejected: it came on robot/command/{publisher} but claims owner "
                                f"{cmd.owner!r}: a planner may command only under its own name")
        if cmd.owner == self.previous_owner and cmd.owner != self.active and now_ns < self.previous_until_ns:
            # The outgoing planner has not seen the switch yet: expected, not hostile.
            self.rejected += 1
            return Verdict(False, False)
        # A running position stream must continue from its own last target
        # (the arm may lag it while the bridge limits it); anything else must
        # start from where the bridge has the arm.
        tracker = self.tracker
        streaming = tracker.mode == "position" and self.status == "ok"
        q_ref = (tracker.planned(now_ns)[0] if tracker.plan is not None else tracker.target) if streaming else tracker.q
        ctx = CheckContext(self.active, self.planner_alive, q_ref, self.last_seq, self.seq_restart_gap,
                           now_ns - self.last_command_ns)
        checked = check_command(cmd, self.env, ctx)
        self.events.extend(self._limit_level(e, "in a withdrawal" if cmd.phase == "REFLEX" else "")
                           for e in checked.events)
        if checked.rejected or checked.values is None:
            self.rejected += 1
            return Verdict(False, False)
        if checked.clipped:
            self.clipped += 1
            self.clipped_expected += cmd.phase == "REFLEX"
        if checked.restarted:
            self.events.append(Event("info", "command_seq_restart",
                                     f"{command_name(cmd)}: seq fell back from {self.last_seq}: a restarted planner"))
        if self.joining and cmd.phase != "REFLEX" and isinstance(cmd, m.PositionCommand):
            poses = checked.values if checked.ahead is None else np.vstack([checked.values, checked.ahead])
            outside = self.reach.outside(poses)
            if outside is not None:
                return self._reject("handover_refused",
                                    f"{command_name(cmd)} rejected: the first motion after the switch to "
                                    f"{cmd.owner!r} moves {outside}: a pose the arm was never at, off the task's path")
        if self.fault is not None or self.implausible:
            # The controller stopped the arm (or the bridge did, not believing its reports); nothing moves until
            # the fault is cleared.
            fault = self.fault or "state_implausible"
            self.events.append(Event(
                "warning", "command_ignored",
                f"{command_name(cmd)} not sent: the robot is in {fault} ({self.fault_detail or self.implausible})",
            ))
            return Verdict(False, False)
        onset = cmd.phase == "REFLEX" and cmd.reflex_seq != self.reflex_seq
        if onset:
            tracker.toward = self._toward()  # into the contact, fixed at the onset
            # A withdrawal is never slowed to a stream's speed, and it ends a handover's first motion:
            # the reflex and its return are the planner's answer to a contact, not a claim.
            tracker.rejoining = False
            self.joining = False
        tracker.reflex = cmd.phase == "REFLEX"
        tracker.withdrawal = tracker.withdrawal or tracker.reflex
        if isinstance(cmd, m.PositionCommand):
            clipped = tracker.follow_position(cmd, checked.values, now_ns, checked.ahead, self.last_seq,
                                              self.last_stamp_ns)
            if clipped is not None:
                self._report_clip(clipped)
        else:
            tracker.follow_velocity(checked.values, cmd, now_ns, self.last_seq, self.last_stamp_ns)
        self.phase = cmd.phase
        self.last_seq = cmd.seq
        self.last_stamp_ns = cmd.stamp_ns
        self.last_command_ns = now_ns
        self.reflex_seq = cmd.reflex_seq
        if onset:
            self.accepted = cmd.trace
            self.accepted_ns = now_ns
        if self.handover is not None and self.handover.first_command_ns == 0 and cmd.owner == self.handover.owner:
            self.handover = msgspec.structs.replace(self.handover, first_command_ns=now_ns)
            if self.joining:  # the incoming stream, joined no faster than the task, for HANDOVER_S at least
                tracker.begin_rejoin(cap=self.joining_cap, cycles=round(HANDOVER_S / tracker.period_s))
            self.events.append(Event(
                "info", "handover_done",
                f"planner {self.handover.owner!r} moves the arm: "
                f"{(now_ns - self.handover.requested_ns) / 1e6:.1f} ms after the request",
            ))
        self._evaluate(now_ns)
        switched = self._maybe_switch(now_ns)
        return Verdict(True, onset, switched)

    def _reject(self, code: str, message: str) -> Verdict:
        """A command refused as hostile or misled: counted and reported as an error."""
        self.rejected += 1
        self.events.append(Event("error", code, message))
        return Verdict(False, False)

    def _report_clip(self, event: Event) -> None:
        """Count and report a clip the tracker made."""
        tracker = self.tracker
        why = "in a withdrawal" if tracker.withdrawal else "rejoining the stream" if tracker.rejoining else \
            "catching up with the stream, itself within the limits" \
            if event.code == "cartesian_limit" and tracker.catching_up else ""
        self.clipped += 1
        self.clipped_expected += bool(why)
        self.events.append(self._limit_level(event, why))

    @staticmethod
    def _limit_level(event: Event, why: str) -> Event:
        """A limit met in a withdrawal, or while the bridge rejoins a stream after a hold (at its own rejoin
        speed), is the envelope shaping the motion as designed: info (counted). Elsewhere the planner asked
        for more than the envelope allows: a warning."""
        if why and event.code in LIMIT_CODES and event.level == "warning":
            return Event("info", event.code, f"{event.message} ({why})")
        return event
