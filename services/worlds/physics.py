"""The physics world: the arm, its skin and the people touching it, in MuJoCo.

A pure core: numbers in, readings out, no clock, no thread, no network. One
fixed step at a time (``timestep_s``, 1 ms by default), single-threaded:
the same calls in the same order give bit-identical readings, so that a
journal of its inputs re-makes a run.

- **The arm** (:mod:`nwr.services.worlds.mjcf`): the robot description's
  links with collision capsules and a compliant cushion per pad, driven by
  a servo per joint (``kp (q_c - q) + kv (dq_c - dq)``, gravity
  compensated, clipped at the joint's effort limit). ``kp`` is the effort
  limit over ``servo_error_rad`` (a joint reaches its torque limit that far
  from its command) and ``kv = kp * servo_damping_s``. ``step(q_command,
  dq_command)``: without ``dq_command`` the servos' speed target is the
  command's own rate of change (its last change over the time it took,
  held until the next change is late, then zero).
- **People** (:mod:`nwr.services.worlds.people`): body parts (finger,
  palm, forearm) that a spring-damper pulls toward their target:
  ``F = k (target - x) - c v`` with ``c = 2 zeta sqrt(k m)``, its magnitude
  clipped at the part's push force. A finger whose target lies behind a
  pad presses it with ``k`` times the distance; when the arm moves into it
  the finger is pushed back and presses harder; when the arm withdraws
  further than the target the finger loses contact. Any number at once, up
  to the slots of each kind (``fingers``, ``palms``, ``forearms``); added,
  retargeted and removed between steps. ``k = 500 N/m`` by default: the
  endpoint stiffness of a human arm is a few hundred N/m (Mussa-Ivaldi,
  Hogan and Bizzi 1985), so a 15 N press puts the target 3 cm behind the
  pad's surface.
- **Skin** (:mod:`nwr.services.worlds.skin`): each pad's pressure change
  from the normal forces on it (``dP = P_sat tanh(F / (A_eff
  P_sat))``, ``A_eff = 125 cm^2``, ``P_sat = 80 hPa``: the paper's PL 2/3/4
  and G = 1 thresholds of 2/6/12/20 hPa at 2.5/7.5/15.1/25.5 N of finger
  force), sampled at 25 Hz with noise and latency. A contact on a pad's
  cushion counts on that pad; the pads cover the whole arm, so a contact on
  a link's housing counts on the pad of the same link that faces it (its
  outward normal within 90 degrees of the contact's) and is nearest; a
  contact no pad faces (the base) is felt by the person only. The skin is
  stiff next to the person's arm (it yields about 0.5 mm under a 15 N
  finger, as an air spring of that effective area over some 0.4 l of air
  at 1013 hPa would: ``k = P A^2 / V``), so a press settles within a few
  per cent of the force its target asks for.
- **Force figures**, per body part: the contact force on the person (N),
  the pressure over the contact area (N/cm^2), the energy the arm put into
  the person (J: the positive work of the contact forces on the part,
  whether it set the part moving or pushed it back against its owner's
  pull), their peaks, and ISO/TS 15066's limits for the body area the part
  stands for. The contact area is the part's shape cut at the
  depth it is pressed in: the cushion's yield plus the tissue's own
  (``F / k`` with ISO/TS 15066's effective spring constant of the region).
  Rigid shapes make it small, so pressures err high (on the safe side).

Bad input is refused before anything moves (:class:`ConfigError`): a model
that does not compile, a body part that starts inside the arm, a push
beyond what a person plausibly makes with that part, a command that is not
a finite joint vector (:class:`SafetyError`). A simulation that diverges
stops the world (:class:`WorldUnstable`, with what was seen): a non-finite
state, a MuJoCo warning (bad accelerations, whose reset would be a jump;
too many contacts), a joint faster than ``max_speed_factor`` times its
limit, a body part faster than ``max_body_speed_m_s``, a kinetic energy
beyond what the arm at those speeds and every body part at that speed can
hold, or a penetration deeper than ``max_penetration_m``. The readings
stay those of the last good step; every later ``step`` raises again.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import msgspec
import mujoco
import numpy as np

from nwr.common.errors import ConfigError, SafetyError
from nwr.common.robot import RobotDescription
from nwr.services.worlds import mjcf
from nwr.services.worlds.people import KINDS, KindSpec, Region, region_of
from nwr.services.worlds.settings import PhysicsSettings, WorldUnstable
from nwr.services.worlds.skin import SkinSample, SkinSampler, force_for_pressure, pressure_from_force
from nwr.services.worlds.world import ArmState

log = logging.getLogger(__name__)

# MuJoCo's warnings that mean the step cannot be trusted.
_WATCHED = (
    (mujoco.mjtWarning.mjWARN_BADQACC, "bad accelerations (MuJoCo reset the state)"),
    (mujoco.mjtWarning.mjWARN_BADQPOS, "a bad position"),
    (mujoco.mjtWarning.mjWARN_BADQVEL, "a bad velocity"),
    (mujoco.mjtWarning.mjWARN_CONTACTFULL, "the contact buffer full"),
    (mujoco.mjtWarning.mjWARN_CNSTRFULL, "the constraint buffer full"),
)


# A body part that enters the world this close to the arm's surface (m) touches it; deeper is inside it.
_TOUCHING_M = 1e-4


Vector = tuple[float, float, float]


class BodyPart(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A person's body part, as a touch script places it. Positions in the robot's base frame, m."""

    # Unique among the world's body parts.
    name: str
    kind: Literal["finger", "palm", "forearm"]
    # Where it is when it enters the world (outside the arm).
    position: Vector
    # Where its owner pulls it.
    target: Vector
    # The direction its contact side faces (a palm's face; a forearm lies across it).
    facing: Vector = (0.0, 0.0, -1.0)
    # A forearm's axis, a palm's long side (None: a fixed choice square to facing).
    along: Vector | None = None
    # The owner's spring toward the target, N/m (None: the world's).
    stiffness_n_m: float | None = None
    # The most its owner pushes with, N (None: the kind's plausible push; more is refused).
    max_force_n: float | None = None


@dataclass(frozen=True, eq=False)
class Touch:
    """One contact between a body part and the arm: ``force`` (N) on the person, ``normal`` from the arm into
    the person, ``point`` in the base frame, ``pad`` the pad id when the arm's side is a pad's cushion."""

    person: str
    geom: str
    pad: int | None
    point: np.ndarray
    normal: np.ndarray
    force: np.ndarray
    depth_m: float


@dataclass(frozen=True, eq=False)
class PersonReport:
    """What one body part feels, now and at its worst since it entered the world.

    ``force_n`` is the magnitude of the contact forces on it, ``push_n`` the
    magnitude of its owner's pull, ``pressure_n_cm2`` the force over
    ``area_cm2`` (0 without contact), ``energy_j`` the work the arm's
    contacts did on it (its positive part: energy put into the person).
    ``region`` is the ISO/TS 15066 body area it is judged by.
    """

    name: str
    kind: str
    region: Region
    position: np.ndarray
    target: np.ndarray
    pads: tuple[int, ...]
    force_n: float
    push_n: float
    area_cm2: float
    pressure_n_cm2: float
    peak_force_n: float
    peak_pressure_n_cm2: float
    energy_j: float

    @property
    def in_contact(self) -> bool:
        return self.force_n > 0.0

    def limits(self) -> dict[str, float]:
        """The peaks as fractions of ISO/TS 15066's limits (transient ones: inf where not permitted)."""
        r = self.region
        transient_f, transient_p = r.transient_force_n, r.transient_pressure_n_cm2
        return {
            "force_quasi_static": self.peak_force_n / r.force_n,
            "force_transient": self.peak_force_n / transient_f if transient_f > 0 else math.inf,
            "pressure_quasi_static": self.peak_pressure_n_cm2 / r.pressure_n_cm2,
            "pressure_transient": self.peak_pressure_n_cm2 / transient_p if transient_p > 0 else math.inf,
        }


@dataclass(eq=False)
class _Slot:
    """A body in the model that a body part can take: its ids, and the part's state while it holds one."""

    name: str
    kind: str
    spec: KindSpec
    region: Region
    body: int
    geom: int
    qadr: int
    dadr: int
    origin: np.ndarray  # the body's position at zero slide (MuJoCo's body_pos): parked, or where the part entered
    part: BodyPart | None = None
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    k: float = 0.0
    c: float = 0.0
    fmax: float = 0.0
    at: np.ndarray = field(default_factory=lambda: np.zeros(3))  # its position after the last good step
    push: np.ndarray = field(default_factory=lambda: np.zeros(3))
    force: np.ndarray = field(default_factory=lambda: np.zeros(3))
    area_cm2: float = 0.0
    pads: tuple[int, ...] = ()
    peak_force: float = 0.0
    peak_pressure: float = 0.0
    energy: float = 0.0

    def position(self, data: Any) -> np.ndarray:
        return self.origin + self.rotation @ data.qpos[self.qadr:self.qadr + 3]

    def velocity(self, data: Any) -> np.ndarray:
        return self.rotation @ data.qvel[self.dadr:self.dadr + 3]


class PhysicsWorld:
    """The arm of ``desc``, its pads and people's body parts in MuJoCo, stepped by :meth:`step`.

    ``q0``: the arm's pose at time 0 (default: the description's home).
    Raises :class:`ConfigError` if the model cannot be built or loaded.
    """

    def __init__(self, desc: RobotDescription, settings: PhysicsSettings | None = None,
                 q0: np.ndarray | None = None) -> None:
        self.desc = desc
        self.settings = s = settings if settings is not None else PhysicsSettings()
        params = mjcf.ModelParams(
            timestep_s=s.timestep_s, shapes=tuple(s.shapes), skeleton_radius_m=s.skeleton_radius_m,
            armature_kg_m2=s.armature_kg_m2, servo_error_rad=s.servo_error_rad, servo_damping_s=s.servo_damping_s,
            cushion_thickness_m=s.cushion_thickness_m, cushion_half_width_m=s.cushion_half_width_m,
            cushion_solref=(s.cushion_timeconst_s, s.cushion_dampratio), cushion_solimp=mjcf.CUSHION_SOLIMP,
            friction=s.friction,
            slots={"finger": s.fingers, "palm": s.palms, "forearm": s.forearms})
        self.xml, self.layout = mjcf.build(desc, params)
        # MuJoCo's own warnings go to this log instead of stdout and a MUJOCO_LOG.TXT in the working directory
        # (process-wide; the world turns the ones that matter into WorldUnstable itself).
        mujoco.set_mju_user_warning(_mujoco_warning)
        try:
            self.model = mujoco.MjModel.from_xml_string(self.xml)
        except (ValueError, mujoco.FatalError) as exc:
            raise ConfigError(f"physics world: MuJoCo cannot load the model built from {desc.urdf_path}: "
                              f"{exc}") from exc
        self.data = mujoco.MjData(self.model)
        m, d = self.model, self.data
        self.n = n = len(desc.joints)
        self.timestep_ns = round(s.timestep_s * 1e9)
        self._time_ns = 0

        self._arm_geoms = np.array([m.geom(g).id for g in self.layout.arm_geoms + self.layout.pad_geoms], dtype=int)
        self._pad_of_geom = np.full(m.ngeom, -1, dtype=int)
        self._pad_geom_ids = np.array([m.geom(name).id for name in self.layout.pad_geoms], dtype=int)
        for pad, geom in enumerate(self._pad_geom_ids):
            self._pad_of_geom[geom] = pad
        # The pads that cover each housing: those on the same body (the same link, or a link fixed to it).
        self._covering: dict[int, np.ndarray] = {}
        for name in self.layout.arm_geoms:
            geom = m.geom(name).id
            pads = [p for p, g in enumerate(self._pad_geom_ids) if m.geom_bodyid[g] == m.geom_bodyid[geom]]
            if pads:
                self._covering[geom] = np.array(pads, dtype=int)
        self._slots: list[_Slot] = []
        self._slot_of_geom = np.full(m.ngeom, -1, dtype=int)
        for name, kind in self.layout.slots:
            body = m.body(name).id
            joint = m.body_jntadr[body]
            slot = _Slot(name=name, kind=kind, spec=KINDS[kind], region=region_of(kind), body=body,
                         geom=m.geom(name).id, qadr=int(m.jnt_qposadr[joint]), dadr=int(m.jnt_dofadr[joint]),
                         origin=np.array(m.body_pos[body]))
            self._slot_of_geom[slot.geom] = len(self._slots)
            self._slots.append(slot)
        self._by_name: dict[str, _Slot] = {}

        q_start = np.array(desc.home if q0 is None else q0, dtype=float)
        if q_start.shape != (n,) or not np.isfinite(q_start).all():
            raise ConfigError(f"physics world: q0 = {q_start.tolist()}; expected {n} finite joint angles (rad)")
        if ((q_start < desc.q_min) | (q_start > desc.q_max)).any():
            raise ConfigError(f"physics world: q0 = {q_start.tolist()} is outside the joint ranges "
                              f"[{desc.q_min.tolist()}, {desc.q_max.tolist()}]")
        d.qpos[:n] = q_start
        d.ctrl[:n] = q_start
        mujoco.mj_forward(m, d)
        self._q_command = q_start.copy()
        self._dq_command = np.zeros(n)
        self._changed_ns = 0  # when the command last changed, and the interval before that
        self._interval_ns = 0

        self._area_m2 = np.full(len(desc.pads), s.effective_area_cm2 * 1e-4)
        self._cushion_face_cm2 = (2.0 * s.cushion_half_width_m) ** 2 * 1e4
        self.sampler = SkinSampler(len(desc.pads), rate_hz=s.skin_rate_hz, latency_s=s.skin_latency_s,
                                   noise_hpa=s.skin_noise_hpa, base_hpa=s.skin_base_hpa,
                                   spread_hpa=s.skin_spread_hpa, seed=s.seed, mean=s.skin_sample == "mean")
        self._pad_force = np.zeros(len(desc.pads))
        self._pressure = np.zeros(len(desc.pads))
        self._contacts: list[tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray, float]] = []
        self._geom_names = [m.geom(g).name for g in range(m.ngeom)]
        self._arm = self._arm_state()
        self._stopped: str | None = None
        self._warnings = [int(d.warning[w].number) for w, _ in _WATCHED]
        self._v_max = np.asarray(desc.v_max, dtype=float)
        self._energy_ceiling = self._kinetic_ceiling()
        self._contact_buffer = np.zeros(6)
        self._mv = np.zeros(m.nv)

    # ------------------------------------------------------------------ time

    @property
    def time_ns(self) -> int:
        """World time, ns since the world started (``steps * timestep_ns``)."""
        return self._time_ns

    @property
    def stopped(self) -> str | None:
        """Why the world stopped, or None while it runs."""
        return self._stopped

    # ------------------------------------------------------------------ stepping

    def step(self, q_command: Any, dq_command: Any = None) -> None:
        """Advance one time step, the servos tracking ``q_command`` (rad; clipped to the joint ranges) and
        ``dq_command`` (rad/s; clipped to the speed limits; None: the command's own rate of change).

        :class:`SafetyError` for a command that is not ``n`` finite numbers (nothing moves);
        :class:`WorldUnstable` when the step diverged (the readings stay the last good step's).
        """
        if self._stopped is not None:
            raise WorldUnstable(f"the physics world stopped at t = {self._time_ns / 1e9:.4f} s: {self._stopped}")
        q = np.clip(self._vector(q_command, "q_command"), self.desc.q_min, self.desc.q_max)
        now_ns = self._time_ns + self.timestep_ns
        if dq_command is None:
            dq = self._command_rate(q, now_ns)
        else:
            dq = self._vector(dq_command, "dq_command")
        m, d, n = self.model, self.data, self.n
        d.ctrl[:n] = q
        d.ctrl[n:2 * n] = np.clip(dq, -self._v_max, self._v_max)
        self._q_command = q
        self._pull()
        mujoco.mj_step(m, d)
        problem = self._health()
        if problem is not None:
            self._stopped = problem
            log.error("physics world stopped at t = %.4f s: %s", now_ns / 1e9, problem)
            raise WorldUnstable(f"the physics world diverged at t = {now_ns / 1e9:.4f} s: {problem}; "
                                "its readings are those of the step before")
        self._time_ns = now_ns
        self._read_contacts()
        self._arm = self._arm_state()
        self.sampler.observe(now_ns, self._pressure)

    def run(self, q_command: Any, seconds: float, dq_command: Any = None) -> None:
        """Step for ``seconds`` (rounded to whole steps) with one command."""
        for _ in range(round(seconds * 1e9 / self.timestep_ns)):
            self.step(q_command, dq_command)

    def _vector(self, value: Any, what: str) -> np.ndarray:
        try:
            out = np.array(value, dtype=float)
        except (TypeError, ValueError):
            raise SafetyError(f"{what} = {value!r} is not a vector of numbers; nothing moved") from None
        if out.shape != (self.n,) or not np.isfinite(out).all():
            raise SafetyError(f"{what} = {out.tolist()}; expected {self.n} finite numbers; nothing moved")
        return out

    def _command_rate(self, q: np.ndarray, now_ns: int) -> np.ndarray:
        """The command's speed: its last change over the time that took, until the next change is late."""
        if not np.array_equal(q, self._q_command):
            self._interval_ns = now_ns - self._changed_ns
            self._dq_command = (q - self._q_command) / (self._interval_ns * 1e-9)
            self._changed_ns = now_ns
        elif now_ns - self._changed_ns > self._interval_ns:
            self._dq_command = np.zeros(self.n)
        return self._dq_command

    def _pull(self) -> None:
        """Each body part's owner pulls it toward its target: a clipped spring-damper, as joint forces."""
        d = self.data
        for slot in self._by_name.values():
            push = slot.k * (slot.target - slot.position(d)) - slot.c * slot.velocity(d)
            size = math.sqrt(float(push @ push))
            if size > slot.fmax:
                push *= slot.fmax / size
            slot.push = push
            d.qfrc_applied[slot.dadr:slot.dadr + 3] = slot.rotation.T @ push

    # ------------------------------------------------------------------ checks

    def _kinetic_ceiling(self) -> float:
        """The most kinetic energy the arm at ``max_speed_factor`` times its speed limits and every body part at
        ``max_body_speed_m_s`` can hold, J: an upper bound from the inertias (the largest eigenvalue of the mass
        matrix is below its trace, each diagonal entry below the armature plus every body's mass at the arm's
        whole reach and its own rotational inertia)."""
        m, s = self.model, self.settings
        arm_bodies = [b for b in range(1, m.nbody) if m.body_dofnum[b] and m.body_dofadr[b] < self.n]
        reach = float(sum(np.linalg.norm(m.body_pos[b]) for b in arm_bodies)) + 0.5
        per_joint = s.armature_kg_m2 + sum(float(m.body_mass[b]) * reach ** 2 + float(m.body_inertia[b].sum())
                                          for b in arm_bodies)
        speeds = (s.max_speed_factor * self._v_max) ** 2
        people = sum(0.5 * slot.spec.mass_kg * s.max_body_speed_m_s ** 2 for slot in self._slots)
        return 0.5 * self.n * per_joint * float(speeds.sum()) + people

    def _health(self) -> str | None:
        m, d, n, s = self.model, self.data, self.n, self.settings
        for index, (warning, meaning) in enumerate(_WATCHED):
            count = int(d.warning[warning].number)
            if count > self._warnings[index]:
                self._warnings[index] = count
                return f"MuJoCo reported {meaning}"
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            return "the state is not finite (NaN or inf in the positions or speeds)"
        ratio = np.abs(d.qvel[:n]) / self._v_max
        worst = int(np.argmax(ratio))
        if ratio[worst] > s.max_speed_factor:
            return (f"joint {self.desc.joints[worst]} moves at {d.qvel[worst]:.3g} rad/s, beyond "
                    f"{s.max_speed_factor} x its limit {self._v_max[worst]:.3g} rad/s")
        for slot in self._by_name.values():
            v = d.qvel[slot.dadr:slot.dadr + 3]
            speed = math.sqrt(float(v @ v))
            if speed > s.max_body_speed_m_s:
                name = slot.part.name if slot.part else slot.name
                return f"body part {name} moves at {speed:.3g} m/s, beyond max_body_speed_m_s = {s.max_body_speed_m_s}"
        mujoco.mj_mulM(m, d, self._mv, d.qvel)
        energy = 0.5 * float(d.qvel @ self._mv)
        if energy > self._energy_ceiling:
            return (f"the kinetic energy grew to {energy:.4g} J, beyond the {self._energy_ceiling:.4g} J the arm "
                    "and the people can hold at their speed limits")
        if d.ncon:
            deepest = float(-d.contact.dist.min())
            if deepest > s.max_penetration_m:
                return (f"a contact is {deepest * 1000:.1f} mm deep, beyond max_penetration_m = "
                        f"{s.max_penetration_m * 1000:.1f} mm (a body passing through the arm)")
        return None

    # ------------------------------------------------------------------ contacts

    def _read_contacts(self) -> None:
        """Contacts between people and the arm: forces on each body part, each pad's force and pressure."""
        m, d = self.model, self.data
        dt = self.timestep_ns * 1e-9
        pad_force = np.zeros(len(self.desc.pads))
        raw: list[tuple[int, int, int, np.ndarray, np.ndarray, np.ndarray, float]] = []
        per_slot: dict[int, dict[int, list[float]]] = {}
        for slot in self._by_name.values():
            slot.force = np.zeros(3)
        if d.ncon:
            contact = d.contact
            pairs, frames, dists = contact.geom, contact.frame, contact.dist
            for i in range(d.ncon):
                g1, g2 = int(pairs[i, 0]), int(pairs[i, 1])
                index, arm, sign = int(self._slot_of_geom[g2]), g1, 1.0
                if index < 0:
                    index, arm, sign = int(self._slot_of_geom[g1]), g2, -1.0
                if index < 0:
                    continue
                mujoco.mj_contactForce(m, d, i, self._contact_buffer)
                frame = frames[i].reshape(3, 3)
                force = sign * (frame.T @ self._contact_buffer[:3])  # on the person
                normal_n = float(self._contact_buffer[0])
                slot = self._slots[index]
                slot.force += force
                normal = sign * frame[0]  # from the arm into the person
                pad = int(self._pad_of_geom[arm])
                if pad < 0 and arm in self._covering:
                    pad = self._facing_pad(self._covering[arm], contact.pos[i], normal)
                if pad >= 0:
                    pad_force[pad] += normal_n
                depth = max(-float(dists[i]), 0.0)
                entry = per_slot.setdefault(index, {}).setdefault(arm, [0.0, 0.0])
                entry[0] += normal_n
                entry[1] = max(entry[1], depth)
                raw.append((index, arm, pad, contact.pos[i].copy(), normal, force, depth))
        for index, geoms in per_slot.items():
            slot = self._slots[index]
            tissue_m_per_n = 1.0 / (slot.region.spring_n_mm * 1000.0)
            area = 0.0
            for arm, (normal_n, depth) in geoms.items():
                cut = slot.spec.contact_area_cm2(depth + normal_n * tissue_m_per_n)
                area += min(cut, self._cushion_face_cm2) if self._pad_of_geom[arm] >= 0 else cut
            slot.area_cm2 = area
            slot.pads = tuple(sorted({pad for (i, _, pad, *_) in raw if i == index and pad >= 0}))
            size = math.sqrt(float(slot.force @ slot.force))
            slot.peak_force = max(slot.peak_force, size)
            slot.peak_pressure = max(slot.peak_pressure, size / area)
            slot.energy += max(float(slot.force @ slot.velocity(d)), 0.0) * dt
        for index, slot in enumerate(self._slots):
            if slot.part is not None:
                slot.at = slot.position(d)
                if index not in per_slot:
                    slot.area_cm2, slot.pads = 0.0, ()
        self._pad_force = pad_force
        self._pressure = pressure_from_force(pad_force, self._area_m2, self.settings.saturation_hpa)
        self._contacts = raw

    def _facing_pad(self, pads: np.ndarray, point: np.ndarray, normal: np.ndarray) -> int:
        """Of ``pads``, the one whose outward normal is within 90 degrees of the contact's ``normal`` and whose
        surface point is nearest ``point``; -1 if none faces it. From the cushions' poses at the contacts' step."""
        d = self.data
        best, best_distance = -1, math.inf
        half = self.settings.cushion_thickness_m / 2.0
        for pad in pads:
            geom = self._pad_geom_ids[pad]
            axes = d.geom_xmat[geom].reshape(3, 3)
            outward = axes[:, 2]
            if float(outward @ normal) <= 0.0:
                continue
            offset = d.geom_xpos[geom] + outward * half - point
            distance = float(offset @ offset)
            if distance < best_distance:
                best, best_distance = int(pad), distance
        return best

    # ------------------------------------------------------------------ readings

    def _arm_state(self) -> ArmState:
        d, n = self.data, self.n
        return ArmState(time_ns=self._time_ns, q=d.qpos[:n].copy(), dq=d.qvel[:n].copy(),
                        tau=d.qfrc_actuator[:n].copy(), tau_external=d.qfrc_constraint[:n].copy(),
                        q_command=self._q_command.copy())

    def arm(self) -> ArmState:
        """The arm after the last good step."""
        return self._arm

    def skin(self) -> list[SkinSample]:
        """The skin samples delivered since the last call, oldest first."""
        return self.sampler.delivered(self._time_ns)

    def pressure_hpa(self) -> np.ndarray:
        """Each pad's pressure change now (hPa, noise-free, no latency), pad id order."""
        return self._pressure.copy()

    def pad_force_n(self) -> np.ndarray:
        """The normal force on each pad's cushion now (N), pad id order."""
        return self._pad_force.copy()

    def touches(self) -> list[Touch]:
        """Every contact between a body part and the arm in the last step."""
        out = []
        for index, arm, pad, point, normal, force, depth in self._contacts:
            slot = self._slots[index]
            out.append(Touch(person=slot.part.name if slot.part else slot.name, geom=self._geom_names[arm],
                             pad=pad if pad >= 0 else None, point=point.copy(), normal=normal.copy(),
                             force=force.copy(), depth_m=depth))
        return out

    def people(self) -> dict[str, PersonReport]:
        """Each body part in the world, by name."""
        out = {}
        for name, slot in self._by_name.items():
            size = float(np.linalg.norm(slot.force))
            out[name] = PersonReport(
                name=name, kind=slot.kind, region=slot.region, position=slot.at.copy(),
                target=slot.target.copy(), pads=slot.pads, force_n=size, push_n=float(np.linalg.norm(slot.push)),
                area_cm2=slot.area_cm2, pressure_n_cm2=size / slot.area_cm2 if slot.area_cm2 > 0 else 0.0,
                peak_force_n=slot.peak_force, peak_pressure_n_cm2=slot.peak_pressure, energy_j=slot.energy)
        return out

    def pad_surface(self, pad: int | str) -> tuple[np.ndarray, np.ndarray]:
        """A pad's cushion surface point and outward normal now (base frame), as the model places them."""
        p = self.desc.pad(pad)
        m, d = self.model, self.data
        mujoco.mj_kinematics(m, d)
        geom = m.geom(self.layout.pad_geoms[p.id]).id
        rotation = d.geom_xmat[geom].reshape(3, 3)
        normal = rotation[:, 2].copy()
        return d.geom_xpos[geom] + normal * self.settings.cushion_thickness_m / 2.0, normal

    def force_for_pressure(self, change_hpa: float) -> float:
        """The normal force (N) on a pad that gives a pressure change ``change_hpa`` (the inverse skin model)."""
        return force_for_pressure(change_hpa, self.settings.effective_area_cm2 * 1e-4, self.settings.saturation_hpa)

    # ------------------------------------------------------------------ people

    def add(self, part: BodyPart) -> None:
        """Put a body part into the world (between steps). :class:`ConfigError` if its name is taken, a vector is
        not finite, its push is beyond a plausible one, no slot of its kind is free, or it starts inside the arm."""
        if not part.name or part.name in self._by_name:
            raise ConfigError(f"physics world: a body part needs a new name; {part.name!r} is "
                              + ("taken" if part.name else "empty"))
        spec = KINDS.get(part.kind)
        if spec is None:
            raise ConfigError(f"physics world: {part.name} is a {part.kind!r}; expected one of {', '.join(KINDS)}")
        position = _finite(part.position, f"{part.name}.position")
        target = _finite(part.target, f"{part.name}.target")
        facing = _finite(part.facing, f"{part.name}.facing")
        if np.linalg.norm(facing) < 1e-9:
            raise ConfigError(f"physics world: {part.name}.facing = {part.facing}; expected a direction")
        along = None if part.along is None else _finite(part.along, f"{part.name}.along")
        k = self.settings.person_stiffness_n_m if part.stiffness_n_m is None else float(part.stiffness_n_m)
        if not (math.isfinite(k) and 10.0 <= k <= 20000.0):
            raise ConfigError(f"physics world: {part.name}.stiffness_n_m = {k}; expected 10 to 20000 N/m "
                              "(a person's arm is a few hundred)")
        fmax = spec.plausible_push_n if part.max_force_n is None else float(part.max_force_n)
        if not (math.isfinite(fmax) and 0.0 < fmax <= spec.plausible_push_n):
            raise ConfigError(f"physics world: {part.name} would push with up to {fmax} N, beyond a plausible push "
                              f"with a {part.kind} ({spec.plausible_push_n} N); lower max_force_n")
        slot = next((s for s in self._slots if s.kind == part.kind and s.part is None), None)
        if slot is None:
            count = sum(1 for s in self._slots if s.kind == part.kind)
            raise ConfigError(f"physics world: no free {part.kind} for {part.name!r}: all {count} are in the world; "
                              f"raise world.physics.{part.kind}s")
        rotation = _orientation(spec, facing, along)
        m, d = self.model, self.data
        m.body_pos[slot.body] = position
        m.body_quat[slot.body] = _quaternion(rotation)
        d.qpos[slot.qadr:slot.qadr + 3] = 0.0
        d.qvel[slot.dadr:slot.dadr + 3] = 0.0
        self._enable(slot, True)
        mujoco.mj_kinematics(m, d)
        deepest, where = 0.0, ""
        for geom in self._arm_geoms:
            distance = mujoco.mj_geomDistance(m, d, slot.geom, int(geom), 0.01, None)
            if distance < deepest:
                deepest, where = distance, m.geom(int(geom)).name
        if deepest < -_TOUCHING_M:
            self._park(slot)
            raise ConfigError(f"physics world: {part.kind} {part.name!r} at {position.round(4).tolist()} starts "
                              f"{-deepest * 1000:.1f} mm inside the arm ({where}); start it outside the arm and "
                              "let its target bring it in")
        slot.part = part
        slot.at = position.copy()
        slot.rotation = rotation
        slot.origin = position.copy()
        slot.target = target
        slot.k = k
        slot.c = 2.0 * self.settings.person_damping_ratio * math.sqrt(k * spec.mass_kg)
        slot.fmax = fmax
        slot.push = np.zeros(3)
        slot.force = np.zeros(3)
        slot.area_cm2, slot.pads, slot.peak_force, slot.peak_pressure, slot.energy = 0.0, (), 0.0, 0.0, 0.0
        self._by_name[part.name] = slot

    def press(self, name: str, pad: int | str, force_n: float, *, kind: Literal["finger", "palm", "forearm"] = "finger",
              clearance_m: float = 0.0, stiffness_n_m: float | None = None) -> BodyPart:
        """A body part that presses ``pad`` at its centre along its normal with ``force_n`` (N): it starts
        ``clearance_m`` off the surface (default: on it, so that it presses without striking it) and its target
        lies ``force_n / k`` behind the surface. Returns the part added."""
        spec = KINDS[kind]
        if not (math.isfinite(force_n) and 0.0 < force_n <= spec.plausible_push_n):
            raise ConfigError(f"physics world: a {kind} pressing with {force_n} N is beyond a plausible push "
                              f"(0 to {spec.plausible_push_n} N)")
        k = self.settings.person_stiffness_n_m if stiffness_n_m is None else stiffness_n_m
        point, normal = self.pad_surface(pad)
        geom = self.model.geom(self.layout.pad_geoms[self.desc.pad(pad).id]).id
        along = self.data.geom_xmat[geom].reshape(3, 3)[:, 0]
        part = BodyPart(name=name, kind=kind, position=_tuple(point + normal * (spec.extent_m + clearance_m)),
                        target=_tuple(point + normal * (spec.extent_m - force_n / k)), facing=_tuple(-normal),
                        along=_tuple(along), stiffness_n_m=k)
        self.add(part)
        return part

    def retarget(self, name: str, target: Any) -> None:
        """Move a body part's target (between steps)."""
        self._slot(name).target = _finite(target, f"{name}.target")

    def remove(self, name: str) -> None:
        """Take a body part out of the world (between steps)."""
        slot = self._slot(name)
        del self._by_name[name]
        self._park(slot)

    def _slot(self, name: str) -> _Slot:
        slot = self._by_name.get(name)
        if slot is None:
            raise ConfigError(f"physics world: no body part {name!r}; there are {sorted(self._by_name) or 'none'}")
        return slot

    def _enable(self, slot: _Slot, on: bool) -> None:
        m = self.model
        contype, conaffinity = (mjcf.PERSON_CONTYPE, mjcf.PERSON_CONAFFINITY) if on else (0, 0)
        m.geom_contype[slot.geom] = contype
        m.geom_conaffinity[slot.geom] = conaffinity
        # MuJoCo's broadphase filters bodies by the union of their geoms' bits, computed when compiling.
        m.body_contype[slot.body] = contype
        m.body_conaffinity[slot.body] = conaffinity

    def _park(self, slot: _Slot) -> None:
        m, d = self.model, self.data
        self._enable(slot, False)
        home = np.array([float(self._slots.index(slot) + 1), 0.0, mjcf.PARK_Z])
        m.body_pos[slot.body] = home
        m.body_quat[slot.body] = (1.0, 0.0, 0.0, 0.0)
        d.qpos[slot.qadr:slot.qadr + 3] = 0.0
        d.qvel[slot.dadr:slot.dadr + 3] = 0.0
        d.qfrc_applied[slot.dadr:slot.dadr + 3] = 0.0
        slot.part = None
        slot.origin = home
        slot.rotation = np.eye(3)


def _mujoco_warning(message: str) -> None:
    log.warning("MuJoCo: %s", message)


def _finite(value: Any, what: str) -> np.ndarray:
    out = np.array(value, dtype=float)
    if out.shape != (3,) or not np.isfinite(out).all():
        raise ConfigError(f"physics world: {what} = {value!r}; expected three finite numbers (m, base frame)")
    return out


def _tuple(v: np.ndarray) -> Vector:
    return (float(v[0]), float(v[1]), float(v[2]))


def _orientation(spec: KindSpec, facing: np.ndarray, along: np.ndarray | None) -> np.ndarray:
    """The body's rotation: a box's -z face toward ``facing``; a capsule's axis square to it (along ``along``)."""
    facing = facing / np.linalg.norm(facing)
    if spec.geom == "sphere":
        return np.eye(3)
    if spec.geom == "box":
        return mjcf.rotation_with_z(-facing, along)
    axis = mjcf.rotation_with_z(facing, along)[:, 0]  # square to facing, as close to along as allowed
    return mjcf.rotation_with_z(axis, facing)


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_mat2Quat(out, np.ascontiguousarray(rotation).ravel())
    return out
