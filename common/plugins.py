"""Plug-ins: the modules of one package, each a plug-in named after itself; nothing else lists them.

The bridge's backends (:mod:`nwr.services.bridge.backends`) and the
gateway's live skin sources (:mod:`nwr.services.gateway.sources`) are each a
:class:`Kind`: adding one is adding a module that sets ``NAME`` to its own
name and defines what its kind needs. A module is imported only when its
name is asked for, so that a plug-in's own library (ur_rtde, rospy) loads
only where it is chosen.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterable
from types import ModuleType

from nwr.common.errors import ConfigError


class Kind:
    """One kind of plug-in: the modules of ``package`` (whose ``__path__`` is ``path``)."""

    def __init__(self, package: str, path: Iterable[str], field: str, what: str, needs: dict[str, str]) -> None:
        self.package = package
        self.path = list(path)
        self.field = field  # the profile field that names one (e.g. bridge.backend)
        self.what = what  # what one is called (e.g. "backend")
        self.needs = needs  # attribute -> what it must be: "callable", "bool" or "str"

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
