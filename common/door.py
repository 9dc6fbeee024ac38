"""The door: every decoded message is checked for its meaning before any core sees it; pure.

The decoder (:mod:`nwr.common.keys`) refuses what is not a message of the
key's type; the door refuses what is one but cannot be true of this robot
and this pipeline: a pad index outside the pad file, a joint vector of the
wrong length or far outside the robot description's ranges, a sequence
number or a stamp that the wire schema (64-bit) or the recording format
(MCAP's 32-bit sequence) cannot hold, a pain level outside 1-4, a gain
outside [0, 1], a name that no service could have, a robot state that does
not continue the bridge's own stream. :meth:`Door.refuse` names the cause in
one short phrase (what a diagnostic counts it under) and the value.

Everything a service reads from the network passes one door
(:meth:`nwr.common.node.Node.subscribe`); only the recorder, which keeps
what travelled, bypasses it.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.robot import RobotDescription, load_description
from nwr.common.skin import hpa_per_unit, load_skin
from nwr.common.taxels import TaxelSkin

SEQ_LIMIT = 2**32  # MCAP's message sequence is a uint32
STAMP_LIMIT = 2**63  # int64 nanoseconds, as msgpack and the recording's log times carry them
NAME = re.compile(r"^[a-z][a-z0-9_-]{0,31}$")  # a service's, a planner's or a strategy's name
# A joint position this far outside the robot description's range cannot be measured, rad.
JOINT_MARGIN_RAD = 0.2
# A joint speed this much above the description's limit cannot be measured (its overshoot), ratio.
SPEED_MARGIN = 1.5
# Pressures an AIRSKIN pad can report, hPa (absolute, and change from its baseline).
ABSOLUTE_HPA = (0.0, 5000.0)
CHANGE_HPA = 2000.0
# A taxel contact's point lies on its link's skin: within this of the link's origin (the UR10e's tubes are 0.6 m).
MAX_REACH_M = 2.0
LEVELS = (1, 4)
# A robot state's pose may move from the last one of the stream by at most the
# joint speed limits over the time between their stamps, plus this, rad.
STREAM_SLACK_RAD = 0.05
# After this long without a state that continues the stream, any valid state starts a new one, s.
STREAM_RESTART_S = 1.0


@dataclass
class Refusal:
    cause: str  # short and stable: what a diagnostic counts it under
    detail: str  # the value, readable

    def __str__(self) -> str:
        return f"{self.cause}: {self.detail}"


class Door:
    """Semantic checks of every decoded message, against one robot description (see the module docstring)."""

    def __init__(self, desc: RobotDescription, skin: TaxelSkin | None = None) -> None:
        self.desc = desc
        self.n = len(desc.joints)
        self.n_pads = len(desc.pads)
        # A skin sample's entries: one per taxel on a taxel skin (robot.skin = "taxels"), else one per pad.
        self.n_entries = len(skin) if skin is not None else self.n_pads
        self.links = frozenset(skin.links) if skin is not None else frozenset()
        self.hpa_per_unit = hpa_per_unit(skin) if skin is not None else 1.0
        self.q_lo = np.asarray(desc.q_min) - JOINT_MARGIN_RAD
        self.q_hi = np.asarray(desc.q_max) + JOINT_MARGIN_RAD
        self.v_top = np.asarray(desc.v_max) * SPEED_MARGIN
        # The same bounds as Python floats: a check of six values per message is cheaper without numpy.
        self._q_bounds = list(zip(self.q_lo.tolist(), self.q_hi.tolist()))
        self._v_top = self.v_top.tolist()
        self._state: tuple[int, int, list[float]] | None = None  # the stream's last (seq, stamp, q)
        self._checks: dict[type, Callable[[Any], Refusal | None]] = {
            m.SkinPressure: self._pressure,
            m.SkinPain: self._pain,
            m.SkinTouch: self._touch,
            m.WorldSkin: self._world_skin,
            m.PositionCommand: self._position,
            m.VelocityCommand: self._velocity,
            m.RobotState: self._robot_state,
            m.PlannerStatus: self._status,
            m.PlannerDecision: self._decision,
            m.SwitchRequest: self._switch,
            m.SafetyModeRequest: self._safety,
            m.Diagnostic: self._diagnostic,
        }

    @classmethod
    def of(cls, profile: Profile) -> Door:
        """The door of a profile's robot and skin."""
        desc = load_description(profile.robot.description or None)
        return cls(desc, load_skin(profile, desc))

    def refuse(self, message: Any) -> Refusal | None:
        """Why ``message`` cannot be true here (None: it may be)."""
        seq, stamp = getattr(message, "seq", 0), getattr(message, "stamp_ns", 0)
        if not 0 <= seq < SEQ_LIMIT:
            return Refusal("seq out of range", f"seq {seq} outside [0, 2^32)")
        if not 0 <= stamp < STAMP_LIMIT:
            return Refusal("stamp out of range", f"stamp_ns {stamp} outside [0, 2^63)")
        check = self._checks.get(type(message))
        return check(message) if check is not None else None

    # -- pieces ---------------------------------------------------------------------------
    def _pad(self, pad: int, what: str, *, none: int | None = None) -> Refusal | None:
        if pad == none or 0 <= pad < self.n_pads:
            return None
        return Refusal("pad out of range", f"{what} {pad}: the robot has pads 0..{self.n_pads - 1}")

    def _trace(self, trace: m.Trace) -> Refusal | None:
        if trace == m.NO_TRACE:
            return None
        if not 0 <= trace.seq < SEQ_LIMIT or not 0 <= trace.stamp_ns < STAMP_LIMIT:
            return Refusal("trace out of range", f"trace seq {trace.seq}, stamp_ns {trace.stamp_ns}")
        return None

    def _joints(self, values: Sequence[float], what: str, *, speeds: bool = False) -> Refusal | None:
        if len(values) != self.n:
            return Refusal("wrong joint count", f"{what} has {len(values)} values, the robot has {self.n} joints")
        # The common case first, on floats; the arrays below only name the first value outside.
        if speeds:
            if all(-top <= x <= top for x, top in zip(values, self._v_top)):
                return None
        elif all(lo <= x <= hi for x, (lo, hi) in zip(values, self._q_bounds)):
            return None
        v = np.asarray(values, dtype=float)
        if speeds:
            outside = np.abs(v) > self.v_top
            bound = "the joint speed limits"
        else:
            outside = (v < self.q_lo) | (v > self.q_hi)
            bound = "the joint ranges"
        if outside.any():
            i = int(np.argmax(outside))
            return Refusal(f"{what} out of range",
                           f"{what}[{i}] = {v[i]:.6g} ({self.desc.joints[i]}) is far outside {bound}")
        return None

    @staticmethod
    def _name(name: str, what: str) -> Refusal | None:
        return None if NAME.match(name) else Refusal("bad name", f"{what} {name!r} is no service's name")

    def _pads(self, values: Sequence[Any], what: str, *, optional: bool = False) -> Refusal | None:
        if len(values) == self.n_pads or (optional and not values):
            return None
        return Refusal("wrong pad count", f"{what} has {len(values)} values, the robot has {self.n_pads} pads")

    def _entries(self, values: Sequence[Any], what: str, *, optional: bool = False) -> Refusal | None:
        if len(values) == self.n_entries or (optional and not values):
            return None
        skin = f"{self.n_entries} taxels" if self.n_entries != self.n_pads else f"{self.n_pads} pads"
        return Refusal("wrong pad count", f"{what} has {len(values)} values, the skin has {skin}")

    def _contact(self, contact: m.Contact) -> Refusal | None:
        return (self._pad(contact.pad, "contact pad")
                or self._level(contact.level, "contact level")
                or self._gain(contact.gain, "contact gain")
                or self._located(contact))

    def _located(self, contact: m.Contact) -> Refusal | None:
        """A contact's own location: none (a pad's), or a link of the robot's with a point and a unit normal."""
        if not (contact.link or contact.point or contact.normal):
            return None
        if contact.link not in self.links:
            return Refusal("contact off the skin", f"contact link {contact.link!r}: not a link of a taxel skin here")
        if len(contact.point) != 3 or len(contact.normal) != 3 or abs(float(np.linalg.norm(contact.normal)) - 1) > 1e-6:
            return Refusal("contact off the skin", f"contact point {contact.point} and normal {contact.normal}: "
                           "expected a point and a unit normal of three values each")
        if float(np.linalg.norm(contact.point)) > MAX_REACH_M:
            return Refusal("contact off the skin", f"contact point {contact.point} farther than {MAX_REACH_M} m "
                           "from its link's origin")
        return None

    @staticmethod
    def _level(level: int, what: str) -> Refusal | None:
        lo, hi = LEVELS
        return None if lo <= level <= hi else Refusal("level out of range", f"{what} {level} outside {lo}..{hi}")

    @staticmethod
    def _gain(gain: float, what: str) -> Refusal | None:
        return None if 0.0 <= gain <= 1.0 else Refusal("gain out of range", f"{what} {gain} outside [0, 1]")

    # -- per message type -------------------------------------------------------------------
    def _pressure(self, msg: m.SkinPressure) -> Refusal | None:
        for values, what in ((msg.absolute_hpa, "absolute_hpa"), (msg.baseline_hpa, "baseline_hpa"),
                             (msg.change_hpa, "change_hpa"), (msg.contact, "contact")):
            refused = self._entries(values, what)
            if refused:
                return refused
        for values, what in ((msg.valid, "valid"), (msg.touch_hpa, "touch_hpa")):
            refused = self._entries(values, what, optional=True)
            if refused:
                return refused
        lo, hi = ABSOLUTE_HPA
        for values, what in ((msg.absolute_hpa, "absolute_hpa"), (msg.baseline_hpa, "baseline_hpa")):
            bad = [x for x in values if not lo <= x <= hi]
            if bad:
                return Refusal("pressure out of range", f"{what} {bad[0]} hPa outside [{lo:g}, {hi:g}]")
        bad = [x for x in (*msg.change_hpa, *msg.touch_hpa) if abs(x) > CHANGE_HPA]
        if bad:
            return Refusal("pressure out of range", f"a pressure change of {bad[0]} hPa (at most {CHANGE_HPA:g})")
        return None

    def _world_skin(self, msg: m.WorldSkin) -> Refusal | None:
        if msg.taxels:  # a taxel skin's sample: one reading per taxel (the skin's unit), no pad lists
            if not self.links:
                return Refusal("wrong pad count", f"taxels has {len(msg.taxels)} values, the skin has pads only")
            refused = self._entries(msg.taxels, "taxels")
            if refused:
                return refused
            if msg.absolute_hpa or msg.change_hpa or msg.force_n:
                return Refusal("wrong pad count", "a taxel sample with pad values: expected one or the other")
            bad = [x for x in msg.taxels if abs(x) * self.hpa_per_unit > CHANGE_HPA]
            if bad:
                return Refusal("pressure out of range", f"a taxel reading of {bad[0]} ({bad[0] * self.hpa_per_unit:g} "
                               f"hPa; at most {CHANGE_HPA:g})")
            return None
        for values, what in ((msg.absolute_hpa, "absolute_hpa"), (msg.change_hpa, "change_hpa"),
                             (msg.force_n, "force_n")):
            refused = self._pads(values, what)
            if refused:
                return refused
        lo, hi = ABSOLUTE_HPA
        bad = [x for x in msg.absolute_hpa if not lo <= x <= hi]
        if bad:
            return Refusal("pressure out of range", f"absolute_hpa {bad[0]} hPa outside [{lo:g}, {hi:g}]")
        bad = [x for x in msg.change_hpa if abs(x) > CHANGE_HPA]
        if bad:
            return Refusal("pressure out of range", f"a pressure change of {bad[0]} hPa (at most {CHANGE_HPA:g})")
        return None

    def _pain(self, msg: m.SkinPain) -> Refusal | None:
        refused = self._trace(msg.trace) or self._pads(msg.level, "level") or self._pads(msg.gain, "gain")
        if refused:
            return refused
        lo, hi = LEVELS
        levels, gains = msg.level, msg.gain
        total = sum(gains)  # NaN if any is (min and max may pass over one)
        if not levels or not (lo <= min(levels) and max(levels) <= hi and total == total
                              and 0.0 <= min(gains) and max(gains) <= 1.0):
            refused = self._pads_pain(levels, gains)
            if refused:
                return refused
        return self._contact(msg.strongest) if msg.strongest is not None else None

    def _pads_pain(self, levels: Sequence[int], gains: Sequence[float]) -> Refusal | None:
        """The first pad whose level or gain is out of range (the slow path, for the refusal's detail)."""
        for i, (level, gain) in enumerate(zip(levels, gains)):
            refused = self._level(level, f"pad {i} level") or self._gain(gain, f"pad {i} gain")
            if refused:
                return refused
        return None

    def _touch(self, msg: m.SkinTouch) -> Refusal | None:
        refused = self._pad(msg.pad, "pad")
        if refused:
            return refused
        if msg.name != self.desc.pads[msg.pad].name:
            return Refusal("pad name mismatch", f"pad {msg.pad} is {self.desc.pads[msg.pad].name!r}, not {msg.name!r}")
        if msg.q is not None:
            return self._joints(msg.q, "q")
        return None

    def _command(self, msg: m.PositionCommand | m.VelocityCommand) -> Refusal | None:
        return self._name(msg.owner, "owner") or self._trace(msg.trace) or \
            (None if msg.reflex_seq >= 0 else Refusal("seq out of range", f"reflex_seq {msg.reflex_seq}"))

    def _position(self, msg: m.PositionCommand) -> Refusal | None:
        # Ranges are the bridge's own check (it clips what has a safe nearest value); lengths are the door's.
        refused = self._command(msg)
        if refused:
            return refused
        if len(msg.q) != self.n or any(len(row) != self.n for row in msg.ahead):
            return Refusal("wrong joint count", f"a position target without {self.n} joint values")
        return None

    def _velocity(self, msg: m.VelocityCommand) -> Refusal | None:
        refused = self._command(msg)
        if refused:
            return refused
        if len(msg.dq) != self.n:
            return Refusal("wrong joint count", f"dq has {len(msg.dq)} values, the robot has {self.n} joints")
        return None

    def _robot_state(self, msg: m.RobotState) -> Refusal | None:
        refused = (self._joints(msg.q, "q") or self._joints(msg.dq, "dq", speeds=True)
                   or (self._name(msg.owner, "owner") if msg.owner else None))
        if refused:
            return refused
        if msg.stop_distance and len(msg.stop_distance) != self.n:
            return Refusal("wrong joint count", f"stop_distance has {len(msg.stop_distance)} values")
        if msg.tau_ext and len(msg.tau_ext) != self.n:
            return Refusal("wrong joint count", f"tau_ext has {len(msg.tau_ext)} values")
        return self._continues(msg)

    def _continues(self, msg: m.RobotState) -> Refusal | None:
        """Does the state continue the bridge's stream (seq and stamp rising, a pose the arm can reach)?"""
        q = [float(x) for x in msg.q]
        last = self._state
        if last is not None:
            seq, stamp, q_last = last
            dt = (msg.stamp_ns - stamp) / 1e9
            if dt > STREAM_RESTART_S or (dt < -STREAM_RESTART_S and msg.seq < seq):
                last = None  # the stream stopped (a restarted bridge starts a new one)
            elif msg.seq <= seq or dt < 0.0:
                return Refusal("robot state out of order",
                               f"seq {msg.seq} at {msg.stamp_ns} after seq {seq} at {stamp}: not the bridge's stream")
            else:
                # Joint by joint on floats: the same IEEE operations as on arrays, without numpy's per-call cost.
                for i, (x, x_last, top) in enumerate(zip(q, q_last, self._v_top)):
                    if abs(x - x_last) > top * dt + STREAM_SLACK_RAD:
                        return Refusal("robot state jumps",
                                       f"{self.desc.joints[i]} moved {abs(x - x_last):.4f} rad in {dt:.4f} s: "
                                       "not the bridge's stream")
        self._state = (msg.seq, msg.stamp_ns, q)
        return None

    def _status(self, msg: m.PlannerStatus) -> Refusal | None:
        refused = self._name(msg.name, "planner") or self._name(msg.strategy, "strategy")
        if refused:
            return refused
        if not 0.0 <= msg.task_time_s < 1e7:
            return Refusal("time out of range", f"task_time_s {msg.task_time_s}")
        if msg.saved_pose is not None:
            refused = self._joints(msg.saved_pose, "saved_pose")
            if refused:
                return refused
        refused = self._pad(msg.target_pad, "target_pad", none=-1)
        if refused or msg.reflex is None:
            return refused
        reflex = msg.reflex
        refused = self._contact(reflex.contact) or self._trace(reflex.trace)
        if refused:
            return refused
        if reflex.target:
            refused = self._joints(reflex.target, "reflex target")
        return refused

    def _decision(self, msg: m.PlannerDecision) -> Refusal | None:
        return self._name(msg.name, "planner") or self._trace(msg.trace)

    def _switch(self, msg: m.SwitchRequest) -> Refusal | None:
        return self._name(msg.name, "planner")

    def _safety(self, msg: m.SafetyModeRequest) -> Refusal | None:
        return None  # its mode is one of two by its type; who may send it is the access control's

    def _diagnostic(self, msg: m.Diagnostic) -> Refusal | None:
        return self._name(msg.service, "service")
