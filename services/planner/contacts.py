"""Every contact counts: the touches the skin feels now, and the ones it felt in the last few seconds.

A pad is *touched* while it feels a touch (pain level 2 or more, or a
gain) or the skin says it is in contact below that (a light touch:
``SkinPain.light_touch``, a hand resting on the arm); its touch begins when it is touched after at least ``gap_s``
without (the restarts' own rule: a flicker is one touch). The touch's
*contact point* and *normal* are the pad's reference point and outward
normal, in the base frame, at the pose where the arm was as the skin felt
that first sample (the measured one, :meth:`.core.Planner._felt_pose`):
where the person met the arm. A pad touched again within ``gap_s`` (the
same touch) further in than that point (against the normal, the way a
withdrawal goes) has the hand where it is now, one that followed the
withdrawn pad and came back to it: the point moves there, and a return keeps
clear of that place, not of the first. (A pad touched without a break as it
withdraws keeps the first: the skin's pressure outlasts a tap by a few
tenths of a second, so that a pad that left the finger still feels it.)
The touch is *active* while the pad is touched, and
*recent* until ``recent_contact_s`` after the last sample in which it was.

The planner passes every recent contact besides the reflex's own to its
strategy (the whole-arm withdrawal keeps the arm away from each and
withdraws each active one's pad in proportion to its gain) and, in hold
mode, keeps a return, and the task after it, from taking a pad through a
recent contact (:func:`passes_through`): the arm waits where it holds until
the contact is no longer recent, rather than sweep a pad through the place a
person was a moment ago. Every return, in both modes, approaches each recent
contact's place slowly (:meth:`Contacts.places`, :mod:`.returning`), an
earlier touch of a pad touched again elsewhere too.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from nwr.common.robot import RobotModel

# A pad feels a touch from this pain level on (PL 2: above the first threshold, below a reflex's).
FELT_LEVEL = 2
# Where a person was: within this distance of a contact point across its pad's normal (a hand's half-width), m.
CONTACT_RADIUS_M = 0.1


@dataclass(frozen=True)
class ContactPoint:
    """One touch: its pad, where the pad was (point, outward normal; base frame, m), its gain and pain level,
    its times."""

    pad: int
    point: np.ndarray
    normal: np.ndarray
    gain: float  # in the last sample (0 once it is no longer felt)
    onset_ns: int
    felt_ns: int  # the last sample with a gain
    level: int = 0  # the pain level in the last sample (0 once it is no longer felt)


class Contacts:
    """The touches of every pad: which are active, which are recent."""

    def __init__(self, model: RobotModel, recent_s: float, gap_s: float, felt_level: int) -> None:
        self.model = model
        self.recent_ns = round(recent_s * 1e9)
        self.gap_ns = round(gap_s * 1e9)
        self.felt_level = felt_level
        self.touches: dict[int, ContactPoint] = {}  # by pad: its latest touch (active or recent)
        self.earlier: list[ContactPoint] = []  # recent touches a later touch of the same pad took the place of
        self.touched: set[int] = set()  # the pads touched in the last sample

    def observe(self, q: np.ndarray, levels: list[int], gains: np.ndarray, now_ns: int,
                light: Iterable[int] = ()) -> list[int]:
        """One pain message's levels and gains, at the pose ``q`` (where the arm was as the skin felt it: the
        measured pose, Planner._felt_pose); the pads whose touch began in it.
        ``light``: the pads it says are in contact below the felt level (``SkinPain.light_touch``), touched too."""
        touched = {pad for pad, (level, gain) in enumerate(zip(levels, gains)) if level >= self.felt_level
                   or gain > 0.0} | {pad for pad in light if 0 <= pad < len(levels)}
        begun = []
        for pad in sorted(touched):
            touch = self.touches.get(pad)
            gain, level = float(gains[pad]), int(levels[pad])
            if touch is None or (pad not in self.touched and now_ns - touch.felt_ns >= self.gap_ns):
                if touch is not None:
                    self.earlier.append(replace(touch, gain=0.0, level=0))
                self.touches[pad] = ContactPoint(pad, self.model.pad_point(q, pad), self.model.pad_normal(q, pad),
                                                 gain, now_ns, now_ns, level)
                begun.append(pad)
            else:
                point = touch.point
                if pad not in self.touched:  # touched again within gap_s: the hand came back to the pad here
                    here = self.model.pad_point(q, pad)
                    if float((here - touch.point) @ touch.normal) < 0.0:  # further in than the place
                        point = here
                self.touches[pad] = replace(touch, point=point, gain=gain, felt_ns=now_ns, level=level)
        for pad in [p for p in self.touches if p not in touched]:
            if now_ns - self.touches[pad].felt_ns >= self.recent_ns:
                del self.touches[pad]
            elif self.touches[pad].gain != 0.0 or self.touches[pad].level != 0:
                self.touches[pad] = replace(self.touches[pad], gain=0.0, level=0)
        self.earlier = [touch for touch in self.earlier if now_ns - touch.felt_ns < self.recent_ns]
        self.touched = touched
        return begun

    def active(self) -> list[ContactPoint]:
        """The touches felt in the last sample, by pad."""
        return [self.touches[pad] for pad in sorted(self.touches) if pad in self.touched]

    def recent(self, now_ns: int) -> list[ContactPoint]:
        """The touches felt within ``recent_contact_s`` of ``now_ns``, by pad (the active ones among them)."""
        return [touch for pad, touch in sorted(self.touches.items()) if now_ns - touch.felt_ns < self.recent_ns]

    def places(self) -> np.ndarray:
        """Where every touch of the last pain message's ``recent_contact_s`` met its pad, an earlier touch of a pad
        touched again too (points, base frame, m; shape (n, 3))."""
        return np.array([t.point for t in [*self.earlier, *self.touches.values()]]).reshape(-1, 3)


def past(model: RobotModel, q: np.ndarray, contact: ContactPoint) -> float:
    """How far the contact's pad is, at ``q``, past where it was touched along its outward normal (toward the
    person), when within :data:`CONTACT_RADIUS_M` of the contact point across that normal (where the person
    was), m; -inf elsewhere."""
    offset = model.pad_point(q, contact.pad) - contact.point
    depth = float(contact.normal @ offset)
    return depth if np.linalg.norm(offset - depth * contact.normal) <= CONTACT_RADIUS_M else -np.inf


def passes_through(model: RobotModel, poses: Iterable[np.ndarray], contact: ContactPoint, margin_m: float) -> float:
    """How far the way through ``poses`` takes the contact's pad past where it was touched, beyond ``margin_m``
    (:func:`past`), m (0: it does not)."""
    return max([0.0, *(past(model, q, contact) - margin_m for q in poses)])


def straight(q0: np.ndarray, q1: np.ndarray, samples: int = 20) -> list[np.ndarray]:
    """Poses on the straight joint-space way from ``q0`` to ``q1`` (``q1`` included, ``q0`` not)."""
    return [q0 + s * (q1 - q0) for s in np.linspace(0.0, 1.0, samples + 1)[1:]]
