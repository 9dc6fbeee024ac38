"""Robot bridge core: the safety envelope and the supervisor, both pure.

Nothing here imports Zenoh or reads a clock: every input carries its time
(``now_ns``), so tests and replays drive it exactly.

- :class:`Envelope` holds the joint limits the bridge enforces: the robot
  description's, scaled by the profile's fractions and tightened by its
  per-joint lists (never loosened).
- :func:`check_command` is the one pure function every command passes. It
  *rejects* what cannot be trusted or has no safe nearest value (wrong owner,
  planner not alive, wrong length or mode, non-finite numbers, a duplicated or
  out-of-order seq, a position target that jumps away from the arm) and
  *clips* what has an obvious safe nearest value (a position target past a
  joint limit, a joint velocity above its limit). It returns what it accepted
  and one :class:`Event` per rejection or clip, naming the value, the limit
  and the sender.
- :class:`BridgeCore` is the supervisor: it turns accepted commands into one
  setpoint per control cycle within the envelope (speed, acceleration and
  braking distance to the joint limits), watches the inputs (commands, skin,
  the active planner's liveliness, the backend's faults) and, when it can no
  longer trust them, brings the arm to rest with a jerk-limited (ruckig) stop
  whose distance and duration it reports.

Clip or reject, per case (docs/bridge.md explains them for operators):

==========================================  ========  ===========================================
case                                        action    why
==========================================  ========  ===========================================
owner is not the active planner             reject    only one process may move the arm
active planner has no liveliness token      reject    a dead planner's name is free to spoof
wrong kind / phase / number of joints       reject    no meaningful nearest command exists
NaN or infinity                             reject    (also rejected by the decoder)
seq duplicated or out of order              reject    a replayed or reordered stream is stale
position target jumps > position_jump_rad  reject    the sender lost track of the arm
position target beyond a joint limit        clip      the limit is the nearest safe target
joint velocity above its limit              clip      scaled uniformly: the direction is kept
implied speed / acceleration of a stream    clip      the tracker follows at the limit
approaching a joint limit too fast          clip      speed bounded by the braking distance
==========================================  ========  ===========================================
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass, field
from typing import Literal

import msgspec
import numpy as np
from ruckig import ControlInterface, InputParameter, Result, Ruckig, Trajectory

from nwr.common import messages as m
from nwr.common.errors import ConfigError

# A control step never integrates more than this, s: after a stall of the
# bridge's loop the arm is not teleported along a long step.
MAX_STEP_S = 0.05
# Bounds of the estimated period of a planner's position stream, s.
MIN_PERIOD_S = 0.0005
MAX_PERIOD_S = 0.05
# A command planned ahead may cover at most this long, s: the bridge notices a
# dead planner at most this much later than with one command per cycle.
MAX_AHEAD_S = 0.1
# Relative tolerance before an implied speed counts as a clip (rounding).
SPEED_TOLERANCE = 1.01
# The bridge's and the planner's loops are not synchronised: a velocity
# step of up to this many control cycles' worth of acceleration is jitter,
# not a clip worth reporting (the tracker shapes it all the same).
ACCEL_JITTER_CYCLES = 2.0
# Below this speed (rad/s) on every joint a stopped arm counts as at rest.
REST_SPEED = 1e-6
# After a switch, the outgoing planner's commands are dropped quietly this long
# (it learns of the switch from the next robot state), ns.
PREVIOUS_OWNER_GRACE_NS = 200_000_000

Level = Literal["info", "warning", "error"]
SetpointMode = Literal["position", "velocity", "hold"]
# Statuses during which the bridge brings the arm to rest and holds it.
STOPPING_STATUSES = frozenset({"stale_command", "stale_skin", "planner_lost", "stopped"})
FAULT_STATUSES = frozenset({"protective_stop", "emergency_stop", "script_not_running", "disconnected"})


@dataclass(frozen=True)
class Event:
    """Something the adapter reports on diag/bridge (and logs)."""

    level: Level
    code: str
    message: str


# --------------------------------------------------------------------------- envelope


@dataclass(frozen=True, eq=False)
class Envelope:
    """Per-joint limits the bridge enforces, rad, rad/s, rad/s^2, rad/s^3."""

    joints: tuple[str, ...]
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray
    j_max: np.ndarray
    position_jump_rad: float = 0.1  # from the stream's last target, or the arm's pose when a stream starts

    @property
    def v_min(self) -> np.ndarray:
        """``-v_max``, computed once (the tracker and the guard need it every cycle)."""
        cached = self.__dict__.get("_v_min")
        if cached is None:
            cached = -self.v_max
            cached.setflags(write=False)
            object.__setattr__(self, "_v_min", cached)
        return cached

    @property
    def n(self) -> int:
        return len(self.joints)

    @property
    def per_joint(self) -> tuple[tuple[float, float, float, float, float], ...]:
        """(q_min, q_max, v_max, a_max, k) of each joint as floats, computed once.

        ``k = a_max / (2 j_max)`` as in :meth:`braking_speed`. The tracker's
        per-cycle arithmetic runs on these: on six joints, plain float
        arithmetic costs a fraction of numpy's per-call overhead, and gives the
        same IEEE double results.
        """
        cached = self.__dict__.get("_per_joint")
        if cached is None:
            k = self.a_max / (2.0 * self.j_max)
            cached = tuple(zip(self.q_min.tolist(), self.q_max.tolist(), self.v_max.tolist(), self.a_max.tolist(),
                               k.tolist()))
            object.__setattr__(self, "_per_joint", cached)
        return cached

    def describe(self) -> str:
        """The envelope as a table, printed when the bridge starts."""
        rows = [f"{'joint':<22s} {'q_min':>8s} {'q_max':>8s} {'v_max':>7s} {'a_max':>7s} {'j_max':>7s}"]
        for i, name in enumerate(self.joints):
            rows.append(
                f"{name:<22s} {self.q_min[i]:8.3f} {self.q_max[i]:8.3f} {self.v_max[i]:7.3f} "
                f"{self.a_max[i]:7.2f} {self.j_max[i]:7.1f}"
            )
        rows.append(f"position targets farther than {self.position_jump_rad} rad from the arm are rejected")
        return "\n".join(rows)

    def braking_speed(self, distance: np.ndarray) -> np.ndarray:
        """Highest speed from which a jerk-limited stop ends within ``distance``.

        Solves v^2 / (2 a) + v a / (2 j) = d: the distance of a stop from
        constant speed that ramps its deceleration up to a at the jerk limit.
        """
        d = np.maximum(distance, 0.0)
        a, k = self.a_max, self.a_max / (2.0 * self.j_max)
        return a * (np.sqrt(k**2 + 2.0 * d / a) - k)


def make_envelope(
    joints: tuple[str, ...],
    description: dict[str, np.ndarray],
    *,
    speed_fraction: float = 1.0,
    acceleration_fraction: float = 1.0,
    jerk_fraction: float = 1.0,
    tighter: dict[str, list[float]] | None = None,
    position_jump_rad: float = 0.1,
) -> Envelope:
    """The envelope from the robot description's limits and the profile's tightening.

    ``description`` holds ``q_min``, ``q_max``, ``v_max``, ``a_max``, ``j_max``.
    ``tighter`` may hold the same names (empty lists = keep the description's);
    a value looser than the description's raises :class:`ConfigError`.
    """
    n = len(joints)
    fractions = {"v_max": speed_fraction, "a_max": acceleration_fraction, "j_max": jerk_fraction}
    limits: dict[str, np.ndarray] = {}
    for name in ("q_min", "q_max", "v_max", "a_max", "j_max"):
        base = np.asarray(description[name], dtype=float).copy()
        if base.shape != (n,):
            raise ConfigError(f"robot description: {name} has {base.size} values, the robot has {n} joints")
        value = base * fractions.get(name, 1.0)
        given = (tighter or {}).get(name) or []
        if given:
            extra = np.asarray(given, dtype=float)
            if extra.shape != (n,) or not np.all(np.isfinite(extra)):
                raise ConfigError(f"bridge.{name} must have {n} finite values (one per joint), got {given}")
            looser = extra < base if name == "q_min" else extra > base
            if np.any(looser):
                i = int(np.argmax(looser))
                raise ConfigError(
                    f"bridge.{name}[{i}] = {extra[i]} is looser than the robot description's {base[i]} "
                    f"for {joints[i]}: the profile may only tighten the limits"
                )
            value = np.maximum(value, extra) if name == "q_min" else np.minimum(value, extra)
        limits[name] = value
    if np.any(limits["q_min"] >= limits["q_max"]):
        i = int(np.argmax(limits["q_min"] >= limits["q_max"]))
        raise ConfigError(f"bridge: q_min {limits['q_min'][i]} >= q_max {limits['q_max'][i]} for {joints[i]}")
    for name in ("v_max", "a_max", "j_max"):
        if np.any(limits[name] <= 0):
            raise ConfigError(f"bridge.{name} must be positive for every joint, got {limits[name].tolist()}")
    for value in limits.values():
        value.setflags(write=False)
    return Envelope(joints, position_jump_rad=position_jump_rad, **limits)


# --------------------------------------------------------------------------- the command check


@dataclass(frozen=True)
class CheckContext:
    """What :func:`check_command` needs to know about the bridge."""

    active: str  # the only owner whose commands may move the arm
    alive: bool  # the active planner's liveliness token is present
    q_ref: np.ndarray  # the pose the bridge currently commands
    last_seq: int | None  # seq of the last accepted command, None after a (re)start
    seq_restart_gap: int = 500


@dataclass
class Checked:
    """The outcome of :func:`check_command`: the values to use, or a rejection."""

    values: np.ndarray | None  # clipped q (position) or dq (velocity); None if rejected
    events: list[Event] = field(default_factory=list)
    rejected: bool = False
    clipped: bool = False
    restarted: bool = False  # the sender's seq fell back: a restarted planner
    ahead: np.ndarray | None = None  # clipped setpoints planned ahead (rows), None if none


def _name(cmd: object) -> str:
    return f"{type(cmd).__name__} {getattr(cmd, 'seq', '?')} from {getattr(cmd, 'owner', '?')!r}"


def check_command(cmd: object, env: Envelope, ctx: CheckContext) -> Checked:
    """Check one command against the envelope: reject, clip or pass it (pure)."""

    def reject(code: str, why: str) -> Checked:
        return Checked(None, [Event("warning", code, f"{_name(cmd)} rejected: {why}")], rejected=True)

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
            out.ahead = _clip(points, env.q_min, env.q_max)
            if not (out.ahead == points).all():
                out.events.append(Event("warning", "command_clipped",
                                        f"{_name(cmd)}: setpoints ahead beyond the joint limits: clipped to them"))
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
        clipped = _clip(values, env.q_min, env.q_max)
        if not (clipped == values).all():
            i = int(np.argmax(np.abs(clipped - values)))
            side = "q_max" if values[i] > env.q_max[i] else "q_min"
            limit = env.q_max[i] if side == "q_max" else env.q_min[i]
            out.events.append(Event(
                "warning", "command_clipped",
                f"{_name(cmd)}: joint {env.joints[i]} target {values[i]:.4f} rad beyond {side} {limit:.4f} rad: "
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
                f"{_name(cmd)}: joint {env.joints[i]} speed {values[i]:.4f} rad/s above v_max {env.v_max[i]:.4f} "
                f"rad/s: all joints scaled by {1 / worst:.3f} (the direction is kept)",
            ))
            out.clipped = True
            out.values = values / worst
    return out


# --------------------------------------------------------------------------- the supervisor


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


@dataclass
class _Stop:
    trajectory: Trajectory | None  # None: ruckig failed, constant-deceleration fallback
    start_ns: int
    q0: np.ndarray
    distance: np.ndarray
    duration_s: float
    done: bool = False


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
    ) -> None:
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
        self.period_s = period_s  # the control period, s
        n = env.n
        # The commanded joint state (what the backend was last sent).
        self.q = q0.copy()
        self.dq = np.zeros(n)
        self.ddq = np.zeros(n)
        self.last_step_ns = now_ns
        # The command being followed.
        self.mode: Literal["none", "position", "velocity"] = "none"
        self.phase: m.Mode = "TASK"
        self.target = q0.copy()  # q (position) or dq (velocity)
        self.v_ff = np.zeros(n)  # feed-forward velocity of a position stream
        self.target_ns = now_ns
        # A position command planned ahead: its setpoints (rows, the first at
        # target_ns, one every plan_period_s), their speeds, how long they reach.
        self.plan: np.ndarray | None = None
        self.plan_v = np.zeros((0, n))
        self.plan_period_s = 0.0
        self.covered_ns = 0
        self.periods: deque[float] = deque(maxlen=15)
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
        # Output state.
        self.status: m.RobotStatus = "idle"
        self.detail = "waiting for the first command"
        self.stop: _Stop | None = None
        self.stop_distance = np.zeros(n)
        self.stop_time_s = 0.0
        self.shutdown = False
        self.rejected = 0
        self.clipped = 0
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
        self.publish_now = False  # something others must learn at once (a switch)
        self._clip_reported = False  # the tracker's clip of the current command was reported
        self._otg = Ruckig(n)
        self._otg_in = InputParameter(n)
        self._otg_in.control_interface = ControlInterface.Velocity
        self._otg_in.max_velocity = env.v_max.tolist()
        self._otg_in.max_acceleration = env.a_max.tolist()
        self._otg_in.max_jerk = env.j_max.tolist()
        self._otg_in.target_velocity = [0.0] * n
        self._otg_in.target_acceleration = [0.0] * n

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
            self.rejected += 1
            self.events.append(Event("error", "command_spoofed",
                                     f"{_name(cmd)} rejected: it came on robot/command/{publisher} but claims owner "
                                     f"{cmd.owner!r}: a planner may command only under its own name"))
            return Verdict(False, False)
        if cmd.owner == self.previous_owner and cmd.owner != self.active and now_ns < self.previous_until_ns:
            # The outgoing planner has not seen the switch yet: expected, not hostile.
            self.rejected += 1
            return Verdict(False, False)
        # A running position stream must continue from its own last target
        # (the arm may lag it while the bridge limits it); anything else must
        # start from where the bridge has the arm.
        streaming = self.mode == "position" and self.status == "ok"
        q_ref = (self._planned(now_ns)[0] if self.plan is not None else self.target) if streaming else self.q
        ctx = CheckContext(self.active, self.planner_alive, q_ref, self.last_seq, self.seq_restart_gap)
        checked = check_command(cmd, self.env, ctx)
        self.events.extend(checked.events)
        if checked.rejected or checked.values is None:
            self.rejected += 1
            return Verdict(False, False)
        if checked.clipped:
            self.clipped += 1
        if checked.restarted:
            self.events.append(Event("info", "command_seq_restart",
                                     f"{_name(cmd)}: seq fell back from {self.last_seq}: a restarted planner"))
        if self.fault is not None:
            # The controller stopped the arm; nothing moves until the fault is cleared.
            self.events.append(Event("warning", "command_ignored",
                                     f"{_name(cmd)} not sent: the robot is in {self.fault} ({self.fault_detail})"))
            return Verdict(False, False)
        if isinstance(cmd, m.PositionCommand):
            self._follow_position(cmd, checked.values, now_ns, checked.ahead)
        else:
            self.mode = "velocity"
            self.target = checked.values
            self.v_ff = np.zeros(self.env.n)
            self.plan = None
            self.covered_ns = 0
        self.phase = cmd.phase
        self._clip_reported = False
        self.last_seq = cmd.seq
        self.last_stamp_ns = cmd.stamp_ns
        self.last_command_ns = now_ns
        onset = cmd.phase == "REFLEX" and cmd.reflex_seq != self.reflex_seq
        self.reflex_seq = cmd.reflex_seq
        if onset:
            self.accepted = cmd.trace
            self.accepted_ns = now_ns
        if self.handover is not None and self.handover.first_command_ns == 0 and cmd.owner == self.handover.owner:
            self.handover = msgspec.structs.replace(self.handover, first_command_ns=now_ns)
            self.events.append(Event(
                "info", "handover_done",
                f"planner {self.handover.owner!r} moves the arm: "
                f"{(now_ns - self.handover.requested_ns) / 1e6:.1f} ms after the request",
            ))
        self._evaluate(now_ns)
        switched = self._maybe_switch(now_ns)
        return Verdict(True, onset, switched)

    def _follow_position(self, cmd: m.PositionCommand, q: np.ndarray, now_ns: int, ahead: np.ndarray | None) -> None:
        env = self.env
        v_ff = np.zeros(env.n)
        gap = cmd.seq - self.last_seq if self.last_seq is not None else 0
        if ahead is not None:
            self._follow_plan(cmd, q, ahead, now_ns)
            return
        if self.mode == "position" and self.plan is not None:
            # After a plan, a stream of one command per cycle (a reflex) carries
            # on at the plan's speed until its own period is measured.
            v_ff = self._planned(now_ns)[1].copy()
            self.periods.clear()
        elif self.mode == "position" and 1 <= gap <= 10 and cmd.stamp_ns > self.last_stamp_ns:
            # The stream's own period (median of its stamp steps, robust to the
            # jitter of both loops) turns successive targets into a velocity.
            self.periods.append((cmd.stamp_ns - self.last_stamp_ns) / gap / 1e9)
            # statistics.median: the same value as np.median, without its overhead on 15 numbers.
            period = min(max(float(statistics.median(self.periods)), MIN_PERIOD_S), MAX_PERIOD_S)
            v_ff = self._at_the_limit(cmd, ((q - self.target) / (gap * period))[None, :], "position stream moves")[0]
        elif self.mode != "position":
            self.periods.clear()
        self.mode = "position"
        self.target = q
        self.v_ff = v_ff
        self.target_ns = now_ns
        self.plan = None
        self.covered_ns = 0

    def _follow_plan(self, cmd: m.PositionCommand, q: np.ndarray, ahead: np.ndarray, now_ns: int) -> None:
        """A position command planned ahead: its setpoints, one every ``cmd.period_s`` from now."""
        plan = np.vstack([q, ahead])
        period = cmd.period_s
        v = self._at_the_limit(cmd, np.diff(plan, axis=0) / period, "planned to move")
        self.periods.clear()
        self.mode = "position"
        self.target = q
        self.v_ff = v[0]
        self.target_ns = now_ns
        self.plan, self.plan_v, self.plan_period_s = plan, v, period
        self.covered_ns = round(len(ahead) * period * 1e9)

    def _at_the_limit(self, cmd: m.PositionCommand, v: np.ndarray, what: str) -> np.ndarray:
        """Joint velocities (one row per step) scaled down to v_max where faster; the worst is reported once."""
        env = self.env
        ratio = (np.abs(v) / env.v_max).max(axis=1)
        worst = float(ratio.max())
        if worst > SPEED_TOLERANCE:
            k = int(np.argmax(ratio))
            i = int(np.argmax(np.abs(v[k]) / env.v_max))
            self.events.append(Event(
                "warning", "command_clipped",
                f"{_name(cmd)}: joint {env.joints[i]} {what} at {v[k, i]:.3f} rad/s, "
                f"v_max {env.v_max[i]:.3f} rad/s: followed at the limit",
            ))
            self.clipped += 1
        return v / np.maximum(ratio, 1.0)[:, None] if worst > 1.0 else v

    def _planned(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The plan's target and feed-forward velocity at ``t_ns``: interpolated, or extrapolated past its end."""
        plan, v = self.plan, self.plan_v
        assert plan is not None
        x = max((t_ns - self.target_ns) / 1e9, 0.0) / self.plan_period_s  # in periods
        k = int(x)
        last = len(plan) - 1
        if k < last:
            return plan[k] + (plan[k + 1] - plan[k]) * (x - k), v[k]
        # Past the last setpoint (the next command is late): on at the last speed, briefly.
        over = min((x - last) * self.plan_period_s, MAX_PERIOD_S)
        return _clip(plan[last] + v[last - 1] * over, self.env.q_min, self.env.q_max), v[last - 1]

    def on_skin(self, pressure: m.SkinPressure, now_ns: int) -> None:
        """A skin sample: fresh skin data (if it is this robot's skin)."""
        if len(pressure.change_hpa) != self.n_pads or len(pressure.contact) != self.n_pads:
            self.events.append(Event(
                "warning", "skin_invalid",
                f"skin sample {pressure.seq} has {len(pressure.change_hpa)} pads, the robot has {self.n_pads}: "
                "it does not count as fresh skin data",
            ))
            return
        self.last_skin_ns = now_ns
        self._evaluate(now_ns)

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
        self._evaluate(now_ns)

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
            self.mode = "none" if self.stop is None else self.mode
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
        self.q = np.asarray(q, dtype=float).copy()
        self.dq[:] = 0.0
        self.ddq[:] = 0.0
        self.stop = None
        self.mode = "none"
        self.last_command_ns = 0
        if fault is None:
            self.events.append(Event("info", "robot_recovered",
                                     f"robot recovered from {self.fault}: waiting for commands"))
        else:
            self.events.append(Event("error", fault, f"robot in {fault}: {detail}"))
        self.fault = fault
        self.fault_detail = detail
        self._evaluate(now_ns)

    def observe(self, q: np.ndarray) -> None:
        """The measured pose; in velocity mode the integrated command follows it."""
        if self.mode == "velocity" and self.stop is None and self.fault is None:
            self.q = np.asarray(q, dtype=float).copy()

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
        elif self.shutdown:
            status, detail = "stopped", self.detail or "stopped"
        elif not self.planner_alive and self.planner_seen:
            status, detail = "planner_lost", f"planner {self.active!r} lost its liveliness token"
        elif not self.planner_alive or self.last_command_ns == 0:
            status = "idle"
            detail = (f"waiting for planner {self.active!r}" if not self.planner_alive
                      else "waiting for the first command")
        elif now_ns - self.last_command_ns - self.covered_ns > self.command_timeout_ns:
            status = "stale_command"
            detail = f"no command for more than {self.command_timeout_ns / 1e6:.0f} ms"
            if self.covered_ns:
                detail += f" past the {self.covered_ns / 1e6:.0f} ms the last one planned ahead"
        elif skin_stale and self.phase != "REFLEX":
            status = "stale_skin"
            if self.last_skin_ns is None:
                age = "no skin data yet"
            elif pain_stale and self.last_pain_ns is not None and now_ns - self.last_skin_ns <= self.skin_timeout_ns:
                age = f"pain data {(now_ns - self.last_pain_ns) / 1e6:.0f} ms old (is the gain estimator running?)"
            else:
                age = f"skin data {(now_ns - self.last_skin_ns) / 1e6:.0f} ms old"
            detail = f"{age} (limit {self.skin_timeout_ns / 1e6:.0f} ms): {self.phase} motion held"
        else:
            status, detail = "ok", ""
        if status != self.status:
            moving = bool(np.any(np.abs(self.dq) > REST_SPEED))
            if status in STOPPING_STATUSES or (status == "idle" and moving):
                self._begin_stop(now_ns)
                if status != "stopped":
                    self.events.append(Event(
                        "warning", status,
                        f"{detail}: decelerating to rest within the limits (stopping distance up to "
                        f"{float(np.max(np.abs(self.stop_distance))):.4f} rad, {self.stop_time_s:.3f} s) and holding",
                    ))
            elif status == "ok" and self.stop is not None:
                self.stop = None  # follow again, from wherever the stop has brought the arm
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
        if self.fault is not None:
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
        elif self.stop is not None:
            self._stop_step(now_ns, h)
        elif self.status == "ok":
            self._track(h)
        else:
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
        return self._setpoint(h)

    def _setpoint(self, h: float) -> Setpoint:
        at_rest = not (np.abs(self.dq) > REST_SPEED).any()
        if self.fault is not None or (self.status != "ok" and (self.stop is None or self.stop.done) and at_rest):
            mode: SetpointMode = "hold"
        elif self.mode == "velocity":
            mode = "velocity"
        else:
            mode = "position"
        return Setpoint(mode, self.q.copy(), self.dq.copy(), self.ddq.copy(), h)

    def _track(self, h: float) -> None:
        env = self.env
        if self.mode == "position":
            if self.plan is not None:
                target, v_ff = self._planned(self.last_step_ns)
            else:
                ahead = min((self.last_step_ns - self.target_ns) / 1e9, MAX_PERIOD_S)
                target = _clip(self.target + self.v_ff * max(ahead, 0.0), env.q_min, env.q_max)
                v_ff = self.v_ff
            self._limit(v_ff.tolist(), h, target.tolist())
            return
        if self.mode == "velocity":
            v_des = self.target.copy()
            jump = np.abs(v_des - self.dq) / (env.a_max * max(h, self.period_s))
            if float(np.max(jump)) > ACCEL_JITTER_CYCLES and not self._clip_reported:
                i = int(np.argmax(jump))
                self._report_clip(
                    "command_clipped",
                    f"velocity command from {self.active!r}: joint {env.joints[i]} asks for {v_des[i]:.3f} rad/s "
                    f"from {self.dq[i]:.3f} rad/s, a_max {env.a_max[i]:.2f} rad/s^2: ramped at the limit",
                )
        else:
            v_des = np.zeros(env.n)
        self._limit(v_des.tolist(), h)

    def _limit(self, v_des: list[float], h: float, target: list[float] | None = None) -> None:
        """Integrate one cycle towards ``v_des`` within the envelope (per joint, in floats).

        With a position ``target``, ``v_des`` is its feed-forward velocity, plus
        a correction that can always brake in time: no overshoot on a step, no
        lag on a smooth stream. Then the speed limit; never faster towards a
        joint limit than a jerk-limited stop allows (:meth:`Envelope.braking_speed`,
        the same formula); the acceleration limit; the joint limits.
        """
        q0, dq0 = self.q.tolist(), self.dq.tolist()
        q1, v1, a1 = [], [], []
        bound_i, bound_by, bound_v = -1, 1e-9, 0.0  # the joint the braking distance bounds most (reported once)
        for i, (q_min, q_max, v_max, a_max, k) in enumerate(self.env.per_joint):
            q, dq = q0[i], dq0[i]
            v = v_des[i]
            if target is not None:
                e = target[i] - q
                correction = min(abs(e) / h, math.sqrt(2.0 * a_max * abs(e)))
                v = v + correction if e >= 0.0 else v - correction
            v = min(max(v, -v_max), v_max)
            d = max(q_max - q, 0.0)
            v_hi = a_max * (math.sqrt(k * k + 2.0 * d / a_max) - k)
            d = max(q - q_min, 0.0)
            v_lo = -(a_max * (math.sqrt(k * k + 2.0 * d / a_max) - k))
            bounded = min(max(v, v_lo), v_hi)
            if abs(bounded - v) > bound_by:
                bound_i, bound_by, bound_v = i, abs(bounded - v), bounded
            v_des[i] = v
            v = min(max(bounded, dq - a_max * h), dq + a_max * h)
            q1.append(min(max(q + 0.5 * (dq + v) * h, q_min), q_max))
            v1.append(v)
            a1.append((v - dq) / h)
        if bound_i >= 0 and not self._clip_reported:
            env, i = self.env, bound_i
            self._report_clip(
                "joint_limit",
                f"{self.mode} command from {self.active!r}: joint {env.joints[i]} at {q0[i]:.4f} rad approaches "
                f"its limit [{env.q_min[i]:.3f}, {env.q_max[i]:.3f}] at {v_des[i]:.3f} rad/s: speed bounded to "
                f"{bound_v:.3f} rad/s (the braking distance)",
            )
        self.q, self.dq, self.ddq = np.array(q1), np.array(v1), np.array(a1)

    def _report_clip(self, code: str, message: str) -> None:
        """Count and report a clip of the tracker once per command (not per cycle)."""
        self._clip_reported = True
        self.clipped += 1
        self.events.append(Event("warning", code, message))

    def _begin_stop(self, now_ns: int) -> None:
        env = self.env
        n = env.n
        inp = self._otg_in
        inp.current_position = self.q.tolist()
        inp.current_velocity = np.clip(self.dq, -env.v_max, env.v_max).tolist()
        inp.current_acceleration = np.clip(self.ddq, -env.a_max, env.a_max).tolist()
        trajectory: Trajectory | None = Trajectory(n)
        result = self._otg.calculate(inp, trajectory)
        if result in (Result.Working, Result.Finished):
            assert trajectory is not None
            end, _, _ = trajectory.at_time(trajectory.duration)
            distance = np.asarray(end) - self.q
            duration = float(trajectory.duration)
        else:
            # Constant deceleration at the acceleration limit, per joint: never
            # happens with valid limits, but a stop must never fail.
            trajectory = None
            distance = self.dq * np.abs(self.dq) / (2.0 * env.a_max)
            duration = float(np.max(np.abs(self.dq) / env.a_max))
            self.events.append(Event("error", "stop_fallback",
                                     f"ruckig could not plan the stop ({result}): constant deceleration instead"))
        self.stop = _Stop(trajectory, now_ns, self.q.copy(), distance, duration)
        self.stop_distance = distance
        self.stop_time_s = duration

    def _stop_step(self, now_ns: int, h: float) -> None:
        stop = self.stop
        assert stop is not None
        env = self.env
        t = (now_ns - stop.start_ns) / 1e9
        if stop.done:
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            return
        if t >= stop.duration_s:
            stop.done = True
            q = stop.q0 + stop.distance
            self.q = np.clip(q, env.q_min, env.q_max)
            self.dq[:] = 0.0
            self.ddq[:] = 0.0
            return
        if stop.trajectory is not None:
            q, dq, ddq = stop.trajectory.at_time(t)
            q, dq, ddq = np.asarray(q), np.asarray(dq), np.asarray(ddq)
        else:
            dq = np.sign(self.dq) * np.maximum(np.abs(self.dq) - env.a_max * h, 0.0)
            ddq = (dq - self.dq) / h
            q = self.q + 0.5 * (self.dq + dq) * h
        self.q = np.clip(q, env.q_min, env.q_max)
        self.dq, self.ddq = dq, ddq

    # -- output -----------------------------------------------------------------------
    def state(self, seq: int, now_ns: int, q: np.ndarray, dq: np.ndarray, backend: str) -> m.RobotState:
        """The robot state to publish, with the measured joints ``q`` and ``dq``."""
        self.publish_now = False
        return m.RobotState(
            seq=seq, stamp_ns=now_ns, q=q.tolist(), dq=dq.tolist(), status=self.status, owner=self.active,
            backend=backend, command_mode=self.mode, reflex_seq=self.reflex_seq, accepted=self.accepted,
            accepted_ns=self.accepted_ns, rejected=self.rejected, clipped=self.clipped,
            stopping=self.stop is not None and not self.stop.done, stop_distance=self.stop_distance.tolist(),
            stop_time_s=self.stop_time_s, skin_age_s=min(self.skin_age_s(now_ns), 1e9), detail=self.detail,
            pending_owner=self.pending.name if self.pending is not None else "", handover=self.handover,
        )

    def release(self) -> None:
        """Drop the trajectory generator at shutdown (its objects must not outlive their module)."""
        self._otg = self._otg_in = None
        if self.stop is not None:
            self.stop.trajectory = None

    def drain_events(self) -> list[Event]:
        events, self.events = self.events, []
        return events


def at_rest(dq: np.ndarray) -> bool:
    return not bool((np.abs(dq) > REST_SPEED).any())


def _clip(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``np.clip(a, lo, hi)`` for ``lo <= hi``, as the two ufuncs it is made of.

    The same values (np.clip is defined as this), without the dispatch
    overhead that dominates on six joints in every 2 ms cycle.
    """
    return np.minimum(np.maximum(a, lo), hi)

