"""The bridge's command check: every command passes :func:`check_command`, pure.

It *rejects* what cannot be trusted or has no safe nearest value (wrong
owner, planner not alive, wrong length or mode, non-finite numbers, a
duplicated or out-of-order seq, a position target that jumps away from the
arm) and *clips* what has an obvious safe nearest value (a position target
past a joint limit, a joint velocity above its limit). It returns what it
accepted and one :class:`Event` per rejection or clip, naming the value, the
limit and the sender.

Clip or reject, per case (docs/bridge.md explains them for operators; the
last two rows are the tracker's, :mod:`.tracking`):

==========================================  ========  ===========================================
case                                        action    why
==========================================  ========  ===========================================
owner is not the active planner             reject    only one process may move the arm
active planner has no liveliness token      reject    a dead planner's name is free to spoof
wrong kind / phase / number of joints       reject    no meaningful nearest command exists
NaN or infinity                             reject    (also rejected by the decoder)
seq duplicated or out of order              reject    a replayed or reordered stream is stale
seq further ahead than the time allows      reject    no planner counts that fast: a forged seq
position target jumps > position_jump_rad  reject    the sender lost track of the arm
position target beyond a joint limit        clip      the limit is the nearest safe target
joint velocity above its limit              clip      scaled uniformly: the direction is kept
implied speed / acceleration of a stream    clip      the tracker follows at the limit
approaching a joint limit too fast          clip      speed bounded by the braking distance
==========================================  ========  ===========================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.envelope import Envelope, clip

# Bounds of the estimated period of a planner's position stream, s.
MIN_PERIOD_S = 0.0005
MAX_PERIOD_S = 0.05
# A command planned ahead may cover at most this long, s: the bridge notices a
# dead planner at most this much later than with one command per cycle.
MAX_AHEAD_S = 0.1
# How far a command's seq may run ahead of the last one accepted: SEQ_SLACK, plus MAX_COMMAND_RATE_HZ times the
# time since it (a planner numbers its commands one by one, 500 a second by default). A seq further ahead is no
# planner's next command: accepting it would make the planner's own commands "out of order" until it caught up
# (one forged seq 450 ahead cost 450 rejected commands, and a stop); it is rejected and changes nothing.
SEQ_SLACK = 20
MAX_COMMAND_RATE_HZ = 2000.0

Level = Literal["info", "warning", "error"]


@dataclass(frozen=True)
class Event:
    """Something the adapter reports on diag/bridge (and logs)."""

    level: Level
    code: str
    message: str
    every_s: float = 1.0  # repeats of the code within this are counted, not sent (0: a change of state, always sent)


@dataclass(frozen=True)
class CheckContext:
    """What :func:`check_command` needs to know about the bridge."""

    active: str  # the only owner whose commands may move the arm
    alive: bool  # the active planner's liveliness token is present
    q_ref: np.ndarray  # the pose the bridge currently commands
    last_seq: int | None  # seq of the last accepted command, None after a (re)start
    seq_restart_gap: int = 500
    since_last_ns: int = 0  # since the last accepted command (its seq: last_seq)


@dataclass
class Checked:
    """The outcome of :func:`check_command`: the values to use, or a rejection."""

    values: np.ndarray | None  # clipped q (position) or dq (velocity); None if rejected
    events: list[Event] = field(default_factory=list)
    rejected: bool = False
    clipped: bool = False
    restarted: bool = False  # the sender's seq fell back: a restarted planner
    ahead: np.ndarray | None = None  # clipped setpoints planned ahead (rows), None if none


def command_name(cmd: object) -> str:
    """The command as events name it: kind, seq and sender."""
    return f"{type(cmd).__name__} {getattr(cmd, 'seq', '?')} from {getattr(cmd, 'owner', '?')!r}"


def check_command(cmd: object, env: Envelope, ctx: CheckContext) -> Checked:
    """Check one command against the envelope: reject, clip or pass it (pure)."""

    def reject(code: str, why: str) -> Checked:
        return Checked(None, [Event("warning", code, f"{command_name(cmd)} rejected: {why}")], rejected=True)

    if not isinstance(cmd, (m.PositionCommand, m.VelocityCommand)):
        return reject("command_invalid", f"a {type(cmd).__name__} is not a joint command")
    if cmd.owner != ctx.active:
        return reject(
            "command_rejected",
            f"sender {cmd.owner!r} is not the active planner {ctx.active!r} "
            "(set bridge.active_planner or --active to follow another)",
        )
    if not ctx.alive:
        return reject(
            "command_rejected",
            f"the active planner {ctx.active!r} has no liveliness token (not started, or lost): "
            "start it, the bridge follows once its token is back",
        )
    if cmd.phase not in m.MODES:
        return reject("command_invalid", f"phase {cmd.phase!r} is not one of {m.MODES}")
    position = isinstance(cmd, m.PositionCommand)
    raw = cmd.q if position else cmd.dq  # type: ignore[union-attr]
    if len(raw) != env.n:
        return reject("command_invalid", f"{len(raw)} joint values, the robot has {env.n} joints")
    values = np.asarray(raw, dtype=float)
    if not np.isfinite(values).all():
        return reject("command_invalid", f"non-finite values {raw}")
    restarted = False
    if ctx.last_seq is not None and cmd.seq <= ctx.last_seq:
        if ctx.last_seq - cmd.seq < ctx.seq_restart_gap:
            kind = "duplicated" if cmd.seq == ctx.last_seq else "out of order"
            return reject("command_out_of_order", f"seq {cmd.seq} is {kind} (last accepted {ctx.last_seq})")
        restarted = True
    elif ctx.last_seq is not None:
        most = ctx.last_seq + SEQ_SLACK + int(max(ctx.since_last_ns, 0) * MAX_COMMAND_RATE_HZ / 1e9)
        if cmd.seq > most:
            return reject("command_seq_jump",
                          f"seq {cmd.seq} is {cmd.seq - ctx.last_seq} ahead of the last accepted ({ctx.last_seq}) "
                          f"{max(ctx.since_last_ns, 0) / 1e6:.1f} ms ago, more than a planner counts in that time "
                          f"(at most {most}): not the planner's next command")

    out = Checked(values, restarted=restarted)
    if position:
        ahead = cmd.ahead  # type: ignore[union-attr]
        if ahead:
            period = cmd.period_s  # type: ignore[union-attr]
            if not MIN_PERIOD_S <= period <= MAX_PERIOD_S:
                return reject("command_invalid", f"period_s {period} of its setpoints ahead is outside "
                                                 f"[{MIN_PERIOD_S}, {MAX_PERIOD_S}] s")
            if len(ahead) * period > MAX_AHEAD_S + 1e-9:
                return reject("command_invalid", f"{len(ahead)} setpoints ahead at {period} s cover more than "
                                                 f"{MAX_AHEAD_S} s")
            if any(len(row) != env.n for row in ahead):
                return reject("command_invalid", f"a setpoint ahead does not have {env.n} joint values")
            points = np.asarray(ahead, dtype=float)
            if not np.isfinite(points).all():
                return reject("command_invalid", "non-finite values in its setpoints ahead")
            step = np.abs(np.diff(np.vstack([values, points]), axis=0))
            if (step > env.position_jump_rad).any():
                k, i = (int(x) for x in np.unravel_index(int(np.argmax(step)), step.shape))
                return reject(
                    "command_jump",
                    f"joint {env.joints[i]} setpoint {k + 1} ahead moves {step[k, i]:.4f} rad in one step, "
                    f"limit {env.position_jump_rad} rad",
                )
            out.ahead = clip(points, env.q_min, env.q_max)
            if not (out.ahead == points).all():
                out.events.append(Event(
                    "warning", "command_clipped",
                    f"{command_name(cmd)}: setpoints ahead beyond the joint limits: clipped to them",
                ))
                out.clipped = True
        jump = np.abs(values - ctx.q_ref)
        if (jump > env.position_jump_rad).any():
            i = int(np.argmax(jump))
            return reject(
                "command_jump",
                f"joint {env.joints[i]} target {values[i]:.4f} rad is {jump[i]:.4f} rad from the commanded "
                f"{ctx.q_ref[i]:.4f} rad, limit {env.position_jump_rad} rad "
                "(resynchronise the planner from robot/state)",
            )
        clipped = clip(values, env.q_min, env.q_max)
        if not (clipped == values).all():
            i = int(np.argmax(np.abs(clipped - values)))
            side = "q_max" if values[i] > env.q_max[i] else "q_min"
            limit = env.q_max[i] if side == "q_max" else env.q_min[i]
            out.events.append(Event(
                "warning", "command_clipped",
                f"{command_name(cmd)}: joint {env.joints[i]} target {values[i]:.4f} rad beyond {side} {limit:.4f} rad: "
                "clipped to the limit",
            ))
            out.clipped = True
            out.values = clipped
    else:
        ratio = np.abs(values) / env.v_max
        worst = float(np.max(ratio))
        if worst > 1.0:
            i = int(np.argmax(ratio))
            out.events.append(Event(
                "warning", "command_clipped",
                f"{command_name(cmd)}: joint {env.joints[i]} speed {values[i]:.4f} rad/s above v_max "
                f"{env.v_max[i]:.4f} rad/s: all joints scaled by {1 / worst:.3f} (the direction is kept)",
            ))
            out.clipped = True
            out.values = values / worst
    return out


class Reach:
    """The range each joint covered in this session, and the task path's: where a handover's first motion may go.

    After a switch, the incoming planner's motion (other than a withdrawal)
    must stay within the range each joint was commanded to in the session
    so far, widened by the task's own range (its amplitudes around home)
    and ``margin``: a planner misled into a pose the arm was never at is
    refused before it moves. The range is per joint (a box, which holds the
    straight line between any two poses in it): the planners check the poses
    themselves against what they measured (:mod:`nwr.services.planner.claims`).
    """

    def __init__(self, q0: np.ndarray, joints: tuple[str, ...], task: tuple[np.ndarray, np.ndarray] | None = None,
                 margin: float = 0.1) -> None:
        self.joints = joints
        self.lo = np.array(q0, dtype=float)
        self.hi = np.array(q0, dtype=float)
        self.task = task
        self.margin = margin
        if task is not None:
            self.add(task[0])
            self.add(task[1])

    def add(self, q: np.ndarray) -> None:
        np.minimum(self.lo, q, out=self.lo)
        np.maximum(self.hi, q, out=self.hi)

    def outside(self, poses: np.ndarray) -> str | None:
        """Why a pose of ``poses`` (one, or rows) lies outside the range, or None."""
        rows = np.atleast_2d(poses)
        beyond = np.maximum(self.lo - self.margin - rows, rows - self.hi - self.margin)
        if not (beyond > 0.0).any():
            return None
        k, i = (int(x) for x in np.unravel_index(int(np.argmax(beyond)), beyond.shape))
        value = float(rows[k, i])
        return (f"joint {self.joints[i]} to {value:.4f} rad, outside [{self.lo[i]:.3f}, {self.hi[i]:.3f}] "
                f"(the range it covered in this session{' and the task' if self.task is not None else ''}) by more "
                f"than {self.margin} rad")



# A report that stops changing is frozen once the commands have moved a joint this far since, rad.
FROZEN_MOTION_RAD = 1e-3
# A controller whose own clock (the reports' stamps) stands still this many times ``frozen_s`` has stopped
# reporting, whatever the commands do (an arm commanded nearly still included); longer than the frozen check's
# limit, so that a loaded machine's late report is no alarm.
STILL_CLOCK_FACTOR = 3.0


@dataclass(frozen=True)
class StateBounds:
    """How far the backend's reported joint state may stray before it is not believed (profile: bridge.*)."""

    error_rad: float = 0.05  # following error beyond the lag model, rad
    lag_s: float = 0.05  # ... plus this times the commanded joint speed, rad per rad/s
    jump_rad: float = 0.01  # a report may move a joint the description's v_max times the time since the last, plus this
    speed_jump_rad_s: float = 0.2  # ... and change its speed a_max times that time, plus this
    frozen_s: float = 0.1  # a report unchanged this long while the commands move is frozen


class StateCheck:
    """The backend's reported joint state is a claim: checked every cycle against the commands and physics (pure).

    The bridge keeps its own model of where the arm should be: the pose it
    commanded (position setpoints), or the displacement it commanded
    (velocity setpoints, integrated), followed with the backend's first-order
    lag ``tau_s`` (ur_rtde's servoJ; 0 for the simulated arm). Each report
    must be finite, within ``error_rad + lag_s * |commanded speed|`` of the
    model (the following error), move each joint no farther than the robot
    description's ``v_max`` allows since the last report (plus ``jump_rad``)
    and change its speed no more than ``a_max`` allows (plus
    ``speed_jump_rad_s``), and change at all within ``frozen_s`` while the
    commands move; a controller that stamps its reports must advance its
    clock within ``STILL_CLOCK_FACTOR * frozen_s``, moving or not (both timed while the bridge observes: a gap
    longer than ``frozen_s`` between two observations, the bridge itself stopped or starved, starts them
    afresh). :meth:`observe` returns why a report is not believed, naming the joint and the size, or None.
    """

    def __init__(self, joints: tuple[str, ...], v_max: np.ndarray, a_max: np.ndarray, q0: np.ndarray, now_ns: int,
                 *, bounds: StateBounds | None = None, period_s: float = 0.002, tau_s: float = 0.0) -> None:
        self.joints = joints
        self.v_max = np.asarray(v_max, dtype=float)
        self.a_max = np.asarray(a_max, dtype=float)
        self.bounds = bounds if bounds is not None else StateBounds()
        self.period_s = period_s
        self.tau_s = tau_s
        self.reset(q0, now_ns)

    def reset(self, q: np.ndarray, now_ns: int) -> None:
        """Start over at rest at ``q`` (the arm's pose after a fault, or at start)."""
        q = np.asarray(q, dtype=float)
        self.commanded = q.copy()  # the pose commanded (integrated in velocity mode)
        self.expected = q.copy()  # where the arm should be: the commanded pose through the lag
        self.speed = np.zeros_like(q)  # the commanded joint speed
        self.mode = "hold"
        self.t_ns = now_ns  # the time of ``expected``
        self.last_q: np.ndarray | None = None
        self.last_dq: np.ndarray | None = None
        self.last_ns = now_ns  # when the last distinct report was first seen
        self.last_stamp: float | None = None  # and the controller's time of it
        self.frozen_ns: int | None = None  # since when the reports have not changed
        self.frozen_at = q.copy()  # the commanded pose when they stopped changing
        self.clock_stamp: float | None = None  # the controller's newest stamp
        self.clock_ns = now_ns  # when it was first seen
        self.seen_ns = now_ns  # the last observation

    def _advance(self, now_ns: int) -> None:
        h = (now_ns - self.t_ns) / 1e9
        if h <= 0.0:
            return
        self.t_ns = now_ns
        if self.mode != "velocity":
            if self.tau_s > 0.0:
                self.expected += (self.commanded - self.expected) * (1.0 - math.exp(-h / self.tau_s))
            else:
                self.expected[:] = self.commanded

    def command(self, mode: str, q_before: np.ndarray, q: np.ndarray, dq: np.ndarray, now_ns: int) -> None:
        """The setpoint the bridge sent at ``now_ns`` (``q_before``: the commanded pose before the cycle)."""
        self._advance(now_ns)
        if mode == "velocity":
            step = q - q_before  # the displacement commanded: never the measured pose itself
            self.commanded += step
            self.expected += step
        else:
            self.commanded = np.array(q, dtype=float)
        self.speed = np.abs(dq)
        self.mode = mode

    def observe(self, q: np.ndarray, dq: np.ndarray, now_ns: int, stamp_s: float | None = None) -> str | None:
        """Why the report (``q``, ``dq``) at ``now_ns`` is not believed, or None.

        How far apart two reports are: the controller's own times (``stamp_s``) where it gives them, else the
        time between their first sightings on the bridge's clock (a report seen again is not a new one: a
        stream that arrives late, then in a burst, is not taken for a jump).
        """
        b = self.bounds
        joints = self.joints
        q = np.asarray(q, dtype=float)
        dq = np.asarray(dq, dtype=float)
        if q.shape != self.commanded.shape or dq.shape != self.commanded.shape:
            return f"the backend reported {q.size} joint positions and {dq.size} speeds, the robot has " \
                   f"{self.commanded.size} joints"
        if not (np.isfinite(q).all() and np.isfinite(dq).all()):
            i = int(np.argmin(np.isfinite(q) & np.isfinite(dq)))
            return f"joint {joints[i]} reported a non-finite position or speed (q {q[i]}, dq {dq[i]})"
        self._advance(now_ns)
        if now_ns - self.seen_ns > b.frozen_s * 1e9:
            # The bridge itself was not looking (stopped, hung, starved): how long a report stood meanwhile says
            # nothing of the controller; the frozen and still-clock checks count from now.
            self.clock_ns = now_ns
            if self.frozen_ns is not None:
                self.frozen_ns = now_ns
        self.seen_ns = now_ns
        why = None
        # As floats: np.array_equal's dispatch costs more than six comparisons (the shapes are the same, the
        # values finite).
        unchanged = (self.last_q is not None and self.last_dq is not None and q.tolist() == self.last_q.tolist()
                     and dq.tolist() == self.last_dq.tolist())
        if self.last_q is not None and self.last_dq is not None and not unchanged:
            if stamp_s is not None and self.last_stamp is not None:
                dt = max(stamp_s - self.last_stamp, self.period_s)
            else:
                dt = max((now_ns - self.last_ns) / 1e9, self.period_s)
            step = np.abs(q - self.last_q) - (self.v_max * dt + b.jump_rad)
            if (step > 0.0).any():
                i = int(np.argmax(step))
                why = (f"joint {joints[i]} jumped {abs(q[i] - self.last_q[i]):.4f} rad in {dt * 1e3:.1f} ms "
                       f"(physically at most {self.v_max[i] * dt + b.jump_rad:.4f} rad)")
            else:
                kick = np.abs(dq - self.last_dq) - (self.a_max * dt + b.speed_jump_rad_s)
                if (kick > 0.0).any():
                    i = int(np.argmax(kick))
                    why = (f"joint {joints[i]} speed jumped {abs(dq[i] - self.last_dq[i]):.3f} rad/s in "
                           f"{dt * 1e3:.1f} ms (physically at most {self.a_max[i] * dt + b.speed_jump_rad_s:.3f} "
                           "rad/s)")
        if unchanged:
            if self.frozen_ns is None:
                self.frozen_ns = self.last_ns
                self.frozen_at = self.commanded.copy()
            moved = np.abs(self.commanded - self.frozen_at)
            if (now_ns - self.frozen_ns) / 1e9 >= b.frozen_s and (moved > FROZEN_MOTION_RAD).any():
                i = int(np.argmax(moved))
                why = (f"the reported state has not changed for {(now_ns - self.frozen_ns) / 1e6:.0f} ms while "
                       f"joint {joints[i]} was commanded {moved[i]:.4f} rad on (limit {b.frozen_s * 1e3:.0f} ms): "
                       "a frozen stream")
        else:
            self.frozen_ns = None
        if stamp_s is not None and stamp_s != self.clock_stamp:
            self.clock_stamp, self.clock_ns = stamp_s, now_ns
        elif stamp_s is not None and why is None and (now_ns - self.clock_ns) / 1e9 >= STILL_CLOCK_FACTOR * b.frozen_s:
            why = (f"the controller's clock has stood at {stamp_s:.3f} s for {(now_ns - self.clock_ns) / 1e6:.0f} ms "
                   f"(limit {STILL_CLOCK_FACTOR * b.frozen_s * 1e3:.0f} ms): its reports have stopped")
        if why is None:
            error = np.abs(q - self.expected) - (b.error_rad + b.lag_s * self.speed)
            if (error > 0.0).any():
                i = int(np.argmax(error))
                why = (f"joint {joints[i]} reported {q[i]:.4f} rad, {q[i] - self.expected[i]:+.4f} rad from where "
                       f"the bridge commanded it ({self.expected[i]:.4f} rad; limit "
                       f"{b.error_rad + b.lag_s * self.speed[i]:.4f} rad)")
        if not unchanged:
            self.last_q, self.last_dq, self.last_ns, self.last_stamp = q, dq, now_ns, stamp_s
        return why
