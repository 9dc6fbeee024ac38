"""The gain estimator on a taxel skin: a sample's contacts, each with its level and gain from its force, and
the pain per pad of the robot's pad list.

A sample's ``change_hpa`` has one entry per taxel (the gateway's hPa). Its contacts are the clusters of
:func:`nwr.common.taxels.contacts` (a taxel presses from ``gateway.contact_hpa``); each contact's pain level
and gain come from the paper's functions (:mod:`.core`: ``pain_level``, ``discrete_gain``,
``continuous_gain``, with ``gain.k`` and ``gain.pl3_gain``) applied to its force on the skin file's
``force_thresholds_n``. ``SkinPain`` stays per pad: each patch is named after the pad it replaces, a pad's
level and gain are its patch's strongest contact's, and a pad without taxels reads level 1, gain 0. The
strongest contact (highest gain, then force) carries its point and normal in its link's frame.
"""

from __future__ import annotations

import numpy as np

from nwr.common import messages as m
from nwr.common.config import GainSection
from nwr.common.errors import ConfigError
from nwr.common.robot import Pad
from nwr.common.skin import hpa_per_unit, patch_pads
from nwr.common.taxels import TaxelContact, TaxelSkin, contacts
from nwr.services.gain.core import EFFECTIVE_MASS, continuous_gain, discrete_gain, pain_level


class TaxelGain:
    """One pain message per taxel sample."""

    def __init__(self, cfg: GainSection, pads: tuple[Pad, ...], skin: TaxelSkin, contact_hpa: float) -> None:
        if cfg.model == EFFECTIVE_MASS:
            raise ConfigError("gain.model = \"effective-mass\" scales each pad's pressure thresholds; on a taxel "
                              "skin a contact's level comes from its force: use \"continuous\" or \"discrete\"")
        if cfg.overrides:
            raise ConfigError(f"gain.overrides ({sorted(cfg.overrides)}) are pad thresholds in hPa; a taxel skin's "
                              f"levels come from its file's force_thresholds_n ({skin.path})")
        self.model = cfg.model
        self.k = cfg.k
        self.pl3_gain = cfg.pl3_gain
        self.pads = pads
        self.skin = skin
        self.pad_of = patch_pads(skin, pads)
        self.hpa_per_unit = hpa_per_unit(skin)
        self.threshold = contact_hpa / self.hpa_per_unit  # in the skin's unit
        self.thresholds = skin.level_thresholds_n
        self.seq = 0
        self.contacts: list[TaxelContact] = []  # the last sample's

    def level_gain(self, force_n: float) -> tuple[int, float]:
        """A contact's pain level and gain from its force."""
        level = pain_level(force_n, self.thresholds)
        if self.model == "discrete":
            return level, discrete_gain(force_n, self.thresholds, self.pl3_gain)
        return level, continuous_gain(force_n, self.thresholds, self.k, self.pl3_gain)

    def process(self, sample: m.SkinPressure, now_ns: int) -> m.SkinPain:
        """Raises ValueError on a wrong taxel count."""
        n = len(self.skin)
        if len(sample.change_hpa) != n or (sample.valid and len(sample.valid) != n):
            raise ValueError(f"skin sample {sample.seq} has {len(sample.change_hpa)} entries, the taxel skin has "
                             f"{n}: sample dropped")
        pressure = np.asarray(sample.change_hpa, dtype=float) / self.hpa_per_unit
        if sample.valid:
            pressure[~np.asarray(sample.valid, dtype=bool)] = np.nan
        self.contacts = contacts(self.skin, pressure, self.threshold)
        levels = [1] * len(self.pads)
        gains = [0.0] * len(self.pads)
        best: tuple[float, float] | None = None
        strongest = None
        for c in self.contacts:
            level, g = self.level_gain(c.force_n)
            pad = self.pad_of[c.patch]
            if (g, level) > (gains[pad], levels[pad]):
                levels[pad], gains[pad] = level, g
            if g > 0 and (best is None or (g, c.force_n) > best):
                best = (g, c.force_n)
                strongest = m.Contact(
                    pad=pad, name=self.pads[pad].name, region=c.region, change_hpa=c.peak * self.hpa_per_unit,
                    level=level, gain=g, link=c.link, point=c.point.tolist(), normal=c.normal.tolist(),
                    force_n=c.force_n)
        light = sorted({self.pad_of[c.patch] for c in self.contacts} - {i for i, level in enumerate(levels)
                                                                         if level > 1})
        msg = m.SkinPain(seq=self.seq, stamp_ns=now_ns, trace=m.Trace(sample.seq, sample.stamp_ns),
                         model=self.model, level=levels, gain=gains, strongest=strongest, light_touch=light)
        self.seq += 1
        return msg
