"""The profile as services and tools load it: :mod:`nwr.common.config`'s checks and the plug-ins' tables.

The plug-ins (skin sources, bridge backends, reflex strategies) keep their
settings beside their code (:mod:`nwr.common.plugins`). Loading a profile
here decodes and checks the tables of the kinds asked for (a service: its
own; a tool or a launch: all) against the robot, takes their safety-relevant
fields into ``[safety]``'s acknowledgements, and writes each of those
plug-ins' full settings into its table, so that a session's journaled
profile holds every value the service ran with (``nwr verify`` re-runs it
as it was). A service process loads no other service's plug-ins.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Iterable

from nwr.common import config
from nwr.common.config import Profile
from nwr.common.guards import Guarded
from nwr.common.launch import apply_env_overrides
from nwr.common.plugins import Plugins, check_all
from nwr.common.robot import RobotDescription, load_description

# The profile section each kind's tables are under -> the package that is the kind (its KIND).
PACKAGES = {
    "gateway": "nwr.services.gateway.sources",
    "bridge": "nwr.services.bridge.backends",
    "planner": "nwr.services.planner.strategies",
}
ALL = tuple(PACKAGES)


def kinds(sections: Iterable[str] = ALL) -> tuple[Plugins, ...]:
    """The kinds of plug-in whose tables are under ``sections`` (imported here, when asked for)."""
    found = []
    for section in sections:
        kind = importlib.import_module(PACKAGES[section]).KIND
        assert isinstance(kind, Plugins)
        found.append(kind)
    return tuple(found)


def check_plugins(profile: Profile, desc: RobotDescription, sections: Iterable[str] = ALL) -> list[Guarded]:
    """The plug-in tables under ``sections`` checked; their safety-relevant fields (ConfigError naming the
    field)."""
    return check_all(kinds(sections), profile, desc)


def resolve(profile: Profile, sections: Iterable[str] = ALL) -> Profile:
    """``profile`` with the full settings (defaults included) of every plug-in under ``sections`` in its table."""
    for kind in kinds(sections):
        kind.resolve(getattr(profile, kind.section), kind.names())
    return profile


def load_profile(name_or_path: str | None = None, sections: Iterable[str] = ALL) -> Profile:
    """The profile by packaged name or path, checked in full, the plug-ins under ``sections`` included
    (:func:`resolve`); the others' tables are left as written, for the services that run them."""
    sections = tuple(sections)
    profile = config.load_profile(
        name_or_path, plugins=lambda p, desc: check_plugins(p, desc, sections), deferred=set(ALL) - set(sections))
    return resolve(profile, sections)


def profile_for(args: argparse.Namespace, sections: Iterable[str] = ALL) -> Profile:
    """The profile of ``--profile`` with the environment's overrides that the CLI read (``args.env_overrides``)."""
    return apply_env_overrides(load_profile(args.profile, sections), getattr(args, "env_overrides", {}))


def loosened_safety(profile: Profile) -> list[dict[str, object]]:
    """The profile's loosened safety values, its plug-ins' included, for the session's metadata."""
    desc = load_description(profile.robot.description or None)
    return config.loosened_safety(profile, check_plugins(profile, desc))
