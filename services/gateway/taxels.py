"""The scripted taxel skin: a touch script's touches pressed on a taxel skin by a round finger.

The touch scripts (``common/scripts/*.toml``) name AIRSKIN pads and give each touch's pressure change in
hPa. On a taxel skin the same script presses where the pad would be: at the taxel of the pad's link nearest
the pad's point (refused, naming the pad, where the taxel skin does not cover it: no taxel of its link within
:data:`COVER_M`). A touch's pressure change becomes a force by mapping the AIRSKIN's pain thresholds onto the
taxel skin's force thresholds piecewise linearly (0 -> 0, t1..t4 hPa -> f1..f4 N, and beyond t4 the last
segment's slope): a touch scripted at PL k on the pads presses with PL k's force on the taxels, so every
script means the same on both skins. The finger's pressure profile is :func:`nwr.common.taxels.finger_pressure`
(Hertz's elliptic profile) with the force of the touch's profile in time (a step or ramps, as on the pads).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from nwr.common.errors import ConfigError
from nwr.common.launch import TouchScript
from nwr.common.robot import Pad
from nwr.common.taxels import TaxelSkin, finger_pressure, nearest_taxel
from nwr.services.gateway.core import touch_profile

# A pad is covered when a taxel of its link lies within this distance of its point.
COVER_M = 0.05
# The default finger: wider than half the diagonal of the packaged skin's coarsest grid (0.03 x 0.031 m: 0.022 m),
# so a finger anywhere on a patch reaches a taxel.
FINGER_RADIUS_M = 0.03


def force_of(change_hpa: float, pad_thresholds_hpa: Sequence[float], force_thresholds_n: Sequence[float]) -> float:
    """The force (N) a pad's scripted pressure change (hPa) means on a taxel skin: the pain thresholds mapped
    onto each other piecewise linearly, extrapolated past the last with the last segment's slope."""
    hpa = np.concatenate([[0.0], pad_thresholds_hpa])
    newton = np.concatenate([[0.0], force_thresholds_n])
    if change_hpa <= hpa[-1]:
        return float(np.interp(change_hpa, hpa, newton))
    slope = (newton[-1] - newton[-2]) / (hpa[-1] - hpa[-2])
    return float(newton[-1] + slope * (change_hpa - hpa[-1]))


def covering_taxel(skin: TaxelSkin, pad: Pad) -> int | None:
    """The taxel a touch on ``pad`` presses, or None where the taxel skin does not cover the pad."""
    if pad.link not in skin.links:
        return None
    taxel = nearest_taxel(skin, pad.link, pad.point)
    return taxel if float(np.linalg.norm(skin.points[taxel] - pad.point)) <= COVER_M else None


def check_covered(skin: TaxelSkin, pads: tuple[Pad, ...], script: TouchScript) -> None:
    """ConfigError naming the pads a touch script touches that the taxel skin does not cover (their touches
    would press no taxel, in the scripted world or the physics world)."""
    by_name = {pad.name: pad for pad in pads}
    uncovered = sorted({t.pad for t in script.touch if t.pad not in by_name
                        or covering_taxel(skin, by_name[t.pad]) is None})
    if uncovered:
        raise ConfigError(
            f"the touch script touches pads {uncovered}, which the taxel skin {skin.path.name} does not cover "
            f"(no taxel of their link within {COVER_M} m of their point); covered: "
            f"{sorted(p.name for p in pads if covering_taxel(skin, p) is not None)}")


class ScriptedTaxels:
    """Each taxel's reading at a script time: the sum of the touches under way, one finger each."""

    def __init__(self, skin: TaxelSkin, pads: tuple[Pad, ...], script: TouchScript,
                 pad_thresholds_hpa: Sequence[float], finger_radius_m: float = FINGER_RADIUS_M) -> None:
        check_covered(skin, pads, script)
        by_name = {pad.name: pad for pad in pads}
        self.touches = list(script.touch)
        self.forces = [force_of(t.peak_hpa, pad_thresholds_hpa, skin.force_thresholds_n) for t in self.touches]
        self.taxels = [covering_taxel(skin, by_name[t.pad]) for t in self.touches]
        # One finger's readings per newton, a row per touch: a sample is the touches' forces times these rows.
        self._unit = np.array([finger_pressure(skin, by_name[t.pad].link, skin.points[taxel], finger_radius_m, 1.0)
                               for t, taxel in zip(self.touches, self.taxels)]).reshape(len(self.touches), len(skin))
        self._start = np.array([t.start_s for t in self.touches])
        self._end = np.array([t.start_s + t.duration_s + (2 * t.ramp_s if t.shape == "ramp" else 0.0)
                              for t in self.touches])
        self._zero = np.zeros(len(skin))

    def force(self, index: int, t: float) -> float:
        """Touch ``index``'s force at script time ``t``, N."""
        touch = self.touches[index]
        return self.forces[index] * touch_profile(touch, t) / touch.peak_hpa

    def sample(self, t: float) -> np.ndarray:
        """Every taxel's reading at script time ``t`` (the skin's unit); zeros between touches."""
        active = np.flatnonzero((self._start <= t) & (t < self._end))
        if active.size == 0:
            return self._zero.copy()
        forces = np.array([self.force(int(i), t) for i in active])
        return forces @ self._unit[active]
