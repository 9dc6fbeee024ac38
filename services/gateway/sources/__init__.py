"""The gateway's live skin sources, one module each: where a running gateway's samples come from.

A module of this package is a source named after itself (``gateway.source``):
it sets ``NAME`` to that name and defines ``run(profile, args) -> int``, the
gateway's process on that source (its Zenoh node, its wiring, its loop or
its callbacks). Nothing else lists them: adding a skin source is adding a
module. The sources a lockstep run steps sample by sample (recorded,
re-simulated, the simulated skin on simulated time) are
:mod:`nwr.services.gateway.stepped`.
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

from nwr.common.errors import ConfigError


def names() -> list[str]:
    """The live sources there are (this package's modules)."""
    return sorted(info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_"))


def live(name: str) -> ModuleType:
    """The module of the live source ``name``; ConfigError naming the ones there are."""
    if name not in names():
        raise ConfigError(f"gateway.source = {name!r} is no skin source; there are: {', '.join(names())} "
                          "(services/gateway/sources/)")
    module = importlib.import_module(f"{__name__}.{name}")
    if getattr(module, "NAME", None) != name or not callable(getattr(module, "run", None)):
        raise ConfigError(f"services/gateway/sources/{name}.py is no skin source: it must set NAME = {name!r} and "
                          "define run(profile, args)")
    return module
