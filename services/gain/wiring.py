"""The gain estimator's wiring: skin/pressure (+ robot/state) -> skin/pain, one message per skin sample.

With the effective-mass model (``gain.model = "effective-mass"``) it also
takes the robot state: each state's impact prediction is made when the state
arrives (:class:`~nwr.services.gain.impact.ImpactModel`), so that a skin
sample only looks it up; the paper's models do not subscribe to it.

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
from nwr.common.robot import RobotModel, load_description
from nwr.services.gain.core import EFFECTIVE_MASS, GainEstimator
from nwr.services.gain.impact import MEASURED, ImpactModel
from nwr.services.wiring import Diag, Input, Out, Wiring, receives

SERVICE = "gain"


class GainWiring(Wiring):
    service = SERVICE
    outputs = (keys.SKIN_PAIN,)

    def __init__(self, profile: Profile, *, journal: Journal, out: Out, diag: Diag) -> None:
        desc = load_description(profile.robot.description or None)
        self.estimator = GainEstimator(profile.gain, desc.pads)
        self.impacts = ImpactModel(profile.gain.effective_mass, RobotModel(desc)) \
            if profile.gain.model == EFFECTIVE_MASS else None
        self.basis = MEASURED  # the last impact prediction's basis (a change is reported once)
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

    def listens(self, inp: Input) -> bool:
        """The robot state only for the effective-mass model."""
        return inp.name != "state" or self.impacts is not None

    @receives("state", keys.ROBOT_STATE)
    def on_state(self, state: m.RobotState) -> None:
        if self.impacts is not None:
            self.impacts.update(state)

    @receives("pressure", keys.SKIN_PRESSURE)
    def on_pressure(self, sample: m.SkinPressure) -> None:
        now = self.journal.now_ns()
        impact = self.impacts.predict(now) if self.impacts is not None else None
        try:
            pain = self.estimator.process(sample, now, impact)
        except ValueError as exc:
            self.diag("warning", "bad_skin_sample", str(exc))
            return
        self.out(keys.SKIN_PAIN, pain)
        if impact is not None and impact.basis != self.basis:
            self.basis = impact.basis
            if impact.known:
                self.diag("info", "impact_predicted", "impact forces predicted from the robot state again",
                          every_s=0)
            else:
                self.diag("warning", "impact_unknown",
                          f"no impact prediction ({impact.basis}): every pad at its most sensitive "
                          f"(thresholds x {self.estimator.floor:g})", every_s=0)
