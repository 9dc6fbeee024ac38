"""The effective-mass model's predicted impact force beside the force a physics world measured, per touch.

For each body part of a physics world's recording that stood for a scripted
touch (``world/contacts``, its ``touch`` the ``skin/touch`` seq): the
moment it first met the arm (its contact force above zero), the pad's speed
and its speed along its outward normal (into the person) from the robot
state then, the prediction of the gain estimator's first pain message from
that moment on (``SkinPain.impact_n`` and ``effective_mass_kg`` for the pad:
what ISO/TS 15066's power and force limiting model says a collision at that
speed would cause), and the peak contact force the world measured on the
body part while it was in the world.

They are not the same quantity, and a close match is not expected:

- the prediction is a free collision (nothing drives the arm on) of the arm's
  effective mass with ISO/TS 15066's body region, a stiff spring (a hand's
  75,000 N/m) with its effective mass (5.6 kg): ``F = v sqrt(k) /
  sqrt(1/m + 1/m_H)``;
- the world's finger is a 0.6 kg sphere on its owner's spring-damper
  (``bridge.physics.person_stiffness_n_m``, 500 N/m, critically damped)
  against a compliant pad cushion, and the arm is servo-driven: it goes on
  pushing until the planner brakes it or withdraws. Its peak is the
  damper's ``c v``, the spring's ``k x`` over the way the arm pushed it back,
  and the preload, a few newtons, where the stiff contact of the prediction
  gives tens.

The comparison means something only where the arm ran into the part
(:attr:`ImpactRow.ran_into`); a touch script's finger that presses a pad at
rest measures its owner's own push. Where the arm ran into it, the
prediction is an upper bound on the measurement, by a factor that
grows with ``sqrt(k m_H)`` of the prediction over the world's softer,
lighter person (:func:`world_free_collision_n` gives the same formula with
the world's finger, for scale). A measured force above the prediction would
say that the model misses what drives the force up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nwr.common import keys
from nwr.common.recordings import Recorded
from nwr.common.robot import RobotDescription, RobotModel

# How far the arm must push a body part back from where it met the pad for its peak force to count as the arm's, mm.
RAN_INTO_MM = 1.0


@dataclass(frozen=True)
class ImpactRow:
    """One body part that stood for a scripted touch: the prediction at first contact and the measured peak."""

    touch: int  # the skin/touch seq
    pad: str
    kind: str  # the body part's kind (finger, ...)
    t_s: float  # first contact, s from the recording's first robot state
    speed_m_s: float  # the pad's speed then (robot state), m/s
    into_m_s: float  # its speed along its outward normal then (> 0: into the person), m/s
    basis: str  # the prediction's basis ("state": from the robot state; else why every pad was unknown)
    mass_kg: float  # the arm's effective mass along the pad's motion, kg
    predicted_n: float  # the predicted impact force, N
    measured_n: float  # the peak contact force on the body part, N
    pushed_mm: float  # how far the arm pushed it back from where it met the pad, mm

    @property
    def ran_into(self) -> bool:
        """Whether the arm ran into the part: its pad moved into it at first contact and pushed it back at least
        RAN_INTO_MM. Elsewhere the force is the person's own press on a pad at rest or moving away, which the
        prediction (a collision caused by the arm's speed) says nothing about."""
        return self.into_m_s > 0.0 and self.pushed_mm >= RAN_INTO_MM

    @property
    def ratio(self) -> float:
        """measured / predicted (inf for a force measured where none was predicted)."""
        if self.predicted_n > 0:
            return self.measured_n / self.predicted_n
        return math.inf if self.measured_n > 0 else 0.0


def world_free_collision_n(into_m_s: float, mass_kg: float, stiffness_n_m: float, person_kg: float) -> float:
    """ISO/TS 15066's transfer-energy force with the world's own person: ``v sqrt(k) / sqrt(1/m + 1/m_H)``."""
    if into_m_s <= 0.0:
        return 0.0
    inverse = 1.0 / mass_kg if mass_kg > 0 else 0.0
    return into_m_s * math.sqrt(stiffness_n_m) / math.sqrt(inverse + 1.0 / person_kg)


def impact_rows(records: list[Recorded], desc: RobotDescription, model: RobotModel | None = None) -> list[ImpactRow]:
    """Per body part of the recording's world that stood for a touch, in order of first contact (module
    docstring). Empty for a recording without a physics world's contacts or without the effective-mass model's
    predictions (``SkinPain.impact_n``)."""
    model = model or RobotModel(desc)
    pains = [r.message for r in records if r.key == keys.SKIN_PAIN and r.message.impact_n]
    states = [r.message for r in records if r.key == keys.ROBOT_STATE]
    if not pains or not states:
        return []
    first: dict[int, tuple[int, str, int, str]] = {}  # touch seq -> (first contact ns, kind, pad, name)
    peak: dict[int, tuple[float, float]] = {}  # touch seq -> (peak force, peak pushed back)
    for r in records:
        if r.key != keys.WORLD_CONTACTS:
            continue
        for p in r.message.people:
            if p.touch < 0:
                continue
            if p.touch not in first and p.force_n > 0.0 and p.pads:
                first[p.touch] = (r.message.stamp_ns, p.kind, p.pads[0], p.name)
            force, pushed = peak.get(p.touch, (0.0, 0.0))
            peak[p.touch] = (max(force, p.peak_force_n), max(pushed, p.peak_pushed_m))
    state_t = np.array([s.stamp_ns for s in states], dtype=np.int64)
    pain_t = np.array([p.stamp_ns for p in pains], dtype=np.int64)
    rows = []
    for touch, (t_ns, kind, pad, _) in sorted(first.items(), key=lambda item: item[1][0]):
        i = int(np.searchsorted(pain_t, t_ns))
        if i >= len(pains):
            continue
        pain = pains[i]
        j = min(int(np.searchsorted(state_t, t_ns)), len(states) - 1)
        q, dq = np.asarray(states[j].q, dtype=float), np.asarray(states[j].dq, dtype=float)
        velocity = model.pad_jacobians(q)[pad] @ dq
        force, pushed = peak[touch]
        rows.append(ImpactRow(
            touch=touch, pad=desc.pads[pad].name, kind=kind, t_s=(t_ns - int(state_t[0])) / 1e9,
            speed_m_s=float(np.linalg.norm(velocity)), into_m_s=float(velocity @ model.pad_normal(q, pad)),
            basis=pain.impact_basis, mass_kg=float(pain.effective_mass_kg[pad]), predicted_n=float(pain.impact_n[pad]),
            measured_n=force, pushed_mm=1e3 * max(0.0, pushed)))
    return rows


def format_rows(rows: list[ImpactRow], stiffness_n_m: float, person_kg: dict[str, float]) -> str:
    """The rows as a table; beside them the same formula with the world's person (``stiffness_n_m``, the mass of
    each kind of body part)."""
    head = (f"{'t (s)':>6} {'pad':>16} {'part':>7} {'speed':>6} {'into':>6} {'mass':>6} {'predicted':>9} "
            f"{'measured':>8} {'ratio':>6} {'pushed':>6} {'ran into':>8} {'world k, m_H':>12}\n"
            f"{'':>6} {'':>16} {'':>7} {'(m/s)':>6} {'(m/s)':>6} {'(kg)':>6} {'(N)':>9} {'(N)':>8} {'':>6} "
            f"{'(mm)':>6} {'':>8} {'(N)':>12}")
    lines = [head]
    for r in rows:
        world = world_free_collision_n(r.into_m_s, r.mass_kg, stiffness_n_m, person_kg.get(r.kind, 0.6))
        lines.append(f"{r.t_s:>6.2f} {r.pad:>16} {r.kind:>7} {r.speed_m_s:>6.3f} {r.into_m_s:>6.3f} "
                     f"{r.mass_kg:>6.4g} {r.predicted_n:>9.1f} {r.measured_n:>8.1f} {r.ratio:>6.2f} "
                     f"{r.pushed_mm:>6.1f} {'yes' if r.ran_into else 'no':>8} {world:>12.1f}")
    return "\n".join(lines)
