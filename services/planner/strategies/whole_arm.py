"""Whole-arm withdrawal: a small quadratic programme every control cycle (velocity mode).

This project's reflex for an arm next to people, beside the paper's four.
Every control cycle, at the current pose q, it solves for the joint velocity
q_dot (one variable per joint)::

    minimise    (a . q_dot - v(t))^2 + m mean_i |J_i q_dot|^2 + r |q_dot|^2          a = J_p^T w
    subject to  n0 . J_p q_dot <= 0                          the touched pad: never toward the contact
                u_i . J_i q_dot >= 0  for every sampled point i of the arm (u_i: unit, from the contact to it)
                n_k . J_k q_dot <= c  for every other pad k (n_k: its outward normal)
                lo <= q_dot <= hi                            joint speed, joint range, acceleration

- ``w`` is the direction the touched pad withdraws along: minus its outward
  normal n0 (taken at the onset, as the Cartesian reflex's). A pad whose
  joints cannot move it along its normal (the shoulder pads: their normals
  are perpendicular to every motion the base joint gives them) withdraws
  along the best direction they allow: at the onset the direction its
  joints move it fastest (the larger of the two senses, ties broken by the
  robot description's reflex_direction), then straight away from the
  contact point (maximising its distance rate). The onset's log line says
  so, and the status's ``direction`` is that direction.
- ``v(t)`` is the pad's speed: G(p) ``distance_m`` / T times a raised-cosine
  profile (:func:`~nwr.services.planner.reflexes.smooth_profile`, ramps of
  ``ramp_s``), over T = ``duration_s``: the pad withdraws ``distance_m``
  at G = 1, in proportion to the gain, and the motion ramps in and out.
- The sampled points: every pad, every joint's origin, points a quarter,
  half and three quarters along each link between them, and the flange.
  Points within :data:`NEAR_M` of the contact (the touched pad's own
  surface) are not constrained; their Jacobians come from pinocchio's
  joint Jacobians through :class:`~nwr.common.robot.RobotModel`.
- ``m mean_i |J_i q_dot|^2`` (``motion_weight``: the sampled points' mean
  squared speed) keeps the rest of the arm as still as the withdrawal lets
  it: without it, a pad the constraints slow down would be "helped" by large
  motions of the whole arm for a millimetre more along its normal. It costs
  the free withdrawal about 4 % of its speed at the default weight.
  ``r |q_dot|^2`` (``regularization``) makes the solution unique, the same
  for the same touch in the same pose (the solver, quadprog, is a
  deterministic active-set method).
- ``c`` (``outward_speed_m_s``): no other pad moves out along its own
  normal, into the space where a hand may be, faster than the arm can stop
  it within 5 mm of where a new touch finds it: a hand the skin feels up to
  one sample period (40 ms at 25 Hz) and a control cycle late, then the
  joints' braking (about 2 m/s^2 at a pad), v T + v^2 / (2 a) <= 5 mm gives
  v ~ 0.07 m/s. The touched pad's own withdrawal is not capped (it moves
  inward along its normal); other pads moving sideways or inward are not
  either. Where the cap (or another constraint) holds the touched pad's
  plateau speed below what its gain asks, the reflex lasts longer (up to
  :data:`STRETCH_MAX` times ``duration_s``) so that the pad still withdraws
  G ``distance_m``: the distance stays in proportion to the gain, the speed
  is what the arm can do safely.
- Bounds: ``speed_fraction`` of each joint's speed limit; no faster toward a
  joint limit (less :data:`MARGIN_RAD`) than it can brake before it. The
  planner's core then limits the change of the commanded velocity per cycle
  to the acceleration limits (as for every velocity stream), and the bridge's
  tracker to the jerk limit.
- The solution is then scaled down uniformly so that no sampled point
  moves faster than ``point_speed_m_s`` (the constraints are cones through
  zero and the bounds contain it: a shorter q_dot keeps to them).

A pose in which nothing can withdraw the pad without bringing another part
of the arm toward the contact gives q_dot = 0: the arm holds still (the
retreat check then reports ``withdraws = false`` and, with
``sustained_contact = "hold"``, the planner holds), logged once per reflex.
A solver failure, an exception or a non-finite result gives q_dot = 0 for
that cycle, counted in :attr:`WholeArm.failures` and reported once per
reflex (a warning, on ``diag/planner-<name>``). Cycles whose motion the
constraints changed (the free withdrawal would have brought a point closer
to the contact) count as corrections: the status's ``retreat.corrected``.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Annotated

import msgspec
import numpy as np
import pinocchio as pin
import quadprog

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.guards import Guard
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.section import Section
from nwr.common.skin import contact_normal, contact_point
from nwr.services.planner.reflexes import smooth_profile
from nwr.services.planner.strategies import KIND, Onset, ReflexStrategy

if TYPE_CHECKING:
    from nwr.common.config import Profile
    from nwr.services.planner.contacts import ContactPoint

log = logging.getLogger(__name__)

# Sampled points closer than this to the contact point at the onset are the touched pad's own surface: not
# constrained, m.
NEAR_M = 0.02
# The motion keeps this far inside each joint's range, rad.
MARGIN_RAD = 0.05
# Points along each link, as fractions of the way between its two ends.
ALONG = (0.25, 0.5, 0.75)
# No sampled point comes closer to the contact point than it was at the onset by more than this, m: the
# linearised constraint each cycle is a velocity damper, u_i . J_i q_dot >= -(d_i - d_i0 + budget) / TAU_S,
# so a point may take up second-order motion (a turn about the base) and rounding, never more. The touched
# pad moves toward the contact along its normal by at most TOWARD_BUDGET_M.
APPROACH_BUDGET_M = 0.003
TOWARD_BUDGET_M = 0.0005
TAU_S = 0.5
# At the onset a pad that can move along its normal at less than this share of its speed (within the budgets)
# withdraws along the best direction across the normal its joints allow.
NORMAL_SHARE = 0.25
# Directions across the normal tried at the onset (evenly around it).
SIDEWAYS_DIRECTIONS = 8
# A pad whose joints can move it along its normal at least this far (m) within the constraints, but less than
# SHORT_SHARE of distance_m, withdraws along it the gain's share of that reach ("short"), not sideways.
REACH_MIN_M = 0.005
SHORT_SHARE = 0.5
# A short withdrawal is this share of the reach at G = 0, growing linearly to all of it at G = 1: a light
# touch's still moves the pad visibly away (more than the retreat check's smallest withdrawal, a tenth of
# 2 mm), rather than hold the arm braking along the task's way, and a stronger touch's further.
SHORT_MIN_SHARE = 0.15
# Below this share of its speed in every direction the pad cannot withdraw at all: the arm holds still.
HOLD_SHARE = 0.05
# A sideways withdrawal follows the direction away from the contact point once this far from it, m.
AWAY_M = 0.002
# A withdrawal the constraints slow down at the onset lasts at most this many times duration_s.
STRETCH_MAX = 2.0
# A constraint row this small (no joint moves that point) is left out.
ZERO_ROW = 1e-9
# This slack (per unit row) keeps a feasible set whose only point is q_dot = 0 (every budget spent) from
# reading as inconsistent constraints to the solver.
SLACK = 1e-7
# A cycle whose pad withdraws at under this share of its speed because of the no-approach constraints counts
# as a correction.
CORRECTED_SHARE = 0.9


@dataclass(frozen=True)
class Other:
    """Another active contact the withdrawal keeps the arm away from (besides the reflex's own)."""

    pad: int
    point: np.ndarray  # where its pad was touched (base frame), m
    normal: np.ndarray  # its pad's outward normal there
    gain: float
    d0: np.ndarray  # each sampled point's distance from it when it began to count, m
    free: np.ndarray  # sampled points not constrained by it (its pad's own surface)


class WholeArmSettings(Section):
    """``[planner.whole-arm]``."""

    # The whole-arm withdrawal ("whole-arm"): every control cycle a small QP
    # finds the joint velocity that moves the touched pad away from the
    # contact while no other sampled point of the arm comes closer to it
    # (docs/reflexes.md). Its stream lasts duration_s, ramped in and out
    # (raised cosine, ramp_s each, at most half of duration_s).
    duration_s: Annotated[float, msgspec.Meta(gt=0, le=2.0)] = 1.0
    ramp_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.3
    # How far the touched pad withdraws at G(p) = 1 when nothing limits it, m
    # (in proportion to the gain below; the Cartesian reflex's 0.125 m).
    distance_m: Annotated[float, msgspec.Meta(gt=0, le=0.3)] = 0.125
    # No sampled point of the arm (pads, joints, points along the links,
    # flange) faster than this, m/s: the whole motion is scaled down to it.
    point_speed_m_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.5
    # No other pad than the touched one moves out along its own normal
    # (toward where a new hand may be) faster than this, m/s: a hand that
    # appears in its path is met with at most skin period + a control cycle
    # of motion plus the joints' braking, within 5 mm (docs/reflexes.md).
    outward_speed_m_s: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 0.07
    # Weight of the arm's mean squared point speed beside the pad's squared
    # speed error: the rest of the arm as still as the withdrawal lets it.
    motion_weight: Annotated[float, msgspec.Meta(ge=0, le=1.0)] = 0.02
    # Weight of |q_dot|^2 (m^2/rad^2): makes the solution unique.
    regularization: Annotated[float, msgspec.Meta(gt=0, le=1.0)] = 1e-4


class WholeArm(ReflexStrategy):
    """The touched pad away from the contact, no other point of the arm toward it: a QP each cycle."""

    name = "whole-arm"
    rank = 50
    mode = "velocity"
    retraces = True
    Settings = WholeArmSettings
    GUARDS = {"duration_s": Guard("below", "s"), "distance_m": Guard("above", "m"),
              "point_speed_m_s": Guard("above", "m/s"), "outward_speed_m_s": Guard("above", "m/s")}

    @staticmethod
    def check_settings(p: WholeArmSettings, profile: Profile | None = None,
                       desc: RobotDescription | None = None) -> None:
        if p.ramp_s > p.duration_s / 2:
            raise ConfigError(f"planner.whole-arm.ramp_s = {p.ramp_s} s is more than half of "
                              f"planner.whole-arm.duration_s = {p.duration_s} s: the ramps in and out would overlap")

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        super().__init__(cfg, desc, model, v_limit)
        p = KIND.settings(cfg, self.name, WholeArmSettings)
        self.check_settings(p)
        self.duration_s = p.duration_s  # this reflex's (start() may lengthen it)
        self.configured_s = p.duration_s
        self.ramp_s = p.ramp_s
        self.distance_m = p.distance_m
        self.point_speed = p.point_speed_m_s
        self.outward_speed = p.outward_speed_m_s
        self.regularization = p.regularization
        self.motion_weight = p.motion_weight
        self.v_limit = np.asarray(v_limit, dtype=float)
        self.a_limit = cfg.speed_fraction * np.asarray(desc.a_max, dtype=float)
        self.dt = 1.0 / cfg.rate_hz
        self.q_lo = desc.q_min + MARGIN_RAD
        self.q_hi = desc.q_max - MARGIN_RAD
        self.sign = np.asarray(desc.reflex_direction, dtype=float)
        self.pad_names = [pad.name for pad in desc.pads]
        self.n_pads = len(desc.pads)
        n = len(desc.joints)
        # pinocchio's joint Jacobians have the root's axes; the model's results the base frame's (a constant turn).
        self._root = np.array(model.frame_pose(desc.home, "universe")[:3, :3])
        self._eye = np.eye(n)
        self._box = np.vstack([-np.eye(n), np.eye(n)])  # -x >= -hi, x >= lo
        # The current reflex (start() replaces these, never changes them in place: a snapshot is a shallow copy).
        self.pad = -1
        self.gain = 0.0
        self.contact = np.zeros(3)
        self.normal = np.zeros(3)
        self.away = np.zeros(3)  # the withdrawal direction w
        self.sideways = False  # the pad cannot move along its normal: it withdraws along w, then from the contact
        self.short = False  # the pad moves along its normal only reach_m: it withdraws G reach_m
        self.reach_m = 0.0  # how far the pad can withdraw along its normal within the constraints (estimate), m
        self.blocked = False  # nothing can withdraw it: the stream is zero
        self.speed_m_s = 0.0  # the pad's mean speed, G distance_m / T; the profile's plateau is T / (T - ramp) of it
        # Counts of the current reflex's live cycles (never of a retreat check's integration).
        self.failures = 0  # solver failures, exceptions, non-finite results: a zero command instead
        self.stalled = 0  # cycles in which the constraints let the pad withdraw at under HOLD_SHARE of its speed
        self._said: set[str] = set()  # what this reflex has reported (once each)
        # Where the reflex's touch began (its first onset: a restart of the same touch keeps it) and each sampled
        # point's distance from it then, m: an escalating press restarts the reflex at each sample, and a budget
        # renewed at each restart would add up.
        self._origin = np.zeros(3)
        self._origin_of: tuple[int, int] | None = None  # (pad, onset_ns) of the touch it is the origin of
        self._touch: ContactPoint | None = None  # the reflex's own touch (set_contacts), if the planner keeps them
        self._d0 = np.zeros(0)
        self._free = np.zeros(0, dtype=bool)  # sampled points not constrained (the touched pad's own surface)
        self.others: list[Other] = []  # the other active contacts (set_contacts), replaced, never changed in place

    # -- every active contact -----------------------------------------------------------------
    def set_contacts(self, q: np.ndarray, contacts: list[ContactPoint], main: int) -> None:
        """The recent contacts at the commanded pose ``q``: each besides the reflex's own (on pad ``main``) is
        kept away from from now on (its pad never toward it, no other point closer to it than when it began to
        count), and the pad of each still felt withdrawn in proportion to its gain."""
        known = {o.pad: o for o in self.others}
        others: list[Other] = []
        points: np.ndarray | None = None
        self._touch = None
        for contact in contacts:
            if contact.pad == main:
                self._touch = contact
                continue
            other = known.get(contact.pad)
            if other is not None and np.array_equal(other.point, contact.point):
                others.append(replace(other, gain=contact.gain))
                continue
            if points is None:
                points = self._samples(q)[0]
            d0 = np.linalg.norm(points - contact.point, axis=1)
            free = d0 <= NEAR_M
            free[contact.pad] = True
            others.append(Other(contact.pad, contact.point, contact.normal, contact.gain, d0, free))
        if [o.pad for o in others] != [o.pad for o in self.others]:
            names = ", ".join(self.pad_names[o.pad] for o in others) or "none"
            log.info("whole-arm withdrawal: besides pad %s, kept away from the contacts on %s",
                     self.pad_names[main], names)
        self.others = others

    # -- the reflex's onset -------------------------------------------------------------------
    def start(self, q: np.ndarray, contact: m.Contact) -> Onset:
        """Begin (or update) a reflex: the contact point and normal at ``q``, and the withdrawal direction."""
        model = self.model
        self.pad = contact.pad
        self.others = [o for o in self.others if o.pad != contact.pad]  # the reflex's own pad is no other
        self.gain = max(0.0, float(contact.gain)) if np.isfinite(contact.gain) else 0.0
        self.corrections = self.failures = self.stalled = 0
        self._said = set()
        self.contact = contact_point(model, q, contact)
        self.normal = contact_normal(model, q, contact)
        self.away = -self.normal
        self.sideways = self.blocked = self.short = False
        self.reach_m = self.distance_m
        self.duration_s = self.configured_s
        self.speed_m_s = self.gain * self.distance_m / self.duration_s
        samples = self._samples(q)
        touch = self._touch if self._touch is not None and self._touch.pad == self.pad else None
        key = None if touch is None else (touch.pad, touch.onset_ns)
        if key is None or key != self._origin_of or len(self._d0) != len(samples[0]):
            self._origin, self._origin_of = self.contact, key
            self._d0 = np.linalg.norm(samples[0] - self.contact, axis=1)
            self._free = self._d0 <= NEAR_M  # the touched pad's own surface: not constrained
            self._free[self.pad] = True
        if self.speed_m_s <= 0.0:
            return Onset(direction=[0.0, 0.0, 0.0])
        name = self.pad_names[contact.pad]
        try:
            self.reach_m = self._reach(q, samples)
            distance = self.distance_m
            if REACH_MIN_M <= self.reach_m < SHORT_SHARE * distance:
                # Only so far along the normal: a share of that reach growing with the gain, in proportion still.
                share = SHORT_MIN_SHARE + (1.0 - SHORT_MIN_SHARE) * self.gain
                self.short, distance = True, self.reach_m * share / self.gain
                self.speed_m_s = self.gain * distance / self.duration_s
            along = self._probe(q, self.away, samples)
            if not self.short and along < NORMAL_SHARE * self.speed_m_s:
                side, rate = self._sideways(q, samples)
                if rate > along:
                    self.away, self.sideways, along = side, True, rate
            plateau = self.speed_m_s * self.duration_s / (self.duration_s - self.ramp_s)
            if HOLD_SHARE * self.speed_m_s <= along < plateau:
                # Slower than the gain asks: longer, so that the distance stays G times the distance.
                self.duration_s = min(STRETCH_MAX * self.configured_s, self.ramp_s + self.gain * distance / along)
                self.speed_m_s = self.gain * distance / self.duration_s
        except Exception as exc:  # the stream then tries every cycle; each failure gives a zero command
            self._say("warning", "whole_arm_failed", f"reflex on pad {name}: the withdrawal's QP failed at the "
                      f"onset ({exc!r}): every cycle it fails the arm is commanded to stand still")
            return Onset(direction=(self.speed_m_s * self.away).tolist(), reason="failed")
        if along < HOLD_SHARE * self.speed_m_s:
            self.blocked, self.sideways = True, False
            self._say("info", "whole_arm_blocked",
                      f"reflex on pad {name}: no joint motion moves it away from the contact without bringing "
                      "another part of the arm closer to it: holding still")
            return Onset(direction=[0.0, 0.0, 0.0], reason="blocked")
        if self.short:
            self._say("info", "whole_arm_short",
                      f"reflex on pad {name}: its joints move it along its normal only "
                      f"{1e3 * self.reach_m:.1f} mm without bringing another part of the arm closer to the contact; "
                      f"it withdraws {1e3 * self.speed_m_s * self.duration_s:.1f} mm, the gain's share of that")
            return Onset(direction=(self.speed_m_s * self.away).tolist(), reason="short", reach_m=self.reach_m)
        if self.sideways:
            self._say("info", "whole_arm_sideways",
                      f"reflex on pad {name}: its joints cannot move it along its normal without bringing another "
                      f"part of the arm closer to the contact; it withdraws sideways, along "
                      f"{np.round(self.away, 3).tolist()} (base frame), away from the contact point")
        return Onset(direction=(self.speed_m_s * self.away).tolist(), reason="sideways" if self.sideways else "",
                     reach_m=self.distance_m)

    def _probe(self, q: np.ndarray, away: np.ndarray, samples: tuple[np.ndarray, np.ndarray]) -> float:
        """How fast the pad can withdraw along ``away`` at the profile's plateau within the approach budgets
        (after the speed cap), m/s."""
        plateau = self.speed_m_s * self.duration_s / (self.duration_s - self.ramp_s)
        dq, _, _ = self._solve(q, plateau, away, samples=samples)
        return float(away @ (samples[1][self.pad] @ dq))

    def _reach(self, q: np.ndarray, samples: tuple[np.ndarray, np.ndarray]) -> float:
        """How far the pad can withdraw along its normal within the constraints, at most, m (an estimate).

        At full gain's plateau speed, the pad's speed along the normal the constraints allow (``fast``), and
        the share of it that spends no approach budget (``rigid``: every point of the arm holding its distance
        from the contact). The rigid share may go on for the longest reflex; the rest spends the budgets,
        which the velocity dampers let go in about ``TAU_S``.
        """
        full = self.distance_m / (self.configured_s - self.ramp_s)
        jac = samples[1][self.pad]
        dq_fast = self._solve(q, full, self.away, samples=samples)[0]
        fast = float(self.away @ (jac @ dq_fast))
        dq_rigid = self._solve(q, full, self.away, samples=samples, budgets=0.0)[0]
        rigid = float(self.away @ (jac @ dq_rigid))
        rigid = min(max(rigid, 0.0), max(fast, 0.0))
        reach = rigid * (STRETCH_MAX * self.configured_s - self.ramp_s) + (max(fast, 0.0) - rigid) * TAU_S
        # No further than the motion goes before a joint reaches its range (less the margin): near a joint limit
        # the speed the QP allows there says nothing of how far it may go.
        return min(reach, max(fast, 0.0) * self._room_s(q, dq_fast))

    def _room_s(self, q: np.ndarray, dq: np.ndarray) -> float:
        """How long ``dq`` may go on from ``q`` before a joint reaches its range less MARGIN_RAD, s."""
        room = np.where(dq > 0.0, self.q_hi - q, q - self.q_lo)
        moving = np.abs(dq) > 1e-9
        if not moving.any():
            return np.inf
        return float(np.min(np.maximum(room[moving], 0.0) / np.abs(dq[moving])))

    def _sideways(self, q: np.ndarray, samples: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, float]:
        """The best direction across the pad's normal that its joints allow, and its speed along it (m/s).

        SIDEWAYS_DIRECTIONS directions evenly around the normal, from the one along which the joints move
        the pad fastest (in the sense that turns them along the robot description's reflex_direction); the
        fastest withdrawal the constraints leave wins, a tie the first.
        """
        jac = samples[1][self.pad]
        across = jac - np.outer(self.normal, self.normal @ jac)
        u, s, _ = np.linalg.svd(across)
        first = u[:, 0] if s[0] > 1e-9 else np.cross(self.normal, np.eye(3)[int(np.argmin(np.abs(self.normal)))])
        first = first / np.linalg.norm(first)
        if float(self.sign @ (jac.T @ first)) < 0.0:
            first = -first
        second = np.cross(self.normal, first)
        best, rate = self.away, 0.0
        for k in range(SIDEWAYS_DIRECTIONS):
            angle = 2.0 * np.pi * k / SIDEWAYS_DIRECTIONS
            candidate = np.cos(angle) * first + np.sin(angle) * second
            r = self._probe(q, candidate, samples)
            if r > rate + 1e-9:
                best, rate = candidate, r
        return best, rate

    # -- every control cycle -------------------------------------------------------------------
    def velocity(self, q: np.ndarray, t: float, *, count: bool = True) -> np.ndarray:
        """q_dot at pose ``q``, ``t`` s into the reflex (``count``: a live cycle, not the retreat check's)."""
        n = len(self.v_limit)
        speed = self.speed_m_s * smooth_profile(t, self.duration_s, self.ramp_s)
        if self.pad < 0 or self.blocked or not speed > 0.0:
            return np.zeros(n)
        try:
            away = self.away
            if self.sideways:  # straight away from the contact point, once the pad has left it
                offset = self.model.pad_point(q, self.pad) - self.contact
                dist = float(np.linalg.norm(offset))
                if dist > AWAY_M:
                    away = offset / dist
            dq, corrected, achieved = self._solve(q, speed, away)
        except Exception as exc:  # never without a command: stand still this cycle
            if count:
                self.failures += 1
                self._say("warning", "whole_arm_failed",
                          f"reflex on pad {self.pad_names[self.pad]}: the withdrawal's QP failed ({exc!r}); the arm "
                          "is commanded to stand still in every cycle it fails (counted)")
            return np.zeros(n)
        if count:
            if corrected:
                self.corrections += 1
            if achieved < HOLD_SHARE * speed:
                self.stalled += 1
                self._say("info", "whole_arm_stalled",
                          f"reflex on pad {self.pad_names[self.pad]}: {t:.2f} s in, no joint motion moves it "
                          "farther without bringing another part of the arm closer to the contact: slowing to a "
                          "stop")
        return dq

    def _solve(self, q: np.ndarray, speed: float, away: np.ndarray, *,
               samples: tuple[np.ndarray, np.ndarray] | None = None, budgets: float = 1.0
               ) -> tuple[np.ndarray, bool, float]:
        """The QP at ``q`` for the pad's speed ``speed`` along ``away``: q_dot, whether the constraints held the
        pad back, and the pad's speed along ``away`` it gives (m/s). ``samples``: :meth:`_samples` at ``q``, if
        known. Raises on a failure."""
        points, jacs = self._samples(q) if samples is None else samples
        jp = jacs[self.pad]
        a = jp.T @ away
        # Constraints G q_dot <= h: the touched pad not toward the contact along n0; no other sampled point
        # closer to the contact point (each beyond its budget).
        offset = points - self._origin
        dist = np.linalg.norm(offset, axis=1)
        keep = ~self._free
        units = offset[keep] / dist[keep, None]
        rows = np.vstack([self.normal @ jp, -np.matmul(units[:, None, :], jacs[keep])[:, 0, :]])
        toward = float(self.normal @ (points[self.pad] - self.contact))
        h = budgets * np.concatenate([[max(0.0, TOWARD_BUDGET_M - toward)],
                                      np.maximum(0.0, dist[keep] - self._d0[keep] + APPROACH_BUDGET_M)]) / TAU_S
        # Every other pad (not the touched pad's own surface): out along its own normal no faster than
        # outward_speed_m_s.
        capped = ~self._free[: self.n_pads]
        normals = self.model.pad_normals(q)[capped]
        rows = np.vstack([rows, np.matmul(normals[:, None, :], jacs[: self.n_pads][capped])[:, 0, :]])
        h = np.concatenate([h, np.full(len(normals), self.outward_speed)])
        # Every other active contact: the same two kinds of constraint, and its pad withdrawn in proportion to
        # its gain (at the reflex's own profile).
        hessian_others = np.zeros((len(a), len(a)))
        linear_others = np.zeros(len(a))
        share = speed / self.speed_m_s if self.speed_m_s > 0.0 else 0.0
        for other in self.others:
            o_offset = points - other.point
            o_dist = np.linalg.norm(o_offset, axis=1)
            o_keep = ~other.free
            o_units = o_offset[o_keep] / o_dist[o_keep, None]
            o_toward = float(other.normal @ (points[other.pad] - other.point))
            rows = np.vstack([rows, other.normal @ jacs[other.pad],
                              -np.matmul(o_units[:, None, :], jacs[o_keep])[:, 0, :]])
            h = np.concatenate([h, budgets * np.concatenate([
                [max(0.0, TOWARD_BUDGET_M - o_toward)],
                np.maximum(0.0, o_dist[o_keep] - other.d0[o_keep] + APPROACH_BUDGET_M)]) / TAU_S])
            if other.gain > 0.0:  # still felt: its pad withdraws too
                o_a = jacs[other.pad].T @ -other.normal
                hessian_others += np.outer(o_a, o_a)
                linear_others += share * other.gain * self.distance_m / self.duration_s * o_a
        norms = np.linalg.norm(rows, axis=1)
        used = norms > ZERO_ROW
        rows = rows[used] / norms[used, None]
        h = h[used] / norms[used] + SLACK
        # Bounds: the joint speed limits, a joint range less the margin no faster than it can brake before.
        room_hi = np.maximum(self.q_hi - q, 0.0)
        room_lo = np.maximum(q - self.q_lo, 0.0)
        hi = np.minimum(self.v_limit, np.sqrt(2.0 * self.a_limit * room_hi))
        lo = -np.minimum(self.v_limit, np.sqrt(2.0 * self.a_limit * room_lo))
        flat = jacs.reshape(-1, jacs.shape[2])
        motion = flat.T @ flat / len(jacs)  # the sampled points' mean squared speed
        hessian = np.outer(a, a) + hessian_others + self.motion_weight * motion + self.regularization * self._eye
        # quadprog: minimise 1/2 x'Gx - a'x subject to C'x >= b (rows x <= h, lo <= x <= hi).
        constraints = np.vstack([-rows, self._box]).T
        bounds = np.concatenate([-h, -hi - SLACK, lo - SLACK])
        dq = np.asarray(quadprog.solve_qp(hessian, speed * a + linear_others, constraints, bounds)[0], dtype=float)
        if dq.shape != a.shape or not np.all(np.isfinite(dq)):
            raise RuntimeError(f"quadprog returned {dq!r}")
        # No sampled point faster than point_speed_m_s.
        fastest = float(np.max(np.linalg.norm(jacs @ dq, axis=1)))
        if fastest > self.point_speed:
            dq = dq * (self.point_speed / fastest)
        achieved = float(a @ dq)
        # Corrected: the pad withdraws slower than asked because the free withdrawal (no constraint, no bound)
        # would have brought another point closer to the contact than the constraints allow.
        free = a * (speed / (float(a @ a) + self.regularization))
        corrected = achieved < CORRECTED_SHARE * speed and bool(np.any(rows @ free > h))
        return dq, corrected, achieved

    def _samples(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The sampled points of the arm at ``q`` (K x 3, base frame; the pads first, in id order) and their
        linear Jacobians (K x 3 x n)."""
        model = self.model
        speed_jacs = model.speed_jacobians(q)  # pads, elbow, flange; also brings pinocchio's data to q
        pads = model.pad_points(q)
        origins = model.joint_positions(q)  # every joint's origin, then the flange
        n = model.nq
        ends = np.empty((n + 1, 3, n))
        for joint in range(1, n + 1):
            ends[joint - 1] = self._root @ pin.getJointJacobian(model.model, model.data, joint,
                                                               pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)[:3]
        ends[n] = speed_jacs[-1]  # the flange
        # Along each link: joint k's origin to joint k+1's (both fixed in link k), the last joint's to the flange.
        fractions = np.asarray(ALONG)
        along = (origins[:-1, None, :] * (1.0 - fractions)[None, :, None]
                 + origins[1:, None, :] * fractions[None, :, None]).reshape(-1, 3)
        along_j = (ends[:-1, None] * (1.0 - fractions)[None, :, None, None]
                   + ends[1:, None] * fractions[None, :, None, None]).reshape(-1, 3, n)
        points = np.concatenate([pads, origins, along])
        jacs = np.concatenate([speed_jacs[: self.n_pads], ends, along_j])
        return points, jacs

    def _say(self, level: str, code: str, message: str) -> None:
        """Report once per reflex: the log and the planner's diagnostics."""
        if code in self._said:
            return
        self._said.add(code)
        log.log(logging.WARNING if level == "warning" else logging.INFO, "%s", message)
        self.notes.append((level, code, message))

    def snapshot(self) -> WholeArm:
        stream = copy.copy(self)
        stream._said = set(self._said)
        stream.notes = []
        return stream


STRATEGY = WholeArm
