"""Skin gateway core: per-pad no-contact baseline and change from it.

The baseline follows slow drift (temperature, pad settling) while a pad is
untouched and must neither follow nor drift away during a press:

- untouched (change below ``contact_hpa``): the baseline moves toward the
  measurement with time constant ``baseline_tau_s``, but never faster than
  ``max_drift_hpa_s`` (a slow press therefore cannot drag it along);
- touched (change above ``contact_hpa``, until it falls below
  ``release_hpa``): the baseline is frozen;
- a "touch" longer than ``max_contact_s`` is taken as a new resting level
  (the pad changed, not a hand): the baseline is re-acquired and the caller
  is told so it can warn.

A non-finite reading leaves the baseline untouched; the pad is published as
invalid (``valid`` false, change 0, so it can never trigger a reflex) and
the caller is told so it can warn.

The simulated skin adds scripted touches to noise and drift. Its contact
model (:func:`contact_pressure`): the finger is a point that stays where it
met the pad; the scripted profile is what the touch presses while the pad
stays put; once the pad has withdrawn ``w`` metres from the finger along the
pad's normal at the contact, the touch presses ``(1 - w / depth)`` of it,
nothing beyond ``depth``, and never more than scripted when the pad moves
toward the finger (the hand yields: a pad cannot be pressed harder than the
person presses). Motion along the pad's surface is ignored. The live
simulated skin applies it only with ``gateway.sim.closed_loop``; a
re-simulation (:class:`Resimulator`) always does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import msgspec
import numpy as np

from nwr.common import messages as m
from nwr.common.config import GatewaySection, NonNegative, Positive
from nwr.common.errors import ConfigError
from nwr.common.launch import Touch, TouchScript
from nwr.common.robot import Pad
from nwr.common.section import Section
from nwr.services.gateway.sources import KIND as SOURCES


class SimSkinSettings(Section):
    """The simulated skin's settings: ``[gateway.sim]`` (the ``sim`` skin source's table)."""

    # Seed of the noise and drift generators (a run is reproducible).
    seed: int = 7
    # Absolute no-contact pressure of a pad, hPa (pads differ by up to +-spread).
    base_hpa: Annotated[float, msgspec.Meta(gt=0, le=5000)] = 1013.0
    spread_hpa: NonNegative = 3.0
    # White noise, standard deviation in hPa.
    noise_hpa: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.08
    # Slow drift (temperature): a random walk of this many hPa per sqrt(s),
    # plus a sine of this amplitude and period.
    drift_walk_hpa: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.02
    drift_sine_hpa: Annotated[float, msgspec.Meta(ge=0, le=10)] = 0.3
    drift_period_s: Positive = 60.0
    # Touch script (TOML, [[touch]] tables); empty = no touches.
    script: str = ""
    # Contact model: the finger stays where it met the pad; once the pad has
    # withdrawn w metres from it along the pad's normal, the touch presses
    # with (1 - w / contact_depth_m) of its scripted pressure (none beyond
    # the depth; never more than scripted when the pad moves toward it). The
    # finger's indentation of the pad's air cushion at the scripted pressure, m.
    contact_depth_m: Annotated[float, msgspec.Meta(gt=0, le=0.2)] = 0.02
    # true: the live simulated skin applies that model (closed loop: a pad
    # that withdraws feels its pressure fall); false: touches press as
    # scripted whatever the arm does (open loop, the default). Re-simulation
    # (`nwr replay --fast --resimulate`) always applies it.
    closed_loop: bool = False


def sim_settings(gateway: GatewaySection) -> SimSkinSettings:
    """The profile's ``[gateway.sim]``."""
    return SOURCES.settings(gateway, "sim", SimSkinSettings)


def with_sim(gateway: GatewaySection, **values: object) -> GatewaySection:
    """``gateway`` with fields of ``[gateway.sim]`` set (e.g. ``closed_loop=True``), checked when next read."""
    plugins = {**gateway.plugins, "sim": {**gateway.plugins.get("sim", {}), **values}}
    return msgspec.structs.replace(gateway, plugins=plugins)


@dataclass
class FilterEvents:
    reacquired: list[int]
    non_finite: list[int]


class BaselineFilter:
    """The baseline of every pad, kept pad by pad on Python floats.

    Ten pads at up to 1 kHz: a loop over floats costs a fraction of the two
    dozen numpy calls on ten-element arrays it replaces, with the same IEEE
    operations in the same order (so the same values, bit for bit; the time
    constant's exponential is still numpy's).
    """

    def __init__(self, cfg: GatewaySection, n_pads: int) -> None:
        self.cfg = cfg
        self.n = n_pads
        self._baseline = [math.nan] * n_pads
        self._contact = [False] * n_pads
        self._since = [0.0] * n_pads
        self.last_t: float | None = None

    @property
    def baseline(self) -> np.ndarray:
        return np.array(self._baseline, dtype=float)

    @property
    def contact(self) -> np.ndarray:
        return np.array(self._contact, dtype=bool)

    @property
    def contact_since(self) -> np.ndarray:
        return np.array(self._since, dtype=float)

    def resume(self, last_t: float | None, baseline: np.ndarray, contact: np.ndarray) -> None:
        """Continue from a state seen elsewhere (a recording): the baseline and contact flags
        before the next sample, and that sample's predecessor's time (None: there was none).
        A contact's start is unknown: it counts from ``last_t``."""
        self._baseline = np.array(baseline, dtype=float).tolist()
        self._contact = np.array(contact, dtype=bool).tolist()
        self._since = [0.0 if last_t is None else float(last_t)] * self.n
        self.last_t = last_t

    def update(self, t: float, absolute: np.ndarray) -> tuple[np.ndarray, FilterEvents]:
        """Feed one sample at time ``t`` (s); returns the change from baseline."""
        change, events = self.step(t, np.asarray(absolute, dtype=float).tolist())
        return np.array(change, dtype=float), events

    def step(self, t: float, absolute: list[float]) -> tuple[list[float], FilterEvents]:
        """:meth:`update` on a list of floats, returning one."""
        cfg = self.cfg
        t = float(t)
        dt = 0.0 if self.last_t is None else max(0.0, t - self.last_t)
        self.last_t = t
        baseline, contact, since = self._baseline, self._contact, self._since
        isfinite = math.isfinite
        finite = [isfinite(a) for a in absolute]
        events = FilterEvents([], [i for i, f in enumerate(finite) if not f])
        change = []
        contact_hpa, release_hpa, max_contact_s = cfg.contact_hpa, cfg.release_hpa, cfg.max_contact_s
        for i, a in enumerate(absolute):
            b = baseline[i]
            if finite[i]:
                if b != b:  # NaN: the pad's first finite reading
                    b = baseline[i] = a
                c = a - b
                if contact[i]:
                    if c < release_hpa:
                        contact[i] = False
                elif c > contact_hpa:
                    contact[i] = True
                    since[i] = t
            else:
                c = a - b
            if contact[i] and t - since[i] > max_contact_s:
                baseline[i] = a
                contact[i] = False
                c = 0.0
                events.reacquired.append(i)
            change.append(c)
        track = [i for i, f in enumerate(finite) if f and not contact[i]]
        if dt > 0 and track:
            # numpy's exponential, as before; the rest in Python floats (the same IEEE operations).
            alpha = float(1.0 - np.exp(-dt / cfg.baseline_tau_s))
            top = cfg.max_drift_hpa_s * dt
            bottom = -cfg.max_drift_hpa_s * dt
            for i in track:
                baseline[i] += min(max(alpha * change[i], bottom), top)
        return change, events


def withdrawal_m(contact_point: np.ndarray, normal: np.ndarray, pad_point: np.ndarray) -> float:
    """How far the pad has moved away from the finger at ``contact_point`` along the contact's
    outward ``normal``, m (negative: toward the finger)."""
    return float(np.dot(np.asarray(contact_point) - np.asarray(pad_point), normal))


def contact_pressure(scripted_hpa: float, withdrawal: float, depth_m: float) -> float:
    """The touch's pressure change when the pad has withdrawn ``withdrawal`` m from the finger, hPa.

    ``scripted_hpa`` (the pressure of the touch on a pad that stays put)
    times ``1 - withdrawal / depth_m``, clamped to [0, 1]: no pressure once
    the pad has withdrawn ``depth_m`` or more, and never more than scripted
    when it moves toward the finger.
    """
    if not (math.isfinite(scripted_hpa) and math.isfinite(withdrawal)):
        raise ValueError(f"contact model: scripted pressure {scripted_hpa} hPa and withdrawal {withdrawal} m "
                         "must be finite numbers")
    if not (math.isfinite(depth_m) and depth_m > 0):
        raise ValueError(f"contact model: the indentation depth must be a positive number of metres, got {depth_m}")
    return scripted_hpa * min(1.0, max(0.0, 1.0 - withdrawal / depth_m))


@dataclass
class ActiveTouch:
    """A scripted touch on pad ``pad``; once started, where the finger met the pad (base frame)."""

    pad: int
    touch: Touch
    started: bool = False
    point: np.ndarray | None = None  # None: the arm's pose was not known when it started
    normal: np.ndarray | None = None


class TouchSet:
    """The touches of a simulated skin and the pressure they make, open or closed loop.

    Every sample, :meth:`start` first (the touches that begin now meet their
    pad where it is), then :meth:`pressure`. Pad points and normals are in
    the base frame, one row per pad, or None when the arm's pose is unknown:
    a touch that started then has no contact point and presses as scripted.
    """

    def __init__(self, n_pads: int, depth_m: float, closed_loop: bool) -> None:
        self.n = n_pads
        self.depth_m = depth_m
        self.closed_loop = closed_loop
        self.touches: list[ActiveTouch] = []
        # The earliest start of a touch not yet begun (inf: none): until then no sample starts one,
        # and an open-loop skin needs no pose (a script of 60 touches is not scanned twice per sample).
        self.next_start = math.inf

    def __len__(self) -> int:
        return len(self.touches)

    def add(self, pad: int, touch: Touch) -> ActiveTouch:
        if not 0 <= pad < self.n:
            raise ConfigError(f"touch on pad {pad}: the skin has pads 0..{self.n - 1}")
        active = ActiveTouch(pad, touch)
        self.touches.append(active)
        self.next_start = min(self.next_start, touch.start_s)
        return active

    def forget_before(self, t: float) -> None:
        """Drop the touches over by ``t`` (a long session must not keep them all)."""
        self.touches = [a for a in self.touches
                        if not a.started or a.touch.start_s + a.touch.duration_s + 2 * a.touch.ramp_s >= t]

    def needs_pose(self, t: float) -> bool:
        """Whether :meth:`start` or :meth:`pressure` at ``t`` use the pads' points: a touch begins,
        or (closed loop) one with a contact point is under way. Otherwise the kinematics can wait."""
        if self.next_start <= t:
            return True  # a touch begins
        if not self.closed_loop:
            return False
        for a in self.touches:
            if a.started and a.point is not None and t <= a.touch.start_s + a.touch.duration_s + 2 * a.touch.ramp_s:
                return True
        return False

    def start(self, t: float, points: np.ndarray | None, normals: np.ndarray | None) -> list[ActiveTouch]:
        """The touches that begin at or before ``t`` and had not yet: each meets its pad where it is now."""
        out: list[ActiveTouch] = []
        if t < self.next_start:
            return out
        for a in self.touches:
            if not a.started and a.touch.start_s <= t:
                a.started = True
                if points is not None and normals is not None:
                    a.point = np.array(points[a.pad], dtype=float)
                    a.normal = np.array(normals[a.pad], dtype=float)
                out.append(a)
        self.next_start = min((a.touch.start_s for a in self.touches if not a.started), default=math.inf)
        return out

    def pressure(self, t: float, points: np.ndarray | None = None) -> np.ndarray:
        """Every pad's pressure change from the touches at time ``t``, hPa."""
        out = np.zeros(self.n)
        for a in self.touches:
            touch = a.touch
            s = t - touch.start_s
            if s < 0.0 or s >= touch.duration_s + 2 * touch.ramp_s:
                continue  # not begun or over: it presses nothing (a script holds every touch of its session)
            p = touch_profile(touch, t)
            if p and self.closed_loop and a.point is not None and a.normal is not None and points is not None:
                p = contact_pressure(p, withdrawal_m(a.point, a.normal, points[a.pad]), self.depth_m)
            out[a.pad] += p
        return out


class SimSkin:
    """Simulated AIRSKIN pads: absolute pressure with noise, drift and scripted touches."""

    def __init__(self, cfg: SimSkinSettings, pads: tuple[Pad, ...], script: TouchScript | None) -> None:
        self.cfg = cfg
        self.pads = pads
        self.rng = np.random.default_rng(cfg.seed)
        n = len(pads)
        self.base = cfg.base_hpa + self.rng.uniform(-cfg.spread_hpa, cfg.spread_hpa, n)
        self.phase = self.rng.uniform(0, 2 * np.pi, n)
        self.walk = np.zeros(n)
        self.last_t = 0.0
        self.touches = TouchSet(n, cfg.contact_depth_m, cfg.closed_loop)
        # The touches' part of the last sample, per pad (SkinPressure.touch_hpa).
        self.touch_hpa = np.zeros(n)
        if script is not None:
            by_name = {p.name: p.id for p in pads}
            for touch in script.touch:
                pad = by_name.get(touch.pad)
                if pad is None and touch.pad.isdigit() and int(touch.pad) < n:
                    pad = int(touch.pad)
                if pad is None:
                    raise ConfigError(f"touch script names pad {touch.pad!r}; the skin has {sorted(by_name)}")
                self.touches.add(pad, touch)

    def add_touch(self, pad: int, touch: Touch) -> None:
        """A touch decided while running (the study's target pad, say)."""
        # Finished touches no longer matter; keep the list short over long sessions.
        self.touches.forget_before(touch.start_s)
        self.touches.add(pad, touch)

    def start(self, t: float, points: np.ndarray | None = None,
              normals: np.ndarray | None = None) -> list[ActiveTouch]:
        """The touches that begin now; they meet their pads at ``points`` (None: the arm's pose is unknown)."""
        return self.touches.start(t, points, normals)

    def touch_pressure(self, t: float, points: np.ndarray | None = None) -> np.ndarray:
        """The touches' pressure change of every pad at time t, hPa (scripted, or closed loop at ``points``)."""
        return self.touches.pressure(t, points)

    def sample(self, t: float, points: np.ndarray | None = None) -> np.ndarray:
        cfg = self.cfg
        dt = max(0.0, t - self.last_t)
        self.last_t = t
        self.walk += self.rng.normal(0.0, cfg.drift_walk_hpa * np.sqrt(dt), len(self.pads))
        drift = self.walk + cfg.drift_sine_hpa * np.sin(2 * np.pi * t / cfg.drift_period_s + self.phase)
        noise = self.rng.normal(0.0, cfg.noise_hpa, len(self.pads))
        self.touch_hpa = self.touch_pressure(t, points)
        return self.base + drift + noise + self.touch_hpa


def touch_profile(touch: Touch, t: float) -> float:
    """Pressure change of one scripted touch at time t (0 outside it)."""
    s = t - touch.start_s
    if touch.shape == "step":
        return touch.peak_hpa if 0.0 <= s < touch.duration_s else 0.0
    r = touch.ramp_s
    if s < 0 or s >= touch.duration_s + 2 * r:
        return 0.0
    if r > 0 and s < r:
        return touch.peak_hpa * s / r
    if s < r + touch.duration_s:
        return touch.peak_hpa
    return touch.peak_hpa * (1.0 - (s - r - touch.duration_s) / r) if r > 0 else 0.0


def touch_message(seq: int, stamp_ns: int, origin_ns: int, active: ActiveTouch, pad_name: str, touches: TouchSet,
                  q: Sequence[float] | np.ndarray | None = None, pose_stamp_ns: int = 0) -> m.SkinTouch:
    """The ground truth of a touch that just started (``skin/touch``)."""
    touch = active.touch
    known = active.point is not None and active.normal is not None
    return m.SkinTouch(
        seq=seq, stamp_ns=stamp_ns, pad=active.pad, name=pad_name, origin_ns=origin_ns,
        start_s=touch.start_s, duration_s=touch.duration_s, peak_hpa=touch.peak_hpa, shape=touch.shape,
        ramp_s=touch.ramp_s,
        contact_point=active.point.tolist() if known and active.point is not None else None,
        normal=active.normal.tolist() if known and active.normal is not None else None,
        q=[float(x) for x in q] if known and q is not None else None,
        pose_stamp_ns=pose_stamp_ns if known else 0,
        closed_loop=touches.closed_loop, depth_m=touches.depth_m, follow_m_s=touch.follow_m_s,
        body_area=touch.body_area,
    )


class Gateway:
    """Turns absolute pad pressures into SkinPressure messages."""

    def __init__(self, cfg: GatewaySection, n_pads: int, source: str = "sim") -> None:
        self.filter = BaselineFilter(cfg, n_pads)
        self.source = source
        self.seq = 0

    def process(self, t: float, stamp_ns: int, absolute: np.ndarray,
                touch_hpa: np.ndarray | None = None) -> tuple[m.SkinPressure, FilterEvents]:
        """One sample; ``touch_hpa``: a simulated skin's touches' part of ``absolute`` (ground truth)."""
        values = np.asarray(absolute, dtype=float).tolist()
        change, events = self.filter.step(t, values)
        isfinite = math.isfinite
        valid = [isfinite(c) for c in change]
        msg = m.SkinPressure(
            seq=self.seq, stamp_ns=stamp_ns,
            absolute_hpa=[a if v else 0.0 for a, v in zip(values, valid)],
            baseline_hpa=[b if isfinite(b) else 0.0 for b in self.filter._baseline],
            change_hpa=[c if v else 0.0 for c, v in zip(change, valid)],
            contact=[c and v for c, v in zip(self.filter._contact, valid)],
            valid=valid,
            source=self.source,
            touch_hpa=[] if touch_hpa is None else touch_hpa.tolist(),
        )
        self.seq += 1
        return msg, events


class TargetFollower:
    """Touches the study's target pad every ``interval_s``, cycling through pressure levels.

    The planner publishes which pad is the target (it lights up red in the
    study); a simulated participant presses it, like the study's game.
    """

    PEAKS_HPA = (9.0, 16.0, 4.0, 25.0, 12.0, 7.0)

    def __init__(self, interval_s: float, seed: int = 0) -> None:
        self.interval_s = interval_s
        self.next_s = interval_s
        self.rng = np.random.default_rng(seed)
        self.count = 0

    def poll(self, t: float, target_pad: int) -> tuple[int, Touch] | None:
        if target_pad < 0 or t < self.next_s:
            return None
        self.next_s = t + self.interval_s
        peak = self.PEAKS_HPA[self.count % len(self.PEAKS_HPA)]
        self.count += 1
        return target_pad, Touch(pad=str(target_pad), start_s=t, duration_s=0.3, peak_hpa=peak, shape="ramp",
                                 ramp_s=float(self.rng.uniform(0.05, 0.2)))


NO_GROUND_TRUTH = ("this recording has no touch ground truth: it was not recorded from the simulated skin; only "
                   "open-loop replay applies (it has no skin/touch channel, or skin samples without touch_hpa)")


class Resimulator:
    """The recorded skin stream with its touches re-simulated against another arm motion.

    Each sample becomes: the recorded absolute pressure, minus what the
    simulated skin's touches added to it (``touch_hpa``, recorded with the
    sample), plus what the recorded touches (``skin/touch``) press by the
    contact model at the pad poses given now. The noise and drift are kept
    as recorded, bit for bit (a pad whose touch part is unchanged keeps its
    absolute pressure exactly), and the change from baseline is computed
    anew by the gateway's baseline filter, on the gateway's script clock, so
    that a stream re-simulated against the very motion it was recorded with
    comes out identical. Each touch meets its pad where the new arm has it
    when the touch starts (the person touches the pad, wherever it is); the
    recorded contact point is that of the original motion.
    """

    def __init__(self, cfg: GatewaySection, touches: Sequence[m.SkinTouch], n_pads: int,
                 previous_stamp_ns: int | None = None) -> None:
        if not touches:
            raise ConfigError(NO_GROUND_TRUTH)
        origins = sorted({t.origin_ns for t in touches})
        if len(origins) > 1:
            raise ConfigError(f"the recorded touches come from {len(origins)} runs of the simulated skin (its "
                              "gateway restarted): re-simulate each run's part on its own with --start/--end")
        self.origin_ns = origins[0]
        self.touches = TouchSet(n_pads, sim_settings(cfg).contact_depth_m, closed_loop=True)
        for t in sorted(touches, key=lambda t: (t.start_s, t.seq)):
            self.touches.add(t.pad, Touch(pad=t.name, start_s=t.start_s, duration_s=t.duration_s,
                                          peak_hpa=t.peak_hpa, shape=t.shape, ramp_s=t.ramp_s))
        self.gateway = Gateway(cfg, n_pads)
        self.previous_stamp_ns = previous_stamp_ns
        self.first = True

    def script_time(self, stamp_ns: int) -> float:
        """The gateway's script time of a sample stamp, s (as the gateway computed it)."""
        return (stamp_ns - self.origin_ns) / 1e9

    def apply(self, sample: m.SkinPressure, points: np.ndarray,
              normals: np.ndarray) -> tuple[m.SkinPressure, list[ActiveTouch]]:
        """The sample re-simulated with the pads at ``points`` / ``normals`` (base frame, one row per pad),
        and the touches that started with it."""
        n = self.touches.n
        if len(sample.touch_hpa) != n or len(sample.absolute_hpa) != n:
            raise ConfigError(f"skin sample {sample.seq} has {len(sample.absolute_hpa)} pads and "
                              f"{len(sample.touch_hpa)} touch values, expected {n}: {NO_GROUND_TRUTH}")
        t = self.script_time(sample.stamp_ns)
        started = self.touches.start(t, points, normals)
        touch = self.touches.pressure(t, points)
        valid = np.asarray(sample.valid, dtype=bool) if sample.valid else np.ones(n, dtype=bool)
        recorded = m.as_array(sample.absolute_hpa)
        # Where the touch part is unchanged the difference is exactly 0.0 and
        # the recorded pressure passes through bit for bit.
        absolute = np.where(valid, recorded + (touch - m.as_array(sample.touch_hpa)), np.nan)
        if self.first:
            self.first = False
            # The filter's state just before this sample: the baseline the
            # change was taken from (exact: absolute and baseline are within a
            # factor of two, so their difference was exact) and the flags.
            before = np.where(valid, recorded - m.as_array(sample.change_hpa), m.as_array(sample.baseline_hpa))
            last_t = None if self.previous_stamp_ns is None else self.script_time(self.previous_stamp_ns)
            self.gateway.filter.resume(last_t, before, np.asarray(sample.contact, dtype=bool))
        self.gateway.seq = sample.seq
        self.gateway.source = sample.source
        out, _ = self.gateway.process(t, sample.stamp_ns, absolute, touch)
        return out, started
