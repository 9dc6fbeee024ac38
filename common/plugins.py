"""Plug-ins: the modules of one package, each a plug-in named after itself; nothing else lists them.

The bridge's backends (:mod:`nwr.services.bridge.backends`), the gateway's
live skin sources (:mod:`nwr.services.gateway.sources`) and the planner's
reflex strategies (:mod:`nwr.services.planner.strategies`) are each a kind of
plug-in (:class:`Plugins`): adding one is adding a module. A module is
imported only when its name is asked for, so that a plug-in's own library
(ur_rtde, rospy) loads only where it is chosen.

A plug-in keeps its parameters beside its code: its ``Settings`` (a
:class:`~nwr.common.section.Section`) is the profile's table named after it
under its service's section (``[bridge.ur_rtde]``, ``[gateway.sim]``,
``[planner.whole-arm]``), decoded and checked when a profile is loaded
(:meth:`Plugins.check`); its ``GUARDS`` name the fields that are
safety-relevant beside a person (``[safety]`` acknowledges them like any
other, :mod:`nwr.common.config`), and an optional ``check_settings(settings,
profile, desc)`` the cross-checks that need the profile or the robot; an optional ``robot_settings(desc)``
the defaults a robot gives it (its safety-relevant fields are guarded against those).
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterable, Iterator
from types import ModuleType
from typing import TYPE_CHECKING, Any, TypeVar

import msgspec

from nwr.common.config import Plugged
from nwr.common.errors import ConfigError
from nwr.common.guards import Guard, Guarded
from nwr.common.section import Section

if TYPE_CHECKING:
    from nwr.common.config import Profile
    from nwr.common.robot import RobotDescription

S = TypeVar("S", bound=Section)


class NoSettings(Section):
    """The settings of a plug-in that has none: its table must be empty."""


class Plugins:
    """The plug-ins of one kind, each with its table ``[<section>.<name>]`` in the profile.

    A subclass says which plug-ins there are (:meth:`names`) and what each
    declares (:meth:`declared`: its Settings class, GUARDS and
    check_settings); this base decodes, checks and guards their tables.
    """

    section: str  # the profile section whose tables these are (e.g. "bridge")
    field: str  # the profile field that chooses one (e.g. "bridge.backend")
    what: str  # what one is called (e.g. "backend")

    def names(self) -> list[str]:
        raise NotImplementedError

    def declared(self, name: str) -> Any:
        """What plug-in ``name`` declares: an object with ``Settings``, ``GUARDS``, ``check_settings`` (each
        optional)."""
        raise NotImplementedError

    def settings_class(self, name: str) -> type[Section]:
        cls = getattr(self.declared(name), "Settings", None)
        return cls if isinstance(cls, type) and issubclass(cls, Section) else NoSettings

    def settings(self, section: Plugged, name: str, cls: type[S] | None = None) -> S:
        """Plug-in ``name``'s settings: its table of ``section`` decoded (its defaults where it has none)."""
        kind = cls or self.settings_class(name)
        try:
            return msgspec.convert(section.plugins.get(name, {}), kind)  # type: ignore[return-value]
        except msgspec.ValidationError as exc:
            raise ConfigError(f"{self.section}.{name}: {exc} (docs/profile.md gives every field's bounds)") from None

    def check(self, section: Plugged, profile: Profile, desc: RobotDescription) -> list[Guarded]:
        """Every table of ``section`` names a plug-in of this kind and holds its settings, which pass the plug-in's
        own checks; the safety-relevant fields of every plug-in (to acknowledge in ``[safety]``)."""
        names = self.names()
        for name in section.plugins:
            if name not in names:
                raise ConfigError(f"[{self.section}.{name}] names no {self.what}; the {self.what}s are "
                                  f"{', '.join(names)} (a table under [{self.section}] is one's settings)")
        guarded: list[Guarded] = []
        for name in names:
            declared = self.declared(name)
            settings: Section = self.settings(section, name)
            check = getattr(declared, "check_settings", None)
            if check is not None:
                check(settings, profile, desc)
            # A plug-in whose defaults are the robot's (robot_settings(desc)) is guarded against those.
            robot_settings = getattr(declared, "robot_settings", None)
            default = robot_settings(desc) if robot_settings is not None else self.settings_class(name)()
            for field, guard in _guards(declared).items():
                guarded.extend(_guarded(f"{self.section}.{name}.{field}", settings, default, field, guard))
        return guarded

    def resolve(self, section: Plugged, names: Iterable[str]) -> None:
        """Write the full settings (defaults included) of plug-ins ``names`` into their tables, as the session's
        journaled profile keeps them."""
        for name in names:
            section.plugins[name] = msgspec.to_builtins(self.settings(section, name))


def _guards(declared: Any) -> dict[str, Guard]:
    guards = getattr(declared, "GUARDS", {})
    return dict(guards) if isinstance(guards, dict) else {}


def _guarded(dotted: str, settings: Section, default: Section, field: str, guard: Guard) -> Iterator[Guarded]:
    """The safety-relevant values at ``field`` (a table of rows: each row, ``field.row``)."""
    head, _, row = field.partition(".")
    value, base = getattr(settings, head), getattr(default, head)
    if row:
        if row in value:
            yield Guarded(dotted, value[row], base.get(row, value[row]), guard)
        elif row in base:  # a row the profile leaves to the default (the robot's): held at it
            yield Guarded(dotted, base[row], base[row], guard)
    else:
        yield Guarded(dotted, value, base, guard)


class Kind(Plugins):
    """The modules of ``package`` (whose ``__path__`` is ``path``), each a plug-in that sets ``NAME`` to its
    own name and has what ``needs`` says (attribute -> "callable", "bool" or "str")."""

    def __init__(self, package: str, path: Iterable[str], field: str, what: str, needs: dict[str, str]) -> None:
        self.package = package
        self.path = list(path)
        self.field = field
        self.section = field.partition(".")[0]
        self.what = what
        self.needs = needs

    def names(self) -> list[str]:
        """The plug-ins there are (the package's modules)."""
        return sorted(info.name for info in pkgutil.iter_modules(self.path) if not info.name.startswith("_"))

    def get(self, name: str) -> ModuleType:
        """The module of plug-in ``name``; ConfigError naming the ones there are, or what the module lacks."""
        folder = self.package.removeprefix("nwr.").replace(".", "/")
        if name not in self.names():
            raise ConfigError(f"{self.field} = {name!r} is no {self.what}; there are: {', '.join(self.names())} "
                              f"({folder}/)")
        module = importlib.import_module(f"{self.package}.{name}")
        lacks = [] if getattr(module, "NAME", None) == name else [f"NAME = {name!r}"]
        for attr, kind in self.needs.items():
            value = getattr(module, attr, None)
            if not (callable(value) if kind == "callable" else type(value).__name__ == kind):
                lacks.append(f"{attr} ({kind})")
        if lacks:
            raise ConfigError(f"{folder}/{name}.py is no {self.what}: it lacks {', '.join(lacks)}")
        return module

    declared = get


def check_all(kinds: Iterable[Plugins], profile: Profile, desc: RobotDescription) -> list[Guarded]:
    """Every kind's tables checked (:meth:`Plugins.check`); their safety-relevant fields."""
    guarded: list[Guarded] = []
    for kind in kinds:
        section = getattr(profile, kind.section)
        guarded.extend(kind.check(section, profile, desc))
    return guarded
