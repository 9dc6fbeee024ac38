"""The safety mode: which of the two sets of Cartesian limits the tracker's limiter applies.

:class:`SafetyModes` owns the normal limits (the profile's ``[bridge]``
ones) and the reduced ones (``bridge.reduced``), the mode the operator asked
for (``nwr safety``: ``control/safety``) and the mode in force: the reduced
limits while the operator asks for them, or while any pad is blind and
``bridge.blind_pads`` is ``"reduced"`` (:mod:`.skin`), the normal ones
otherwise. A change of the mode in force is reported and published at once.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common import messages as m
from nwr.services.bridge.cartesian import CartesianLimiter, Limits
from nwr.services.bridge.checks import Event
from nwr.services.bridge.envelope import Envelope
from nwr.services.bridge.status import Status


class SafetyModes(Status):
    """The normal and the reduced Cartesian limits, the one the operator asked for and the one in force."""

    def __init__(self, env: Envelope, q0: np.ndarray, now_ns: int, *, limiter: CartesianLimiter | None,
                 reduced: Limits | None, **below: Any) -> None:
        super().__init__(env, q0, now_ns, limiter=limiter, **below)
        # The Cartesian limits of the normal and the reduced mode.
        self.normal_limits = limiter.limits if limiter is not None else None
        self.reduced_limits = reduced
        self.safety_mode: m.SafetyMode = "normal"  # in force: the operator's, or reduced while a pad is blind
        self.operator_mode: m.SafetyMode = "normal"  # as the operator (nwr safety) asked

    def set_safety_mode(self, mode: m.SafetyMode, now_ns: int, requested_by: str = "") -> bool:
        """Switch the Cartesian limits to the normal or the reduced set; False if there is nothing to switch
        (while a pad is blind and blind_pads is "reduced", the reduced set stays in force until it sees again)."""
        limiter = self.tracker.limiter
        if limiter is None or self.normal_limits is None or self.reduced_limits is None:
            self.events.append(Event("warning", "safety_mode_rejected",
                                     f"safety mode {mode!r} refused: this bridge has no Cartesian limits"))
            return False
        self.operator_mode = mode
        if mode == "normal" and self.blind and self.blind_policy == "reduced":
            self.events.append(Event("warning", "safety_mode", "safety mode normal requested"
                                     + (f" by {requested_by}" if requested_by else "") + ": the reduced limits stay "
                                     f"while pad(s) {', '.join(self.pad_names[i] for i in sorted(self.blind))} are "
                                     "blind", every_s=0.0))
        return self._apply_safety_mode(now_ns, requested_by)

    def _apply_safety_mode(self, now_ns: int, requested_by: str) -> bool:
        limiter = self.tracker.limiter
        blind_reduced = bool(self.blind) and self.blind_policy == "reduced"
        mode: m.SafetyMode = "reduced" if self.operator_mode == "reduced" or blind_reduced else "normal"
        limits = self.reduced_limits if mode == "reduced" else self.normal_limits
        if limiter is None or limits is None:
            return False
        if mode == self.safety_mode:
            return False
        limiter.limits = limits
        self.safety_mode = mode
        self.publish_now = True
        self.events.append(Event(
            "warning" if mode == "reduced" else "info", "safety_mode",
            f"safety mode {mode}{f' (requested by {requested_by})' if requested_by else ''}: {limits.describe()}",
        ))
        return True
