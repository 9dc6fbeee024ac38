"""The bridge's backends, one module each: the arm the bridge drives (``bridge.backend``, ``--backend``).

A module of this package is a backend named after itself: it sets ``NAME``
to that name, ``REAL_ARM`` (a real arm: the bridge needs ``--robot-ip`` and
``--i-am-next-to-the-robot``, and a re-run by ``nwr verify`` cannot stand
in for its measurements) and defines ``make(cfg, env, q0, args) ->
Backend`` (:class:`nwr.services.bridge.backend.Backend`: connect,
get_observation, send_action, stop). Nothing else lists them: adding a
backend is adding a module; its own library is imported there, when it is
chosen, so that the others never load it.
"""

from __future__ import annotations

import importlib
import pkgutil
from types import ModuleType

from nwr.common.errors import ConfigError


def names() -> list[str]:
    """The backends there are (this package's modules)."""
    return sorted(info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_"))


def plugin(name: str) -> ModuleType:
    """The module of backend ``name``; ConfigError naming the ones there are."""
    if name not in names():
        raise ConfigError(f"bridge.backend = {name!r} is no backend; there are: {', '.join(names())} "
                          "(services/bridge/backends/)")
    module = importlib.import_module(f"{__name__}.{name}")
    if getattr(module, "NAME", None) != name or not callable(getattr(module, "make", None)) \
            or not isinstance(getattr(module, "REAL_ARM", None), bool):
        raise ConfigError(f"services/bridge/backends/{name}.py is no backend: it must set NAME = {name!r} and "
                          "REAL_ARM, and define make(cfg, env, q0, args)")
    return module
