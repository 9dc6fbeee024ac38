"""The reflex strategies' registry: the modules of the package are the strategies, in rank order."""

import argparse
import sys

import numpy as np
import pytest

from nwr.common import messages as m
from nwr.common.config import PlannerSection, Profile
from nwr.common.errors import ConfigError
from nwr.common.robot import RobotModel, load_description
from nwr.services.planner import main, strategies
from nwr.services.planner.core import Planner

DESC = load_description()
MODEL = RobotModel(DESC)
PAPER = ("uniform", "location", "cartesian", "cartesian-smooth")
ALL = (*PAPER, "whole-arm")  # the paper's four, then this project's whole-arm withdrawal

# A strategy as a new module would define it: lift the upper arm a little (ranked between location and cartesian).
LIFT = '''
import numpy as np

from nwr.services.planner.strategies import Onset, ReflexStrategy


class Lift(ReflexStrategy):
    name = "lift"
    rank = 25
    mode = "position"

    def start(self, q, contact):
        return Onset(target=q + np.array([0.0, -0.1, 0.0, 0.0, 0.0, 0.0]))


STRATEGY = Lift
'''


@pytest.fixture
def dropped(tmp_path, monkeypatch):
    """A directory added to the strategies package's path: a module written there is in the package."""
    monkeypatch.setattr(strategies, "__path__", [*strategies.__path__, str(tmp_path)])
    strategies._registry.cache_clear()
    yield tmp_path
    strategies._registry.cache_clear()
    for module in tmp_path.glob("*.py"):
        sys.modules.pop(f"{strategies.__name__}.{module.stem}", None)
        vars(strategies).pop(module.stem, None)


def test_the_registry_lists_the_papers_strategies_then_the_projects_in_order():
    assert strategies.names() == ALL


@pytest.mark.parametrize("name", ALL)
def test_each_strategy_is_built_under_its_name(name):
    strategy = strategies.build(PlannerSection(strategy=name), DESC, MODEL, 0.9 * DESC.v_max)
    assert strategy.name == name and strategy.mode in ("position", "velocity")


def test_an_unknown_strategy_is_a_configuration_error_naming_the_known_ones():
    with pytest.raises(ConfigError) as err:
        strategies.build(PlannerSection(strategy="cartesain"), DESC, MODEL, 0.9 * DESC.v_max)
    assert "'cartesain'" in str(err.value) and ", ".join(ALL) in str(err.value)


def test_the_planner_process_checks_the_strategy_before_it_starts():
    profile = Profile()
    profile.planner.strategy = "cartesain"
    with pytest.raises(ConfigError, match="cartesain"):
        main.run(profile, argparse.Namespace(name=None, reflex=None))


def test_a_module_dropped_into_the_package_is_a_strategy(dropped):
    (dropped / "lift.py").write_text(LIFT)
    assert strategies.names() == ("uniform", "location", "lift", "cartesian", "cartesian-smooth", "whole-arm")
    planner = Planner(PlannerSection(strategy="lift"), DESC, MODEL)
    planner.on_state(DESC.home.copy(), following=True)
    while planner.mode != "TASK":
        planner.step(0)
    pad = DESC.pads[3]
    gains = [0.0] * len(DESC.pads)
    gains[pad.id] = 1.0
    contact = m.Contact(pad=pad.id, name=pad.name, region=pad.region, change_hpa=25.0, level=4, gain=1.0)
    first = planner.on_pain(m.SkinPain(seq=1, stamp_ns=0, trace=m.Trace(1, 0), model="continuous",
                                       level=[1] * len(gains), gain=gains, strongest=contact), 0)
    assert isinstance(first, m.PositionCommand) and planner.status(0).reflex.strategy == "lift"
    target = planner.reflex.target.copy()
    while planner.mode == "REFLEX":
        planner.step(0)
    np.testing.assert_allclose(planner.q, target, atol=1e-6)


def test_a_module_without_a_strategy_is_an_error(dropped):
    (dropped / "helpers.py").write_text("X = 1\n")
    with pytest.raises(TypeError, match="helpers defines no STRATEGY"):
        strategies.names()
