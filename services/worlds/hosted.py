"""The physics world as the bridge hosts it: on the bridge's clock, a touch script's touches as fingers.

A pure core, like the world it wraps (:class:`~nwr.services.worlds.physics.PhysicsWorld`):
no clock, no thread, no network. The bridge's ``physics`` backend
(:mod:`nwr.services.bridge.backends.physics`) calls it; live, lockstep and
``nwr verify`` run this one piece of code, so the same inputs (the
bridge's journal: its cycles' times, the commands, the touches) give the
same world, bit for bit.

- **Time.** World time 0 is the bridge time of the first :meth:`advance`.
  Each call steps the world at its fixed step up to the bridge time it is
  given, with the command of the moment (the bridge's last setpoint). A
  late cycle catches up at most ``max_catch_up_s`` of steps; the rest is
  skipped (the world's clock falls behind the bridge's by that much, counted
  in :attr:`HostedWorld.lost_ns`), never run in a burst that would look like
  a jump. A step's bridge time counts back from the call's (its last step
  is at the bridge time given): the touches keep the script's clock and the
  samples the bridge's, however much world time was lost.
- **Touches.** Each touch of a touch script (the gateway's ground truth on
  ``skin/touch``) becomes a finger on its pad (:meth:`touch`): it enters
  where the pad is when the touch reaches the bridge, presses along the
  pad's normal with the force that makes the script's pressure on a pad
  that stays put (:meth:`PhysicsWorld.force_for_pressure`, following the
  script's profile: a ramp's target moves deeper step by step), and stays
  where its owner holds it: a pad that moves into it presses harder, one
  that withdraws loses it. A touch with ``follow_m_s`` (a finger that
  follows the arm) is held on the pad instead: the point its owner holds it
  at (its *anchor*) moves toward where it would rest on the pad now, along
  the pad's normal now, at most ``follow_m_s`` per second (a person's hand
  keeping up with a moving surface; :data:`~nwr.common.launch.MAX_FOLLOW_M_S`
  at most), so that the script's force is applied however the task carries
  the pad, a pad that moves into it faster than that presses harder, and
  one that withdraws faster loses it. At the touch's end its target moves
  off the pad (:data:`LIFT_M`; a following finger stops following), and the
  finger leaves the world :data:`LINGER_S` later. A touch's ``body_area``
  (the ISO/TS 15066 body area it names) is checked here and judged by in
  the force figures (:func:`nwr.services.tools.recordings.analysis.world_figures`);
  the world's finger stays a finger (its shape, mass and tissue spring).
- **Outputs.** Each skin sample the world delivers (``world/skin``, the
  device's absolute pressures) and, while any body part is in the world,
  their contact figures (``world/contacts``), stamped with the bridge time
  of the world step that made them.
- **A taxel skin** (:meth:`use_taxels`, ``robot.skin = "taxels"``): the
  world's contacts read by the taxels (:class:`~nwr.services.worlds.taxels.WorldTaxels`,
  a finger's width each) and sampled at ``taxel_rate_hz`` (1 kHz by
  default) with the pads' conventions where they apply: ``skin_sample``
  ("instant" or "mean"), ``skin_latency_s``, and ``skin_noise_hpa`` of white
  noise (in the skin's unit; a taxel reports over its own baseline: no base,
  no spread, and never below 0: noise under the baseline reads 0, as the
  absolute pressures of ``skin/pressure`` are never negative). Each sample
  goes out on ``world/skin`` as ``taxels`` (the pad lists empty); the
  pads' samples are no longer published, but each one's step still
  publishes the contact figures, so ``world/contacts`` keeps the pads' rate
  whatever the skin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import ConfigError
from nwr.common.launch import MAX_FOLLOW_M_S, Touch, TouchScript
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.skin import hpa_per_unit
from nwr.common.taxels import TaxelSkin
from nwr.services.gateway.core import touch_profile
from nwr.services.gateway.taxels import FINGER_RADIUS_M
from nwr.services.worlds.people import ISO_TS_15066, KINDS
from nwr.services.worlds.physics import BodyPart, PhysicsSettings, PhysicsWorld
from nwr.services.worlds.settings import check_taxel_rate
from nwr.services.worlds.skin import SkinSampler, force_for_pressure
from nwr.services.worlds.taxels import WorldTaxels

# At a touch's end its finger's target moves this far off the pad, m; it leaves the world LINGER_S later.
LIFT_M = 0.03
LINGER_S = 0.3
# The most world time one advance catches up, s (a longer stall loses the rest).
MAX_CATCH_UP_S = 0.05


def touch_of(msg: m.SkinTouch) -> Touch:
    """The touch script's touch a ``skin/touch`` message carries."""
    return Touch(pad=msg.name, start_s=msg.start_s, duration_s=msg.duration_s, peak_hpa=msg.peak_hpa,
                 shape=msg.shape, ramp_s=msg.ramp_s, follow_m_s=msg.follow_m_s,
                 body_area=msg.body_area)


def touch_end_s(touch: Touch) -> float:
    """When a touch presses no more, script time, s."""
    return touch.start_s + touch.duration_s + (2 * touch.ramp_s if touch.shape == "ramp" else 0.0)


def check_script(script: TouchScript, settings: PhysicsSettings, desc: RobotDescription,
                 q0: np.ndarray | None = None) -> None:
    """A touch script's touches as the physics world's fingers: ConfigError for a pad the skin lacks, a push
    no finger makes (a peak beyond the pressure a finger's plausible push gives), more fingers at once than
    the world holds, or (with the arm's starting pose ``q0``) a finger that would start inside the arm on its
    pad there (another link over it). Before anything moves (a launcher)."""
    area_m2, saturation = settings.effective_area_cm2 * 1e-4, settings.saturation_hpa
    plausible = KINDS["finger"].plausible_push_n
    limit_hpa = float(saturation * math.tanh(plausible / (area_m2 * 100.0 * saturation)))
    names = {p.name: p.id for p in desc.pads}
    for touch in script.touch:
        if touch.body_area and touch.body_area not in ISO_TS_15066:
            raise ConfigError(f"touch on {touch.pad} at {touch.start_s} s names body_area {touch.body_area!r}; "
                              f"ISO/TS 15066's are {', '.join(ISO_TS_15066)}")
        if touch.pad not in names and not (touch.pad.isdigit() and int(touch.pad) < len(desc.pads)):
            raise ConfigError(f"touch script names pad {touch.pad!r}; the skin has {sorted(names)}")
        force = finger_force(touch.peak_hpa, settings)
        if not (math.isfinite(force) and force <= plausible):
            raise ConfigError(f"touch on {touch.pad} at {touch.start_s} s: a peak of {touch.peak_hpa} hPa takes "
                              f"{force:.1f} N of finger force in the physics world, beyond a finger's plausible "
                              f"push of {plausible:.0f} N ({limit_hpa:.1f} hPa); lower peak_hpa")
    spans = sorted((t.start_s, touch_end_s(t) + LINGER_S) for t in script.touch)
    for i, (start, _) in enumerate(spans):
        at_once = sum(1 for s, e in spans[:i + 1] if e > start)
        if at_once > settings.fingers:
            raise ConfigError(f"the touch script has {at_once} touches at once at {start} s; the physics world "
                              f"holds {settings.fingers} fingers (raise bridge.physics.fingers)")
    if q0 is not None and script.touch:
        world = PhysicsWorld(desc, settings, q0)
        for touch in script.touch:
            pad = desc.pad(int(touch.pad) if touch.pad.isdigit() else touch.pad).id
            try:
                world.press("check", pad, max(finger_force(touch.peak_hpa, settings), 1e-3))
            except ConfigError as exc:
                raise ConfigError(f"touch on {touch.pad} at {touch.start_s} s, at the arm's starting pose: "
                                  f"{exc}") from None
            world.remove("check")


def finger_force(change_hpa: float, settings: PhysicsSettings) -> float:
    """The finger force (N) that makes ``change_hpa`` on a pad (inf beyond the pad's saturation)."""
    if change_hpa <= 0.0:
        return 0.0
    if change_hpa >= settings.saturation_hpa:
        return math.inf
    return force_for_pressure(change_hpa, settings.effective_area_cm2 * 1e-4, settings.saturation_hpa)


@dataclass(eq=False)
class _Finger:
    """A touch's finger: the touch, its script clock's zero (bridge time), its part as it entered, where its
    owner holds it (``anchor``: where it entered, or for a following finger where it caught up with the pad)."""

    name: str
    seq: int
    touch: Touch
    origin_ns: int
    part: BodyPart
    into: np.ndarray  # the direction it presses in (-normal of the pad)
    k: float
    pad: int
    anchor: np.ndarray
    peak_pushed: float = 0.0
    lifted: bool = False  # its touch has ended: its target is off the pad

    def script_s(self, bridge_ns: int) -> float:
        return (bridge_ns - self.origin_ns) / 1e9

    def target(self, force_n: float) -> np.ndarray:
        return self.anchor + self.into * (force_n / self.k)

    def pushed(self, at: np.ndarray) -> float:
        """How far the arm pushed it back from where its owner holds it, along the pad's outward normal, m."""
        return float((self.anchor - at) @ self.into)


class HostedWorld:
    """A :class:`PhysicsWorld` on the bridge's clock, touched by a touch script's fingers."""

    def __init__(self, desc: RobotDescription, settings: PhysicsSettings, q0: np.ndarray,
                 max_catch_up_s: float = MAX_CATCH_UP_S) -> None:
        self.desc = desc
        self.settings = settings
        self.world = PhysicsWorld(desc, settings, q0)
        self.step_ns = self.world.timestep_ns
        self.max_steps = max(1, round(max_catch_up_s * 1e9 / self.step_ns))
        self.origin_ns: int | None = None  # the bridge time of world time 0 (moved on by lost time)
        self.lost_ns = 0
        self.fingers: dict[str, _Finger] = {}
        self.skin_seq = 0
        self.contacts_seq = 0
        self.taxels: WorldTaxels | None = None
        self.taxel_sampler: SkinSampler | None = None

    def use_taxels(self, skin: TaxelSkin) -> None:
        """Publish a taxel skin's samples instead of the pads' (before the first :meth:`advance`); ConfigError
        for a rate above the world's step rate."""
        s = self.settings
        if self.origin_ns is not None:
            raise ConfigError("the physics world's skin is chosen before it starts")
        check_taxel_rate(s)
        self.taxels = WorldTaxels(self.world, skin, RobotModel(self.desc), FINGER_RADIUS_M)
        self.taxel_sampler = SkinSampler(len(skin), rate_hz=s.taxel_rate_hz, latency_s=s.skin_latency_s,
                                         noise_hpa=s.skin_noise_hpa / hpa_per_unit(skin), base_hpa=0.0,
                                         spread_hpa=0.0, seed=s.seed, mean=s.skin_sample == "mean")

    def touch(self, msg: m.SkinTouch, now_ns: int) -> BodyPart:
        """A touch reached the bridge at ``now_ns``: its finger enters on its pad. ConfigError (nothing enters)
        for a pad the skin lacks, a push no finger makes, no free finger, or a finger that would start inside
        the arm."""
        if not 0 <= msg.pad < len(self.desc.pads):
            raise ConfigError(f"touch {msg.seq} on pad {msg.pad}: the skin has pads 0..{len(self.desc.pads) - 1}")
        touch = touch_of(msg)
        if touch.body_area and touch.body_area not in ISO_TS_15066:
            raise ConfigError(f"touch {msg.seq} on {msg.name}: body_area {touch.body_area!r} is none of ISO/TS "
                              "15066's: not pressed")
        if not 0.0 <= touch.follow_m_s <= MAX_FOLLOW_M_S:
            raise ConfigError(f"touch {msg.seq} on {msg.name}: follow_m_s = {touch.follow_m_s}; expected 0 to "
                              f"{MAX_FOLLOW_M_S} m/s (a hand's speed): not pressed")
        name = f"touch-{msg.seq}"
        if name in self.fingers:
            raise ConfigError(f"touch {msg.seq} is in the world already")
        peak = finger_force(touch.peak_hpa, self.settings)
        plausible = KINDS["finger"].plausible_push_n
        if not (math.isfinite(peak) and peak <= plausible):
            raise ConfigError(f"touch {msg.seq} on {msg.name}: {touch.peak_hpa} hPa takes {peak:.1f} N of finger "
                              f"force, beyond a finger's plausible push ({plausible:.0f} N): not pressed")
        part = self.world.press(name, msg.pad, max(peak, 1e-3))
        k = part.stiffness_n_m if part.stiffness_n_m is not None else self.settings.person_stiffness_n_m
        finger = _Finger(name, msg.seq, touch, msg.origin_ns, part, np.asarray(part.facing, dtype=float), k,
                         msg.pad, np.asarray(part.position))
        self.fingers[name] = finger
        self._aim(finger, now_ns)
        return part

    def advance(self, now_ns: int, q_command: np.ndarray, dq_command: np.ndarray) -> list[tuple[str, Any]]:
        """Step the world up to bridge time ``now_ns`` with the command; what it published meanwhile.
        Raises :class:`~nwr.services.worlds.physics.WorldUnstable` when a step diverged (the world stays
        stopped)."""
        world = self.world
        if self.origin_ns is None:
            self.origin_ns = now_ns - world.time_ns
        due = (now_ns - self.origin_ns - world.time_ns) // self.step_ns
        if due > self.max_steps:
            lost = (due - self.max_steps) * self.step_ns
            self.origin_ns += lost
            self.lost_ns += lost
            due = self.max_steps
        out: list[tuple[str, Any]] = []
        for i in range(max(0, due)):
            # The step's bridge time: the last step of the call is at now (a world that lost time is behind
            # the bridge's clock, the touches are not: they keep the script's clock).
            at_ns = now_ns - (due - 1 - i) * self.step_ns
            for finger in list(self.fingers.values()):
                self._aim(finger, at_ns)
            world.step(q_command, dq_command)
            if self.taxel_sampler is not None:
                self._taxel_step(at_ns, out)
                continue
            for sample in world.skin():
                stamp = at_ns - (world.time_ns - sample.delivered_ns)
                out.append((keys.WORLD_SKIN, m.WorldSkin(
                    seq=self.skin_seq, stamp_ns=stamp, world_ns=sample.taken_ns,
                    absolute_hpa=sample.absolute_hpa.tolist(), change_hpa=sample.change_hpa.tolist(),
                    force_n=world.pad_force_n().tolist())))
                self.skin_seq += 1
                if self.fingers:
                    out.append((keys.WORLD_CONTACTS, self.contacts(stamp)))
        return out

    def _taxel_step(self, at_ns: int, out: list[tuple[str, Any]]) -> None:
        """A step of a taxel skin: its sample when due, the samples delivered; the contact figures at each pad
        sample's step (the pads' rate)."""
        world, sampler, taxels = self.world, self.taxel_sampler, self.taxels
        assert sampler is not None and taxels is not None
        now = world.time_ns
        if sampler.mean:
            sampler.observe(now, taxels.readings())
        elif sampler.due(now):
            sampler.take(now, taxels.readings())
        for sample in sampler.delivered(now):
            out.append((keys.WORLD_SKIN, m.WorldSkin(
                seq=self.skin_seq, stamp_ns=at_ns - (now - sample.delivered_ns), world_ns=sample.taken_ns,
                absolute_hpa=[], change_hpa=[], force_n=[], taxels=np.maximum(sample.absolute_hpa, 0.0).tolist())))
            self.skin_seq += 1
        for sample in world.skin():
            if self.fingers:
                out.append((keys.WORLD_CONTACTS, self.contacts(at_ns - (now - sample.delivered_ns))))

    def contacts(self, stamp_ns: int) -> m.WorldContacts:
        """The body parts in the world now, with their figures."""
        people = []
        for name, report in self.world.people().items():
            finger = self.fingers.get(name)
            pushed = finger.pushed(report.position) if finger is not None else 0.0
            if finger is not None and not finger.lifted:  # the lift off the pad is the person's, not the arm's
                finger.peak_pushed = max(finger.peak_pushed, pushed)
            people.append(m.WorldPerson(
                name=name, kind=report.kind, touch=finger.seq if finger is not None else -1,
                pads=list(report.pads), force_n=report.force_n, peak_force_n=report.peak_force_n,
                pressure_n_cm2=report.pressure_n_cm2, peak_pressure_n_cm2=report.peak_pressure_n_cm2,
                energy_j=report.energy_j, pushed_m=pushed,
                peak_pushed_m=finger.peak_pushed if finger is not None else 0.0))
        seq = self.contacts_seq
        self.contacts_seq += 1
        return m.WorldContacts(seq=seq, stamp_ns=stamp_ns, world_ns=self.world.time_ns, people=people)

    def _aim(self, finger: _Finger, bridge_ns: int) -> None:
        """The finger's target at ``bridge_ns``: the script's force for its profile now, off the pad after its
        end, out of the world once it has lingered."""
        t = finger.script_s(bridge_ns)
        end = touch_end_s(finger.touch)
        if t >= end + LINGER_S:
            self.world.remove(finger.name)
            del self.fingers[finger.name]
        elif t >= end:
            finger.lifted = True
            self.world.retarget(finger.name, finger.target(-LIFT_M * finger.k))
        else:
            if finger.touch.follow_m_s > 0.0:
                self._follow(finger)
            force = finger_force(touch_profile(finger.touch, t), self.settings)
            self.world.retarget(finger.name, finger.target(force))

    def _follow(self, finger: _Finger) -> None:
        """A following finger's owner moves it on with the pad: its anchor toward where it rests on the pad now
        (the pad's surface point, out along its normal by the finger's extent), at most ``follow_m_s`` per
        step's time; it presses along the pad's normal now."""
        point, normal = self.world.pad_surface(finger.pad)
        rest = point + normal * KINDS[finger.part.kind].extent_m
        gap = rest - finger.anchor
        distance = float(np.linalg.norm(gap))
        reach = finger.touch.follow_m_s * self.step_ns / 1e9
        finger.anchor = rest if distance <= reach else finger.anchor + gap * (reach / distance)
        finger.into = -normal
