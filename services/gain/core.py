"""Pressure change -> pain level and gain G(p), exactly as in the paper.

Pain levels (PL) by the pressure change p from a no-touch baseline, with
thresholds t = [t1, t2, t3, t4] = [2, 6, 12, 20] hPa:

    PL 1: p < t1      PL 2: t1 <= p < t2      PL 3: t2 <= p < t3      PL 4: p >= t3

Discrete model:   G = 0 (PL 1-2), 0.35 (PL 3), 1 (PL 4).

Continuous model, with the scaled sigmoid
    sigma(x; k) = 1 / (1 + exp(-k (x - 0.5))),
    sigma_s(x; k) = (sigma(x; k) - sigma(0; k)) / (sigma(1; k) - sigma(0; k)):

    G = 0                                              p < t2
    G = 0.35 sigma_s((p - t2) / (t3 - t2); k)          t2 <= p < t3
    G = 0.35 + 0.65 sigma_s((p - t3) / (t4 - t3); k)   t3 <= p < t4
    G = 1                                              p >= t4

with k = 3. Non-finite changes give PL 1 and G = 0 (and are counted by the
caller): a pad that reports garbage must never trigger a reflex.

Effective-mass model (``gain.model = "effective-mass"``, this project's,
after Rustler et al.'s adaptive sensitivity): the continuous model with each
pad's four thresholds multiplied by

    s = 1 - (1 - floor) * min(1, F / F_limit)

F the impact force a collision at the pad's speed would cause (:mod:`.impact`),
F_limit its body region's transient limit: s = 1 (the paper's thresholds) for
a pad at rest, ``floor`` (default 0.6) for one whose predicted force reaches
the limit, and ``floor`` for every pad while no prediction can be made (no,
stale or non-finite robot state, an ill-conditioned mass matrix). A pad is
never less sensitive than the paper's, nor more than ``floor`` times its
thresholds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nwr.common import messages as m
from nwr.common.config import GainSection
from nwr.common.errors import ConfigError
from nwr.common.robot import Pad
from nwr.services.gain.impact import Impact

EFFECTIVE_MASS = "effective-mass"

# Beyond this exponent e^t overflows a double near 709.8; 1 / (1 + e^t) equals
# e^-t to double precision long before (from t = 37 on).
_EXP_TOP = 700.0


def sigmoid(x: float, k: float) -> float:
    """1 / (1 + e^(-k (x - 0.5))), for any finite k (never an OverflowError)."""
    t = -k * (x - 0.5)
    if t > _EXP_TOP:
        return math.exp(-t)  # underflows to 0.0 gracefully, never overflows
    return 1.0 / (1.0 + math.exp(t))


def scaled_sigmoid(x: float, k: float) -> float:
    """sigma_s(x; k): the sigmoid rescaled to pass through (0, 0) and (1, 1)."""
    lo, hi = sigmoid(0.0, k), sigmoid(1.0, k)
    return (sigmoid(x, k) - lo) / (hi - lo)


def pain_level(p: float, thresholds: tuple[float, ...]) -> int:
    if not math.isfinite(p) or p < thresholds[0]:
        return 1
    if p < thresholds[1]:
        return 2
    if p < thresholds[2]:
        return 3
    return 4


def discrete_gain(p: float, thresholds: tuple[float, ...], pl3_gain: float = 0.35) -> float:
    level = pain_level(p, thresholds)
    return 0.0 if level <= 2 else pl3_gain if level == 3 else 1.0


def continuous_gain(p: float, thresholds: tuple[float, ...], k: float = 3.0, pl3_gain: float = 0.35) -> float:
    if not math.isfinite(p):
        return 0.0
    _, t2, t3, t4 = thresholds
    if p < t2:
        return 0.0
    if p < t3:
        return pl3_gain * scaled_sigmoid((p - t2) / (t3 - t2), k)
    if p < t4:
        return pl3_gain + (1.0 - pl3_gain) * scaled_sigmoid((p - t3) / (t4 - t3), k)
    return 1.0


@dataclass(frozen=True)
class PadGain:
    thresholds: tuple[float, float, float, float]
    k: float


class GainEstimator:
    """Applies the configured model to every pad of a skin sample."""

    def __init__(self, cfg: GainSection, pads: tuple[Pad, ...]) -> None:
        self.model = cfg.model
        self.pl3_gain = cfg.pl3_gain
        self.pads = pads
        names = {p.name for p in pads}
        unknown = sorted(set(cfg.overrides) - names)
        if unknown:
            raise ConfigError(f"gain.overrides names pads {unknown} that the skin does not have "
                              f"(pads: {sorted(names)})")
        self.per_pad: list[PadGain] = []
        for pad in pads:
            over = cfg.overrides.get(pad.name)
            thresholds = over.thresholds_hpa if over and over.thresholds_hpa else cfg.thresholds_hpa
            k = over.k if over and over.k else cfg.k
            self.per_pad.append(PadGain(tuple(thresholds), k))  # type: ignore[arg-type]
        self.floor = cfg.effective_mass.floor
        self.seq = 0
        self.non_finite = 0

    def gain(self, pad: int, p: float, scale: float = 1.0) -> tuple[int, float]:
        """A pad's pain level and gain for the change ``p``; ``scale``: the effective-mass model's threshold
        scale (1: the paper's thresholds)."""
        pg = self.per_pad[pad]
        if self.model == "discrete":
            return pain_level(p, pg.thresholds), discrete_gain(p, pg.thresholds, self.pl3_gain)
        thresholds = pg.thresholds if scale == 1.0 else tuple(t * scale for t in pg.thresholds)
        return pain_level(p, thresholds), continuous_gain(p, thresholds, pg.k, self.pl3_gain)

    def scales(self, impact: Impact) -> list[float]:
        """The effective-mass model's threshold scale per pad: 1 - (1 - floor) min(1, F / F_limit)."""
        return (1.0 - (1.0 - self.floor) * impact.ratio).tolist()

    def gain_range(self, pad: int, p: float) -> tuple[float, float]:
        """The gains the model may give a change ``p`` on a pad: (least, most) sensitive (the same for the
        paper's models; the effective-mass model's at rest and at its floor)."""
        g = self.gain(pad, p)[1]
        return (g, self.gain(pad, p, self.floor)[1]) if self.model == EFFECTIVE_MASS else (g, g)

    def process(self, sample: m.SkinPressure, now_ns: int, impact: Impact | None = None) -> m.SkinPain:
        """One pain message per skin sample; raises ValueError on a wrong pad count.

        ``impact``: the effective-mass model's prediction for the sample (required by that model, unused by the
        paper's)."""
        change = sample.change_hpa
        if len(change) != len(self.pads):
            raise ValueError(
                f"skin sample {sample.seq} has {len(change)} pads, the skin has {len(self.pads)}: sample dropped"
            )
        if self.model == EFFECTIVE_MASS:
            if impact is None:
                raise ValueError("the effective-mass gain model needs an impact prediction for every sample")
            return self._scaled(sample, now_ns, impact)
        levels: list[int] = []
        gains: list[float] = []
        best = -1
        per_pad = self.per_pad
        touching = sample.contact if len(sample.contact) == len(change) else ()
        light: list[int] = []
        for i, p in enumerate(change):
            if -math.inf < p < per_pad[i].thresholds[0]:
                # PL 1 (a finite change below the first threshold): G = 0 in both models, and no contact.
                levels.append(1)
                gains.append(0.0)
                if touching and touching[i]:
                    light.append(i)  # in contact all the same: a light touch
                continue
            if not math.isfinite(p):
                self.non_finite += 1
            level, g = self.gain(i, p)
            levels.append(level)
            gains.append(g)
            # Strongest contact: highest gain, then highest change.
            if g > 0 and (best < 0 or (g, change[i]) > (gains[best], change[best])):
                best = i
        msg = m.SkinPain(
            seq=self.seq, stamp_ns=now_ns, trace=m.Trace(sample.seq, sample.stamp_ns),
            model=self.model, level=levels, gain=gains, strongest=self._contact(best, change, levels, gains),
            light_touch=light,
        )
        self.seq += 1
        return msg

    def _contact(self, best: int, change: list[float], levels: list[int], gains: list[float]) -> m.Contact | None:
        if best < 0:
            return None
        pad = self.pads[best]
        return m.Contact(pad=best, name=pad.name, region=pad.region, change_hpa=float(change[best]),
                         level=levels[best], gain=gains[best])

    def _scaled(self, sample: m.SkinPressure, now_ns: int, impact: Impact) -> m.SkinPain:
        """The effective-mass model: the continuous model on each pad's scaled thresholds."""
        change = sample.change_hpa
        scales = self.scales(impact)
        levels: list[int] = []
        gains: list[float] = []
        best = -1
        per_pad = self.per_pad
        touching = sample.contact if len(sample.contact) == len(change) else ()
        light: list[int] = []
        for i, p in enumerate(change):
            if -math.inf < p < per_pad[i].thresholds[0] * scales[i]:
                levels.append(1)  # PL 1 at the pad's scaled thresholds: G = 0, no contact
                gains.append(0.0)
                if touching and touching[i]:
                    light.append(i)
                continue
            if not math.isfinite(p):
                self.non_finite += 1
            level, g = self.gain(i, p, scales[i])
            levels.append(level)
            gains.append(g)
            if g > 0 and (best < 0 or (g, change[i]) > (gains[best], change[best])):
                best = i
        msg = m.SkinPain(
            seq=self.seq, stamp_ns=now_ns, trace=m.Trace(sample.seq, sample.stamp_ns),
            model=self.model, level=levels, gain=gains, strongest=self._contact(best, change, levels, gains),
            effective_mass_kg=impact.mass_kg.tolist(), impact_n=impact.force_n.tolist(), threshold_scale=scales,
            impact_basis=impact.basis, light_touch=light,
        )
        self.seq += 1
        return msg


def gain_curve(model: str, p: np.ndarray, thresholds: tuple[float, ...], k: float = 3.0) -> np.ndarray:
    """G over an array of pressure changes (for figures and tests)."""
    f = discrete_gain if model == "discrete" else (lambda x, t: continuous_gain(x, t, k))
    return np.array([f(float(x), thresholds) for x in p])
