"""Robot bridge core: the supervisor, pure.

Nothing here imports Zenoh or reads a clock: every input carries its time
(``now_ns``), so tests and replays drive it exactly.

:class:`BridgeCore` is the supervisor: every command passes the command check
(:func:`~nwr.services.bridge.checks.check_command`) against the envelope
(:class:`~nwr.services.bridge.envelope.Envelope`), and the accepted ones are
followed by its tracker (:class:`~nwr.services.bridge.tracking.Tracker`),
which gives one setpoint per control cycle within the envelope. The
supervisor watches the inputs (commands, skin, the active planner's
liveliness, the backend's faults), switches the active planner, and, when it
can no longer trust its inputs, has the tracker bring the arm to rest with a
jerk-limited (ruckig) stop whose distance and duration it reports.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.door import ABSOLUTE_HPA, CHANGE_HPA
from nwr.common.errors import ConfigError
from nwr.services.bridge.cartesian import CartesianLimiter, Limits
from nwr.services.bridge.checks import CheckContext, Event, Reach, StateBounds, StateCheck, check_command, command_name
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.limits import REJOIN_FLOOR_M_S
from nwr.services.bridge.tracking import Tracker

# A control step never integrates more than this, s: after a stall of the
# bridge's loop the arm is not teleported along a long step.
MAX_STEP_S = 0.05
# Below this speed (rad/s) on every joint a stopped arm counts as at rest.
REST_SPEED = 1e-6
# After a switch, the outgoing planner's commands are dropped quietly this long
# (it learns of the switch from the next robot state), ns.
PREVIOUS_OWNER_GRACE_NS = 200_000_000
# A handover's first motion, s: the incoming planner's stream is followed no
# faster than the outgoing one moved the arm, and only within the range the arm
# covered in the session, for at least this long and until the arm has joined it.
HANDOVER_S = 1.0
# A state_implausible fault clears once the reports have shown the arm at rest (every joint slower than
# CLEAR_SPEED_RAD_S, rad/s), where the bridge stopped it, for this long, s.
CLEAR_S = 1.0
CLEAR_SPEED_RAD_S = 0.01

# While a pad is blind, it is reported again at most this often, s (a change of the blind pads at once).
BLIND_REPORT_S = 10.0

SetpointMode = Literal["position", "velocity", "hold"]
BlindPolicy = Literal["reduced", "stop"]
# Statuses during which the bridge brings the arm to rest and holds it.
# Reports of a limit the bridge held a command to (a warning, but info in a withdrawal: see _limit_level).
LIMIT_CODES = frozenset({"command_clipped", "joint_limit", "cartesian_limit"})
STOPPING_STATUSES = frozenset({"stale_command", "stale_skin", "planner_lost", "stopped"})


@dataclass(frozen=True)
class Setpoint:
    """What the backend gets for one control cycle."""

    mode: SetpointMode  # "hold": the arm is at rest (backends end their stream)
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    h: float = 0.0  # the step it was computed over, s


@dataclass(frozen=True)
class Verdict:
    accepted: bool
    onset: bool  # the first command of a new reflex: send it to the backend now
    switched: bool = False  # a pending switch of the active planner happened: publish the state now


class BridgeCore:
    """The bridge's supervisor: commands and inputs in, one setpoint per cycle out."""

    def __init__(
        self,
        env: Envelope,
        q0: np.ndarray,
        now_ns: int,
        *,
        active: str,
        n_pads: int,
        command_timeout_s: float = 0.02,
        skin_timeout_s: float = 0.12,
        seq_restart_gap: int = 500,
        period_s: float = 0.002,
        limiter: CartesianLimiter | None = None,
        reduced: Limits | None = None,
        task_range: tuple[np.ndarray, np.ndarray] | None = None,
        task_peak_m_s: float = 0.0,
        physical: tuple[np.ndarray, np.ndarray] | None = None,
        state_bounds: StateBounds | None = None,
        lag_s: float = 0.0,
        pad_names: tuple[str, ...] = (),
        blind_pad_s: float = 0.2,
        blind_pads: BlindPolicy = "reduced",
    ) -> None:
        """``physical``: the robot description's joint speed and acceleration limits (the reports are checked
        against them; default: the envelope's); ``state_bounds``: how far a report may stray
        (:class:`~nwr.services.bridge.checks.StateCheck`); ``lag_s``: the backend's following lag (its servo's
        time constant; 0 for the simulated arm); ``pad_names``: for the reports; ``blind_pad_s``: a pad invalid
        this long is blind; ``blind_pads``: what a blind pad does to the motion (``reduced``: the reduced
        Cartesian limits while any pad is blind; ``stop``: the skin counts as stale, as with no skin data)."""
        q0 = np.asarray(q0, dtype=float)
        if q0.shape != (env.n,):
            raise ConfigError(f"initial pose has {q0.size} joints, the robot has {env.n}")
        if np.any(q0 < env.q_min) or np.any(q0 > env.q_max):
            raise ConfigError(f"initial pose {q0.tolist()} is outside the joint limits of the envelope")
        self.env = env
        self.active = active
        self.n_pads = n_pads
        self.command_timeout_ns = round(command_timeout_s * 1e9)
        self.skin_timeout_ns = round(skin_timeout_s * 1e9)
        self.seq_restart_gap = seq_restart_gap
        # The commanded joint state, the command it follows, the controlled stop.
        self.tracker = Tracker(env, q0, now_ns, period_s=period_s, limiter=limiter)
        # The Cartesian limits of the normal and the reduced mode.
        self.normal_limits = limiter.limits if limiter is not None else None
        self.reduced_limits = reduced
        self.safety_mode: m.SafetyMode = "normal"  # in force: the operator's, or reduced while a pad is blind
        self.operator_mode: m.SafetyMode = "normal"  # as the operator (nwr safety) asked
        # Skin validity: a pad whose readings are invalid (not finite, out of range) since ``invalid_since``
        # for blind_pad_s is blind; a sample without any valid pad is no fresh skin data.
        self.pad_names = pad_names if len(pad_names) == n_pads else tuple(str(i) for i in range(n_pads))
        self.blind_pad_ns = round(blind_pad_s * 1e9)
        self.blind_policy: BlindPolicy = blind_pads
        self.invalid_since: list[int | None] = [None] * n_pads
        self.blind: frozenset[int] = frozenset()
        self.contact_pad = -1  # the strongest contact of the newest pain message (-1: none)
        self.last_step_ns = now_ns
        # The command being followed: its phase, and the last one accepted.
        self.phase: m.Mode = "TASK"
        self.last_seq: int | None = None
        self.last_stamp_ns = 0
        self.last_command_ns = 0
        # Inputs.
        self.planner_alive = False
        self.planner_seen = False
        self.last_skin_ns: int | None = None
        # The planner acts on skin/pain, not on skin/pressure: once pain
        # messages flow, their staleness (a dead gain estimator) stops the task too.
        self.last_pain_ns: int | None = None
        self.fault: m.RobotStatus | None = None
        self.fault_detail = ""
        # The reported joint state is a claim (StateCheck): a report not believed is the bridge's own fault,
        # state_implausible (its reason here), which holds the arm until the reports show it at rest where the
        # bridge stopped it (within ``hold_margin``) for CLEAR_S.
        v_phys, a_phys = physical if physical is not None else (env.v_max, env.a_max)
        self.claims = StateCheck(env.joints, v_phys, a_phys, q0, now_ns, bounds=state_bounds, period_s=period_s,
                                 tau_s=lag_s)
        self.lag_s = lag_s
        self.implausible = ""
        self.hold_q = q0.copy()
        self.hold_margin = np.zeros(env.n)
        self.plausible_since: int | None = None
        # Output state.
        self.status: m.RobotStatus = "idle"
        self.detail = "waiting for the first command"
        self.shutdown = False
        self.rejected = 0
        self.clipped = 0
        self.clipped_expected = 0  # of them, in a withdrawal or while rejoining a stream (see _limit_level)
        self.reflex_seq = 0
        self.accepted: m.Trace | None = None
        self.accepted_ns = 0
        self.events: list[Event] = []
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
        self.publish_now = False  # something others must learn at once (a switch)

    # -- inputs -----------------------------------------------------------------
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
        ctx = CheckContext(self.active, self.planner_alive, q_ref, self.last_seq, self.seq_restart_gap)
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

    def on_skin(self, pressure: m.SkinPressure, now_ns: int) -> None:
        """A skin sample: fresh skin data if it is this robot's skin and has a valid pad; it also tells which
        pads are blind (invalid for ``blind_pad_s``)."""
        if len(pressure.change_hpa) != self.n_pads or len(pressure.contact) != self.n_pads:
            self.events.append(Event(
                "warning", "skin_invalid",
                f"skin sample {pressure.seq} has {len(pressure.change_hpa)} pads, the robot has {self.n_pads}: "
                "it does not count as fresh skin data",
            ))
            return
        valid = pad_validity(pressure, self.n_pads)
        for i, ok in enumerate(valid):
            if ok:
                self.invalid_since[i] = None
            elif self.invalid_since[i] is None:
                self.invalid_since[i] = now_ns
        self._update_blind(now_ns)
        if not any(valid):
            self.events.append(Event(
                "error", "skin_blind",
                f"skin sample {pressure.seq} has no valid pad (every reading not finite or outside "
                f"[{ABSOLUTE_HPA[0]:g}, {ABSOLUTE_HPA[1]:g}] hPa: a skin in Pa, say): it does not count as fresh "
                "skin data",
            ))
            self._evaluate(now_ns)
            return
        self.last_skin_ns = now_ns
        self._evaluate(now_ns)

    def _update_blind(self, now_ns: int) -> None:
        """The pads invalid for blind_pad_s: reported when they change, and at most every BLIND_REPORT_S while
        any is; the reduced limits (or the stop) while any is."""
        blind = frozenset(i for i, since in enumerate(self.invalid_since)
                          if since is not None and now_ns - since >= self.blind_pad_ns)
        if blind == self.blind:
            if blind:
                self.events.append(Event("warning", "skin_blind_pad", self._blind_message(blind),
                                         every_s=BLIND_REPORT_S))
            return
        recovered = self.blind - blind
        self.blind = blind
        if blind:
            self.events.append(Event("warning", "skin_blind_pad", self._blind_message(blind), every_s=0.0))
        if recovered:
            self.events.append(Event("info", "skin_pad_recovered",
                                     f"pad(s) {', '.join(self.pad_names[i] for i in sorted(recovered))} valid again"
                                     + ("" if blind else ": every pad sees again"), every_s=0.0))
        self._apply_safety_mode(now_ns, "blind pads" if blind else "")

    def _blind_message(self, blind: frozenset[int]) -> str:
        what = ("the reduced Cartesian limits while any pad is blind" if self.blind_policy == "reduced"
                else "task and return held (bridge.blind_pads = \"stop\")")
        return (f"{len(blind)} of {self.n_pads} pads blind (invalid for more than {self.blind_pad_ns / 1e6:.0f} ms): "
                f"{', '.join(self.pad_names[i] for i in sorted(blind))}; {what}")

    def on_pain(self, pain: m.SkinPain, now_ns: int) -> None:
        """A pain message: the skin data the planners act on is fresh."""
        if len(pain.gain) != self.n_pads:
            self.events.append(Event(
                "warning", "pain_invalid",
                f"pain message {pain.seq} has {len(pain.gain)} pads, the robot has {self.n_pads}: "
                "it does not count as fresh skin data",
            ))
            return
        self.last_pain_ns = now_ns
        strongest = pain.strongest
        self.contact_pad = strongest.pad if strongest is not None and 0 <= strongest.pad < self.n_pads else -1
        self._evaluate(now_ns)

    def _toward(self) -> np.ndarray | None:
        """The direction toward the newest contact (the touched pad's outward normal, toward the finger), if any."""
        limiter = self.tracker.limiter
        if limiter is None or self.contact_pad < 0:
            return None
        return limiter.model.pad_normal(self.tracker.q, self.contact_pad)

    def set_safety_mode(self, mode: m.SafetyMode, now_ns: int, requested_by: str = "") -> bool:
        """Switch the Cartesian limits to the normal or the reduced set; False if there is nothing to switch
        (while a pad is blind and blind_pads is "reduced", the reduced set stays in force until it sees again)."""
        limiter = self.tracker.limiter
        if limiter is None or self.normal_limits is None or self.reduced_limits is None:
            self.events.append(Event("warning", "safety_mode_rejected",
                                     f"safety mode {mode!r} refused: this bridge has no Cartesian limits"))
            return False
        self.operator_mode = mode
        if mode == "normal" and self.blind and self.blind_policy == "reduced":
            self.events.append(Event("warning", "safety_mode", "safety mode normal requested"
                                     + (f" by {requested_by}" if requested_by else "") + ": the reduced limits stay "
                                     f"while pad(s) {', '.join(self.pad_names[i] for i in sorted(self.blind))} are "
                                     "blind", every_s=0.0))
        return self._apply_safety_mode(now_ns, requested_by)

    def _apply_safety_mode(self, now_ns: int, requested_by: str) -> bool:
        limiter = self.tracker.limiter
        blind_reduced = bool(self.blind) and self.blind_policy == "reduced"
        mode: m.SafetyMode = "reduced" if self.operator_mode == "reduced" or blind_reduced else "normal"
        limits = self.reduced_limits if mode == "reduced" else self.normal_limits
        if limiter is None or limits is None:
            return False
        if mode == self.safety_mode:
            return False
        limiter.limits = limits
        self.safety_mode = mode
        self.publish_now = True
        self.events.append(Event(
            "warning" if mode == "reduced" else "info", "safety_mode",
            f"safety mode {mode}{f' (requested by {requested_by})' if requested_by else ''}: {limits.describe()}",
        ))
        return True

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

    def on_fault(self, fault: m.RobotStatus | None, detail: str, q: np.ndarray, now_ns: int) -> None:
        """The backend's fault (protective stop, ...) or None once it is cleared.

        The controller stops the arm by itself in a fault; the core takes the
        measured pose as its own and waits for fresh commands afterwards.
        """
        if fault == self.fault:
            return
        self.tracker.restart(q)
        self.claims.reset(q, now_ns)
        self.last_command_ns = 0
        if fault is None:
            self.events.append(Event("info", "robot_recovered",
                                     f"robot recovered from {self.fault}: waiting for commands", every_s=0.0))
        else:
            # a change of the controller's state: each one is heard, however soon after the last of its code
            # (a program stopped 0.3 s after an emergency stop's restart, say)
            self.events.append(Event("error", fault, f"robot in {fault}: {detail}", every_s=0.0))
        self.fault = fault
        self.fault_detail = detail
        self._evaluate(now_ns)

    def observe(self, q: np.ndarray, dq: np.ndarray, now_ns: int, stamp_s: float | None = None) -> bool:
        """The reported joint state: checked (:class:`StateCheck`) before anything adopts it.

        A report believed is passed to the tracker (in velocity mode the integrated command follows it); one not
        believed stops the arm (``state_implausible``: the backend's own controlled stop) and holds it until the
        reports show it at rest where the bridge stopped it for CLEAR_S. True: that fault has just cleared and
        the bridge starts over from ``q`` (the backend must resync). ``stamp_s``: the controller's time of the
        report, if it has one (how far apart two reports are, whenever they arrive).
        """
        if self.fault is not None:
            return False
        if self.implausible:
            return self._maybe_clear(np.asarray(q, dtype=float), np.asarray(dq, dtype=float), now_ns)
        why = self.claims.observe(q, dq, now_ns, stamp_s)
        if why is not None:
            self._not_believed(why, now_ns)
            return False
        self.tracker.observe(q)
        return False

    def _not_believed(self, why: str, now_ns: int) -> None:
        claims = self.claims
        self.implausible = why
        self.plausible_since = None
        # Where the arm should come to rest: the backend's controlled stop from the commanded speed (at the
        # slowest joint's a_max, as ur_rtde's servoStop / speedStop), on top of the following error allowed.
        v = claims.speed
        a_stop = float(np.min(self.env.a_max))
        b = claims.bounds
        self.hold_q = claims.expected.copy()
        self.hold_margin = b.error_rad + (b.lag_s + self.lag_s) * v + v * v / (2.0 * a_stop)
        self.events.append(Event("error", "state_implausible",
                                 f"the robot's reported state is not believed: {why}: stopping the arm (the "
                                 "controller's own stop) and holding it until the reports show it at rest where "
                                 "it was stopped", every_s=0.0))
        self._evaluate(now_ns)

    def _maybe_clear(self, q: np.ndarray, dq: np.ndarray, now_ns: int) -> bool:
        """While ``state_implausible``: clear it once the reports have shown the arm at rest near where it was
        stopped for CLEAR_S."""
        ok = (q.shape == self.hold_q.shape and dq.shape == self.hold_q.shape and bool(np.isfinite(q).all())
              and bool(np.isfinite(dq).all()) and not (np.abs(dq) > CLEAR_SPEED_RAD_S).any()
              and not (np.abs(q - self.hold_q) > self.hold_margin).any())
        if not ok:
            self.plausible_since = None
            return False
        if self.plausible_since is None:
            self.plausible_since = now_ns
        if now_ns - self.plausible_since < round(CLEAR_S * 1e9):
            return False
        self.events.append(Event("info", "state_plausible",
                                 f"the robot's reported state is believed again (at rest, within "
                                 f"{float(np.max(np.abs(q - self.hold_q))):.4f} rad of where it was stopped, for "
                                 f"{CLEAR_S:g} s): waiting for commands", every_s=0.0))
        self.implausible = ""
        self.plausible_since = None
        self.tracker.restart(q)
        self.claims.reset(q, now_ns)
        self.last_command_ns = 0
        self._evaluate(now_ns)
        return True

    def request_stop(self, now_ns: int, reason: str) -> None:
        """Stop for good (shutdown): a controlled stop, then hold."""
        self.shutdown = True
        self.detail = reason
        self._evaluate(now_ns)

    # -- status -------------------------------------------------------------------
    def skin_age_s(self, now_ns: int) -> float:
        return -1.0 if self.last_skin_ns is None else (now_ns - self.last_skin_ns) / 1e9

    def _evaluate(self, now_ns: int) -> None:
        """Set the status from the inputs; start a controlled stop on entering a stopping one."""
        pain_stale = self.last_pain_ns is not None and now_ns - self.last_pain_ns > self.skin_timeout_ns
        skin_stale = self.last_skin_ns is None or now_ns - self.last_skin_ns > self.skin_timeout_ns or pain_stale
        status: m.RobotStatus
        if self.fault is not None:
            status, detail = self.fault, self.fault_detail
        elif self.implausible:
            status, detail = "state_implausible", self.implausible
        elif self.shutdown:
            status, detail = "stopped", self.detail or "stopped"
        elif not self.planner_alive and self.planner_seen:
            status, detail = "planner_lost", f"planner {self.active!r} lost its liveliness token"
        elif not self.planner_alive or self.last_command_ns == 0:
            status = "idle"
            detail = (f"waiting for planner {self.active!r}" if not self.planner_alive
                      else "waiting for the first command")
        elif now_ns - self.last_command_ns - self.tracker.covered_ns > self.command_timeout_ns:
            status = "stale_command"
            detail = f"no command for more than {self.command_timeout_ns / 1e6:.0f} ms"
            if self.tracker.covered_ns:
                detail += f" past the {self.tracker.covered_ns / 1e6:.0f} ms the last one planned ahead"
        elif (skin_stale or (self.blind and self.blind_policy == "stop")) and self.phase != "REFLEX":
            status = "stale_skin"
            if not skin_stale:
                pads = ", ".join(self.pad_names[i] for i in sorted(self.blind))
                age = f"pad(s) {pads} blind (bridge.blind_pads = stop)"
            elif self.last_skin_ns is None:
                age = "no skin data yet"
            elif pain_stale and self.last_pain_ns is not None and now_ns - self.last_skin_ns <= self.skin_timeout_ns:
                age = f"pain data {(now_ns - self.last_pain_ns) / 1e6:.0f} ms old (is the gain estimator running?)"
            else:
                age = f"skin data {(now_ns - self.last_skin_ns) / 1e6:.0f} ms old"
            detail = f"{age} (limit {self.skin_timeout_ns / 1e6:.0f} ms): {self.phase} motion held"
        else:
            status, detail = "ok", ""
        if status != self.status:
            tracker = self.tracker
            moving = bool(np.any(np.abs(tracker.dq) > REST_SPEED))
            if status in STOPPING_STATUSES or (status == "idle" and moving):
                failed = tracker.begin_stop(now_ns)
                if failed is not None:
                    self.events.append(failed)
                if status != "stopped":
                    # Before the first skin sample the skin is starting (the gateway starts last): not a fault.
                    starting = status == "stale_skin" and self.last_skin_ns is None
                    self.events.append(Event(
                        "info" if starting else "warning", status,
                        f"{detail}: decelerating to rest within the limits (stopping distance up to "
                        f"{float(np.max(np.abs(tracker.stop_distance))):.4f} rad, {tracker.stop_time_s:.3f} s) "
                        "and holding",
                    ))
            elif status == "ok" and tracker.stop is not None:
                tracker.stop = None  # follow again, from wherever the stop has brought the arm
                tracker.begin_rejoin()  # ... and never faster than the stream itself: no catch-up
                if self.status != "idle":
                    self.events.append(Event("info", "resumed", f"following {self.active!r} again after {self.status}"))
        self.status, self.detail = status, detail

    # -- the control cycle -----------------------------------------------------------
    def step(self, now_ns: int) -> Setpoint:
        """One control cycle at ``now_ns``: the setpoint within the envelope."""
        h = min(max((now_ns - self.last_step_ns) / 1e9, 0.0), MAX_STEP_S)
        self.last_step_ns = max(now_ns, self.last_step_ns)
        self._evaluate(now_ns)
        self._maybe_switch(now_ns)  # a pending switch while the outgoing planner is not commanding
        if h <= 0.0:
            return self._setpoint(0.0)
        tracker = self.tracker
        q_before = tracker.q.copy()
        if self.fault is not None or self.implausible:
            tracker.hold()
        elif tracker.stop is not None:
            tracker.stop_step(now_ns, h)
        elif self.status == "ok":
            clipped = tracker.track(h, self.last_step_ns, self.active)
            if clipped is not None:
                self._report_clip(clipped)
            if self.joining and self.handover is not None and self.handover.first_command_ns and not tracker.rejoining:
                self.joining = False  # the arm follows the incoming planner's stream
        else:
            tracker.hold()
        if not self.joining:  # the first motion of a handover does not widen where it may go
            self.reach.add(tracker.q)
        setpoint = self._setpoint(h)
        self.claims.command(setpoint.mode, q_before, setpoint.q, setpoint.dq, now_ns)
        return setpoint

    def _setpoint(self, h: float) -> Setpoint:
        tracker = self.tracker
        at_rest = not (np.abs(tracker.dq) > REST_SPEED).any()
        stopped = tracker.stop is None or tracker.stop.done
        if self.fault is not None or self.implausible or (self.status != "ok" and stopped and at_rest):
            mode: SetpointMode = "hold"
        elif tracker.mode == "velocity":
            mode = "velocity"
        else:
            mode = "position"
        return Setpoint(mode, tracker.q.copy(), tracker.dq.copy(), tracker.ddq.copy(), h)

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

    # -- output -----------------------------------------------------------------------
    def state(self, seq: int, now_ns: int, q: np.ndarray, dq: np.ndarray, backend: str,
              pose_stale: bool = False) -> m.RobotState:
        """The robot state to publish, with the measured joints ``q`` and ``dq`` (``pose_stale``: the last known)."""
        self.publish_now = False
        tracker = self.tracker
        return m.RobotState(
            seq=seq, stamp_ns=now_ns, q=q.tolist(), dq=dq.tolist(), status=self.status, owner=self.active,
            backend=backend, command_mode=tracker.mode, reflex_seq=self.reflex_seq, accepted=self.accepted,
            accepted_ns=self.accepted_ns, rejected=self.rejected, clipped=self.clipped,
            stopping=tracker.stop is not None and not tracker.stop.done, stop_distance=tracker.stop_distance.tolist(),
            stop_time_s=tracker.stop_time_s, skin_age_s=min(self.skin_age_s(now_ns), 1e9), detail=self.detail,
            pending_owner=self.pending.name if self.pending is not None else "", handover=self.handover,
            safety_mode=self.safety_mode, limited=tracker.limited,
            phase="REFLEX" if tracker.withdrawal else self.phase, pose_stale=pose_stale,
        )

    def release(self) -> None:
        """Drop the trajectory generator at shutdown (its objects must not outlive their module)."""
        self.tracker.release()

    def drain_events(self) -> list[Event]:
        events, self.events = self.events, []
        return events


def pad_validity(pressure: m.SkinPressure, n_pads: int) -> list[bool]:
    """Per pad, whether its reading is valid: the gateway's own flag (a non-finite reading; all valid when the
    sample has none), and within what a pad can report (absolute and change, hPa: a skin read in Pa is not)."""
    lo, hi = ABSOLUTE_HPA
    flags = pressure.valid if len(pressure.valid) == n_pads else [True] * n_pads
    valid = [bool(ok) and lo <= a <= hi and abs(c) <= CHANGE_HPA
             for ok, a, c in zip(flags, pressure.absolute_hpa, pressure.change_hpa, strict=False)]
    return valid + [False] * (n_pads - len(valid))  # a pad the sample does not cover is not valid


def at_rest(dq: np.ndarray) -> bool:
    return not bool((np.abs(dq) > REST_SPEED).any())

