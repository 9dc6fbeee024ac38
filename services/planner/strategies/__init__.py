"""Reflex strategies: the interface the planner core drives, and their registry.

Every module of this package is one strategy: it defines a subclass of
:class:`ReflexStrategy` and names it ``STRATEGY``. The registry imports the
modules it finds here (nothing else lists them) and orders the strategies by
their ``rank``, the order of CLI choices and figures. Adding a strategy is
adding a module.

The core's state machine asks a strategy for two things. At a contact,
:meth:`ReflexStrategy.start` gives the reflex's :class:`Onset`. Then, by the
strategy's command ``mode``:

- ``"position"``: the onset's joint ``target``, which the core reaches with a
  jerk-limited trajectory (ruckig); the reflex ends on arrival;
- ``"velocity"``: a joint velocity every control cycle
  (:meth:`ReflexStrategy.velocity`), streamed for the strategy's
  ``duration_s`` (``planner.reflex_duration_s`` unless it sets its own).
"""

from __future__ import annotations

import copy
import functools
import importlib
import pkgutil
import sys
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, ClassVar, Literal

import numpy as np

from nwr.common import messages as m
from nwr.common.config import PlannerSection
from nwr.common.errors import ConfigError
from nwr.common.guards import Guard
from nwr.common.plugins import NoSettings, Plugins
from nwr.common.robot import RobotDescription, RobotModel
from nwr.common.section import Section

if TYPE_CHECKING:
    from nwr.services.planner.contacts import ContactPoint

CommandMode = Literal["position", "velocity"]


@dataclass(frozen=True)
class Onset:
    """How a reflex starts."""

    target: np.ndarray | None = None  # position mode: the joint target, rad
    direction: list[float] = field(default_factory=list)  # velocity mode: the pad's Cartesian velocity, m/s
    corrected: bool = False  # guarded mode changed the planned motion
    # Why the motion is not the strategy's plain withdrawal ("" when it is): ReflexInfo.reason.
    reason: str = ""
    # ReflexInfo.reach_m: how far the pad would withdraw at full gain, m (0: the strategy does not say).
    reach_m: float = 0.0

    @property
    def sideways(self) -> bool:
        """Velocity mode: the pad withdraws across its normal, away from the contact point (its joints cannot
        move it along the normal); the retreat check then judges the withdrawal by the distance from it."""
        return self.reason == "sideways"


class ReflexStrategy(ABC):
    """One reflex strategy, built once per planner from its profile section."""

    name: ClassVar[str]  # the profile's planner.strategy
    rank: ClassVar[int]  # place among the strategies (names())
    mode: ClassVar[CommandMode]
    # Its own parameters, the profile's [planner.<name>] (KIND.settings), and which of them are safety-relevant
    # beside a person; a staticmethod check_settings(settings, profile, desc) may add cross-checks.
    Settings: ClassVar[type[Section]] = NoSettings
    GUARDS: ClassVar[dict[str, Guard]] = {}

    # Velocity mode: the return to the saved pose goes back along the withdrawal's own path (through poses
    # on it), not on the straight line in joint space, which can swing another part of the arm closer to the
    # contact than the withdrawal ever brought it.
    retraces = False

    def __init__(self, cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> None:
        self.model = model
        # Velocity mode: how long the core streams velocity(), s.
        self.duration_s = cfg.reflex_duration_s
        # Control cycles of the current reflex whose velocity the guard
        # corrected (a position target's correction is in its Onset).
        self.corrections = 0
        # Diagnostics for the planner to publish (level, code, message); live cycles only.
        self.notes: list[tuple[str, str, str]] = []
        # The other active contacts with a gain when the reflex (re)starts (set_contacts), by pad.
        self.other_contacts: list[ContactPoint] = []

    def set_contacts(self, q: np.ndarray, contacts: list[ContactPoint], main: int) -> None:
        """The recent contacts (:mod:`nwr.services.planner.contacts`) at the commanded pose ``q``, the reflex's
        own on pad ``main``; the planner gives them before each :meth:`start` and, during a reflex, at each
        pain message. The paper's strategies keep the other active ones with a gain (:attr:`other_contacts`)
        and react to those at the next (re)start (docs/reflexes.md "Every contact counts"): one contact gives
        exactly the published motion."""
        self.other_contacts = others(contacts, main)

    @abstractmethod
    def start(self, q: np.ndarray, contact: m.Contact) -> Onset:
        """Begin (or update) a reflex on ``contact`` at the commanded pose ``q``."""

    def velocity(self, q: np.ndarray, t: float, *, count: bool = True) -> np.ndarray:
        """Velocity mode: the joint velocity at pose ``q``, ``t`` s into the reflex.

        ``count``: whether a guard correction counts in :attr:`corrections`
        (not when the retreat check integrates the stream ahead).
        """
        raise NotImplementedError(f"the {self.name} strategy is position-controlled: it has no velocity stream")

    def snapshot(self) -> ReflexStrategy:
        """A copy of the current reflex's state, for a retreat check on another thread (and model)."""
        return copy.copy(self)


def others(contacts: list[ContactPoint], main: int) -> list[ContactPoint]:
    """The active contacts with a gain among ``contacts`` besides the one on pad ``main``."""
    return [contact for contact in contacts if contact.pad != main and contact.gain > 0.0]


def discover(package: ModuleType) -> dict[str, type[ReflexStrategy]]:
    """The strategies of ``package``'s modules (each one's ``STRATEGY``), by name in rank order."""
    found: dict[str, type[ReflexStrategy]] = {}
    for info in pkgutil.iter_modules(package.__path__):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        strategy = getattr(module, "STRATEGY", None)
        if not (isinstance(strategy, type) and issubclass(strategy, ReflexStrategy)):
            raise TypeError(f"{module.__name__} defines no STRATEGY (a ReflexStrategy subclass): every module of "
                            f"{package.__name__} is one reflex strategy")
        if strategy.name in found:
            raise TypeError(f"{module.__name__} and {found[strategy.name].__module__} both define the "
                            f"strategy {strategy.name!r}")
        found[strategy.name] = strategy
    return dict(sorted(found.items(), key=lambda item: item[1].rank))


@functools.cache
def _registry() -> dict[str, type[ReflexStrategy]]:
    return discover(sys.modules[__name__])


def names() -> tuple[str, ...]:
    """The strategies' names, in rank order: uniform, location, cartesian, cartesian-smooth, whole-arm."""
    return tuple(_registry())


def check(name: str) -> None:
    """ConfigError unless ``name`` is a strategy."""
    if name not in _registry():
        raise ConfigError(f"planner.strategy {name!r} is not a reflex strategy; the strategies are "
                          f"{', '.join(names())}")


class Strategies(Plugins):
    """The strategies as plug-ins with their tables ``[planner.<name>]`` (:class:`nwr.common.plugins.Plugins`)."""

    section = "planner"
    field = "planner.strategy"
    what = "strategy"

    def names(self) -> list[str]:
        return list(_registry())

    def declared(self, name: str) -> type[ReflexStrategy]:
        check(name)
        return _registry()[name]


KIND = Strategies()


def build(cfg: PlannerSection, desc: RobotDescription, model: RobotModel, v_limit: np.ndarray) -> ReflexStrategy:
    """The strategy ``cfg.strategy`` (ConfigError naming the strategies if there is none by that name)."""
    check(cfg.strategy)
    return _registry()[cfg.strategy](cfg, desc, model, v_limit)
