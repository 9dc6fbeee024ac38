"""The gain estimator's wiring: skin/pressure (+ robot/state) -> skin/pain, one message per skin sample.

With the effective-mass model (``gain.model = "effective-mass"``) it also
takes the robot state: each state's impact prediction is made when the state
arrives (:class:`~nwr.services.gain.impact.ImpactModel`), so that a skin
sample only looks it up; the paper's models do not subscribe to it. With
``gain.torque.enabled`` it takes the robot state too: each state's external
torques go through :class:`~nwr.services.gain.torque.TorqueDetector`, and a
skin sample blind where that contact is located gets its gain
(:func:`~nwr.services.gain.torque.blind_fallback`).

The call order of the service, with no Zenoh, no thread and no clock of its
own (its time comes from the journal): the live process
(:mod:`.main`), lockstep runs and ``nwr verify`` all run this code.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.journal import Journal
from nwr.common.robot import RobotModel, load_description
from nwr.common.skin import load_skin
from nwr.services.gain.core import EFFECTIVE_MASS, GainEstimator
from nwr.services.gain.impact import MEASURED, ImpactModel
from nwr.services.gain.taxels import TaxelGain
from nwr.services.gain.torque import TorqueContact, TorqueDetector, blind_fallback
from nwr.services.wiring import Diag, Input, Out, Wiring, receives

SERVICE = "gain"


class GainWiring(Wiring):
    service = SERVICE
    outputs = (keys.SKIN_PAIN,)

    def __init__(self, profile: Profile, *, journal: Journal, out: Out, diag: Diag) -> None:
        desc = load_description(profile.robot.description or None)
        self.estimator = GainEstimator(profile.gain, desc.pads)
        skin = load_skin(profile, desc)
        # A taxel skin (robot.skin = "taxels"): contacts from the taxels, pain per pad (.taxels).
        self.taxels = TaxelGain(profile.gain, desc.pads, skin, profile.gateway.contact_hpa) \
            if skin is not None else None
        if self.taxels is not None and profile.gain.torque.enabled:
            raise ConfigError("gain.torque locates a contact on a pad the skin is blind at; on a taxel skin it is "
                              "not available: set gain.torque.enabled = false")
        model = RobotModel(desc) if profile.gain.model == EFFECTIVE_MASS or profile.gain.torque.enabled else None
        self.impacts = ImpactModel(profile.gain.effective_mass, model) \
            if profile.gain.model == EFFECTIVE_MASS and model is not None else None
        tcfg = self.torque_cfg = profile.gain.torque
        self.pads = desc.pads
        self.pl3_gain = profile.gain.pl3_gain
        self.torque = TorqueDetector(model, np.full(model.nq, tcfg.on_nm),
                                     np.full(model.nq, tcfg.on_nm * tcfg.off_ratio),
                                     baseline=tcfg.baseline) if tcfg.enabled and model is not None else None
        self.torque_contact: TorqueContact | None = None
        self.torque_ns = 0  # the stamp of the state that gave torque_contact
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
        """The robot state only for the effective-mass model and the torque fallback."""
        return inp.name != "state" or self.impacts is not None or self.torque is not None

    @receives("state", keys.ROBOT_STATE)
    def on_state(self, state: m.RobotState) -> None:
        if self.impacts is not None:
            self.impacts.update(state)
        if self.torque is not None:
            self.on_torque(state)

    def on_torque(self, state: m.RobotState) -> None:
        assert self.torque is not None
        if state.pose_stale or not state.tau_ext:
            if self.torque_contact is not None:  # no measured state: learn the offset again when one comes
                self.torque.reset()
                self.torque_contact = None
            return
        try:
            contact = self.torque.update(np.asarray(state.q, dtype=float), np.asarray(state.tau_ext, dtype=float),
                                         np.asarray(state.dq, dtype=float), state.stamp_ns)
        except ValueError as exc:
            self.diag("warning", "bad_torque_state", str(exc))
            self.torque.reset()
            self.torque_contact = None
            return
        self.torque_contact, self.torque_ns = contact, state.stamp_ns

    @receives("pressure", keys.SKIN_PRESSURE)
    def on_pressure(self, sample: m.SkinPressure) -> None:
        now = self.journal.now_ns()
        if self.taxels is not None:
            try:
                self.out(keys.SKIN_PAIN, self.taxels.process(sample, now))
            except ValueError as exc:
                self.diag("warning", "bad_skin_sample", str(exc))
            return
        impact = self.impacts.predict(now) if self.impacts is not None else None
        try:
            pain = self.estimator.process(sample, now, impact)
        except ValueError as exc:
            self.diag("warning", "bad_skin_sample", str(exc))
            return
        contact = self.torque_contact
        if contact is not None and contact.detected and sample.valid and \
                now - self.torque_ns <= self.torque_cfg.state_timeout_s * 1e9:
            pain = blind_fallback(pain, sample.valid, contact, self.pads, self.torque_cfg.full_force_n,
                                  self.pl3_gain)
            if pain.torque_pads:
                self.diag("warning", "torque_contact", f"the skin is blind at {self.pads[contact.pad].name}: "
                          f"its gain {pain.gain[contact.pad]:.2f} from the arm's external torques "
                          f"({contact.force_n:.0f} N)", every_s=1.0)
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
