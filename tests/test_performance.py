"""The pieces of issue #8 that are not timing: the retreat check off the planner's lock, real-time scheduling."""

import logging
import os

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import PlannerSection, Profile
from nwr.common.pacing import realtime
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner.core import Planner

DESC = load_description()
MODEL = RobotModel(DESC)


def pain_on(pad: str, gain: float, seq: int) -> m.SkinPain:
    info = DESC.pad(pad)
    gains = [0.0] * len(DESC.pads)
    gains[info.id] = gain
    contact = m.Contact(pad=info.id, name=info.name, region=info.region, change_hpa=25.0, level=4, gain=gain)
    return m.SkinPain(seq=seq, stamp_ns=0, trace=m.Trace(seq, 0), model="continuous", level=[1] * len(gains),
                      gain=gains, strongest=contact)


def reflex_started(strategy: str, pad: str = "wrist_3") -> Planner:
    planner = Planner(PlannerSection(strategy=strategy), DESC, MODEL)
    planner.on_state(DESC.home.copy(), following=True)
    while planner.mode != "TASK":
        planner.step(0)
    assert planner.on_pain(pain_on(pad, 0.8, 1), 0) is not None
    for _ in range(5):
        planner.step(0)
    return planner


@pytest.mark.parametrize("strategy", ["uniform", "location", "cartesian", "cartesian-smooth"])
def test_retreat_check_on_its_own_model_gives_what_assess_gives(strategy):
    # The planner's process runs the check in a thread of its own, on a model
    # of its own, between two lock holds: the figures must be assess()'s.
    a, b = reflex_started(strategy), reflex_started(strategy)
    check = b.retreat_check()
    assert check is not None
    for _ in range(3):  # the control loop goes on while the check runs
        b.step(0)
    assert b.apply_retreat(check, check.run(RobotModel(DESC)))
    expected = a.assess()
    assert b.reflex.retreat == expected
    assert b.changed  # published with the next status


def test_a_check_of_a_superseded_reflex_is_not_applied():
    planner = reflex_started("cartesian")
    check = planner.retreat_check()
    first = planner.reflex
    # A new contact on another pad updates the reflex while the check runs.
    assert planner.on_pain(pain_on("forearm_top", 1.0, 2), 0) is not None
    assert planner.reflex is not first
    assert not planner.apply_retreat(check, check.run(RobotModel(DESC)))
    assert planner.reflex.retreat is None and first.retreat is None


def test_no_check_outside_a_reflex():
    planner = Planner(PlannerSection(strategy="cartesian"), DESC, MODEL)
    planner.on_state(DESC.home.copy(), following=True)
    assert planner.retreat_check() is None


def test_real_time_scheduling_is_off_by_default_but_for_the_bridge():
    # the bridge asks for it (its control cycle and the controller's watchdog, docs/bridge.md); 0 leaves it alone
    assert Profile().planner.realtime_priority == 0 and Profile().bridge.realtime_priority == 20
    assert realtime(0, "planner") is False


def test_real_time_scheduling_fails_soft(monkeypatch, caplog):
    def refuse(*_args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level(logging.WARNING):
        assert realtime(20, "bridge") is False
    assert "not permitted" in caplog.text and "CAP_SYS_NICE" in caplog.text


def test_real_time_scheduling_applies_when_permitted(monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, policy, param: calls.append((pid, policy, param)))
    assert realtime(20, "bridge") is True
    assert calls == [(0, os.SCHED_FIFO, os.sched_param(20))]


def test_retreat_check_copies_the_stream_it_integrates():
    planner = reflex_started("cartesian")
    check = planner.retreat_check()
    assert check is not None and check.stream is not planner.strategy
    twist = planner.strategy._twist.copy()
    check.run(RobotModel(DESC))
    np.testing.assert_array_equal(planner.strategy._twist, twist)
    assert planner.strategy.model is MODEL
