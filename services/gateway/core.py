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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nwr.common import messages as m
from nwr.common.config import GatewaySection, SimSkinSection, Touch, TouchScript
from nwr.common.errors import ConfigError
from nwr.common.robot import Pad


@dataclass
class FilterEvents:
    reacquired: list[int]
    non_finite: list[int]


class BaselineFilter:
    def __init__(self, cfg: GatewaySection, n_pads: int) -> None:
        self.cfg = cfg
        self.n = n_pads
        self.baseline = np.full(n_pads, np.nan)
        self.contact = np.zeros(n_pads, dtype=bool)
        self.contact_since = np.zeros(n_pads)
        self.last_t: float | None = None

    def update(self, t: float, absolute: np.ndarray) -> tuple[np.ndarray, FilterEvents]:
        """Feed one sample at time ``t`` (s); returns the change from baseline."""
        cfg = self.cfg
        dt = 0.0 if self.last_t is None else max(0.0, t - self.last_t)
        self.last_t = t
        finite = np.isfinite(absolute)
        events = FilterEvents([], [int(i) for i in np.flatnonzero(~finite)])
        fresh = finite & np.isnan(self.baseline)
        self.baseline[fresh] = absolute[fresh]
        change = absolute - self.baseline

        starting = finite & ~self.contact & (change > cfg.contact_hpa)
        ending = finite & self.contact & (change < cfg.release_hpa)
        self.contact_since[starting] = t
        self.contact = (self.contact | starting) & ~ending

        too_long = self.contact & (t - self.contact_since > cfg.max_contact_s)
        if too_long.any():
            self.baseline[too_long] = absolute[too_long]
            self.contact[too_long] = False
            change[too_long] = 0.0
            events.reacquired = [int(i) for i in np.flatnonzero(too_long)]

        track = finite & ~self.contact
        if dt > 0 and track.any():
            alpha = 1.0 - np.exp(-dt / cfg.baseline_tau_s)
            step = np.clip(alpha * change[track], -cfg.max_drift_hpa_s * dt, cfg.max_drift_hpa_s * dt)
            self.baseline[track] += step
        return change, events


class SimSkin:
    """Simulated AIRSKIN pads: absolute pressure with noise, drift and scripted touches."""

    def __init__(self, cfg: SimSkinSection, pads: tuple[Pad, ...], script: TouchScript | None) -> None:
        self.cfg = cfg
        self.pads = pads
        self.rng = np.random.default_rng(cfg.seed)
        n = len(pads)
        self.base = cfg.base_hpa + self.rng.uniform(-cfg.spread_hpa, cfg.spread_hpa, n)
        self.phase = self.rng.uniform(0, 2 * np.pi, n)
        self.walk = np.zeros(n)
        self.last_t = 0.0
        self.touches: list[tuple[int, Touch]] = []
        if script is not None:
            by_name = {p.name: p.id for p in pads}
            for touch in script.touch:
                pad = by_name.get(touch.pad)
                if pad is None and touch.pad.isdigit() and int(touch.pad) < n:
                    pad = int(touch.pad)
                if pad is None:
                    raise ConfigError(f"touch script names pad {touch.pad!r}; the skin has {sorted(by_name)}")
                self.touches.append((pad, touch))

    def add_touch(self, pad: int, touch: Touch) -> None:
        """A touch decided while running (the study's target pad, say)."""
        self.touches.append((pad, touch))
        # Finished touches no longer matter; keep the list short over long sessions.
        self.touches = [(p, x) for p, x in self.touches if x.start_s + x.duration_s + 2 * x.ramp_s >= touch.start_s]

    def touch_pressure(self, t: float) -> np.ndarray:
        """The scripted pressure change of every pad at time t, hPa."""
        out = np.zeros(len(self.pads))
        for pad, touch in self.touches:
            out[pad] += touch_profile(touch, t)
        return out

    def sample(self, t: float) -> np.ndarray:
        cfg = self.cfg
        dt = max(0.0, t - self.last_t)
        self.last_t = t
        self.walk += self.rng.normal(0.0, cfg.drift_walk_hpa * np.sqrt(dt), len(self.pads))
        drift = self.walk + cfg.drift_sine_hpa * np.sin(2 * np.pi * t / cfg.drift_period_s + self.phase)
        noise = self.rng.normal(0.0, cfg.noise_hpa, len(self.pads))
        return self.base + drift + noise + self.touch_pressure(t)


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


class Gateway:
    """Turns absolute pad pressures into SkinPressure messages."""

    def __init__(self, cfg: GatewaySection, n_pads: int, source: str = "sim") -> None:
        self.filter = BaselineFilter(cfg, n_pads)
        self.source = source
        self.seq = 0

    def process(self, t: float, stamp_ns: int, absolute: np.ndarray) -> tuple[m.SkinPressure, FilterEvents]:
        change, events = self.filter.update(t, absolute)
        valid = np.isfinite(change)
        baseline = self.filter.baseline
        msg = m.SkinPressure(
            seq=self.seq, stamp_ns=stamp_ns,
            absolute_hpa=np.where(valid, absolute, 0.0).tolist(),
            baseline_hpa=np.where(np.isfinite(baseline), baseline, 0.0).tolist(),
            change_hpa=np.where(valid, change, 0.0).tolist(),
            contact=(self.filter.contact & valid).tolist(),
            valid=valid.tolist(),
            source=self.source,
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
