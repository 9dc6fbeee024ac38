"""Skin validity: fresh skin data, blind pads, and the contact a withdrawal must not move into.

A skin sample is fresh skin data if it is this robot's skin (one reading
per pad) and has at least one valid pad (:func:`pad_validity`: the
gateway's own flag, and within what a pad can report); a pain message, if
it has one gain per pad. Their age is what :meth:`~.status.Status._evaluate`
calls stale skin. A pad invalid for ``blind_pad_s`` is blind: reported when
the blind pads change, and at most every :data:`BLIND_REPORT_S` while any
is; meanwhile the reduced Cartesian limits are in force (:mod:`.safety`), or,
with ``bridge.blind_pads = "stop"``, the skin counts as stale.

:class:`SkinValidity` owns since when each pad is invalid, how long makes it
blind, and the strongest contact of the newest pain message, whose outward
normal is the direction into the contact that a withdrawal's speed toward
it is limited along (:meth:`SkinValidity._toward`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.common.door import ABSOLUTE_HPA, CHANGE_HPA
from nwr.services.bridge.checks import Event
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.safety import SafetyModes

# While a pad is blind, it is reported again at most this often, s (a change of the blind pads at once).
BLIND_REPORT_S = 10.0


class SkinValidity(SafetyModes):
    """Skin samples and pain messages: their freshness, the blind pads, the newest contact."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, blind_pad_s: float,
                 entry_pads: tuple[int, ...] = (), **below: Any) -> None:
        super().__init__(env, q0, now_ns, **below)
        # A taxel skin (robot.skin = "taxels"): each taxel's pad (-1: none). A pad is valid while any of its
        # taxels is (one failed taxel does not blind a patch); a pad without taxels has nothing to go blind.
        self.entry_pads = entry_pads
        self._taxels_of = [[i for i, p in enumerate(entry_pads) if p == pad] for pad in range(self.n_pads)]
        # Skin validity: a pad whose readings are invalid (not finite, out of range) since ``invalid_since``
        # for blind_pad_s is blind; a sample without any valid pad is no fresh skin data.
        self.blind_pad_ns = round(blind_pad_s * 1e9)
        self.invalid_since: list[int | None] = [None] * self.n_pads
        self.contact_pad = -1  # the strongest contact of the newest pain message (-1: none)

    def on_skin(self, pressure: m.SkinPressure, now_ns: int) -> None:
        """A skin sample: fresh skin data if it is this robot's skin and has a valid pad; it also tells which
        pads are blind (invalid for ``blind_pad_s``)."""
        n = len(self.entry_pads) or self.n_pads
        if len(pressure.change_hpa) != n or len(pressure.contact) != n:
            skin = f"{n} taxels" if self.entry_pads else f"{n} pads"
            self.events.append(Event(
                "warning", "skin_invalid",
                f"skin sample {pressure.seq} has {len(pressure.change_hpa)} entries, the skin has {skin}: "
                "it does not count as fresh skin data",
            ))
            return
        valid = pad_validity(pressure, n)
        if self.entry_pads:
            valid = [any(valid[i] for i in taxels) if taxels else True for taxels in self._taxels_of]
        for i, ok in enumerate(valid):
            if ok:
                self.invalid_since[i] = None
            elif self.invalid_since[i] is None:
                self.invalid_since[i] = now_ns
        self._update_blind(now_ns)
        if not any(valid):
            self.events.append(Event(
                "error", "skin_blind",
                f"skin sample {pressure.seq} has no valid pad (every reading not finite or outside "
                f"[{ABSOLUTE_HPA[0]:g}, {ABSOLUTE_HPA[1]:g}] hPa: a skin in Pa, say): it does not count as fresh "
                "skin data",
            ))
            self._evaluate(now_ns)
            return
        self.last_skin_ns = now_ns
        self._evaluate(now_ns)

    def _update_blind(self, now_ns: int) -> None:
        """The pads invalid for blind_pad_s: reported when they change, and at most every BLIND_REPORT_S while
        any is; the reduced limits (or the stop) while any is."""
        blind = frozenset(i for i, since in enumerate(self.invalid_since)
                          if since is not None and now_ns - since >= self.blind_pad_ns)
        if blind == self.blind:
            if blind:
                self.events.append(Event("warning", "skin_blind_pad", self._blind_message(blind),
                                         every_s=BLIND_REPORT_S))
            return
        recovered = self.blind - blind
        self.blind = blind
        if blind:
            self.events.append(Event("warning", "skin_blind_pad", self._blind_message(blind), every_s=0.0))
        if recovered:
            self.events.append(Event("info", "skin_pad_recovered",
                                     f"pad(s) {', '.join(self.pad_names[i] for i in sorted(recovered))} valid again"
                                     + ("" if blind else ": every pad sees again"), every_s=0.0))
        self._apply_safety_mode(now_ns, "blind pads" if blind else "")

    def _blind_message(self, blind: frozenset[int]) -> str:
        what = ("the reduced Cartesian limits while any pad is blind" if self.blind_policy == "reduced"
                else "task and return held (bridge.blind_pads = \"stop\")")
        return (f"{len(blind)} of {self.n_pads} pads blind (invalid for more than {self.blind_pad_ns / 1e6:.0f} ms): "
                f"{', '.join(self.pad_names[i] for i in sorted(blind))}; {what}")

    def on_pain(self, pain: m.SkinPain, now_ns: int) -> None:
        """A pain message: the skin data the planners act on is fresh."""
        if len(pain.gain) != self.n_pads:
            self.events.append(Event(
                "warning", "pain_invalid",
                f"pain message {pain.seq} has {len(pain.gain)} pads, the robot has {self.n_pads}: "
                "it does not count as fresh skin data",
            ))
            return
        self.last_pain_ns = now_ns
        strongest = pain.strongest
        self.contact_pad = strongest.pad if strongest is not None and 0 <= strongest.pad < self.n_pads else -1
        self._evaluate(now_ns)

    def _toward(self) -> np.ndarray | None:
        """The direction toward the newest contact (the touched pad's outward normal, toward the finger), if any."""
        limiter = self.tracker.limiter
        if limiter is None or self.contact_pad < 0:
            return None
        return limiter.model.pad_normal(self.tracker.q, self.contact_pad)

    def skin_age_s(self, now_ns: int) -> float:
        return -1.0 if self.last_skin_ns is None else (now_ns - self.last_skin_ns) / 1e9


def pad_validity(pressure: m.SkinPressure, n_pads: int) -> list[bool]:
    """Per pad, whether its reading is valid: the gateway's own flag (a non-finite reading; all valid when the
    sample has none), and within what a pad can report (absolute and change, hPa: a skin read in Pa is not)."""
    lo, hi = ABSOLUTE_HPA
    flags = pressure.valid if len(pressure.valid) == n_pads else [True] * n_pads
    valid = [bool(ok) and lo <= a <= hi and abs(c) <= CHANGE_HPA
             for ok, a, c in zip(flags, pressure.absolute_hpa, pressure.change_hpa, strict=False)]
    return valid + [False] * (n_pads - len(valid))  # a pad the sample does not cover is not valid
