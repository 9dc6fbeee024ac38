"""The gain estimator's wiring: skin/pressure -> skin/pain, one message per skin sample.

The call order of the service, with no Zenoh, no thread and no clock of its
own (its time comes from the journal): the live process
(:mod:`.main`), lockstep runs and ``nwr verify`` all run this code.
"""

from __future__ import annotations

from typing import Any

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.journal import Journal
from nwr.common.robot import load_description
from nwr.services.gain.core import GainEstimator
from nwr.services.wiring import Diag, Out, Wiring, receives

SERVICE = "gain"


class GainWiring(Wiring):
    service = SERVICE
    outputs = (keys.SKIN_PAIN,)

    def __init__(self, profile: Profile, *, journal: Journal, out: Out, diag: Diag) -> None:
        self.estimator = GainEstimator(profile.gain, load_description(profile.robot.description or None).pads)
        self.journal = journal
        self.out = out
        self.diag = diag
        journal.begin("start")

    @classmethod
    def rebuild(cls, profile: Profile, params: dict[str, Any], *, journal: Journal, out: Out,
                diag: Diag) -> GainWiring:
        return cls(profile, journal=journal, out=out, diag=diag)

    def params(self) -> dict[str, Any]:
        return {}

    @receives("pressure", keys.SKIN_PRESSURE)
    def on_pressure(self, sample: m.SkinPressure) -> None:
        try:
            pain = self.estimator.process(sample, self.journal.now_ns())
        except ValueError as exc:
            self.diag("warning", "bad_skin_sample", str(exc))
            return
        self.out(keys.SKIN_PAIN, pain)
