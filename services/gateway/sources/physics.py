"""A physics world's skin (``gateway.source = "physics"``): the pads as the world the bridge hosts samples them.

The bridge's ``physics`` backend hosts the world (the arm, its skin, the
people touching it) and publishes its skin samples on ``world/skin``; this
source takes each as a device's sample (:meth:`GatewayWiring.on_world_skin`,
an input of the gateway's wiring, journaled like any other). The touch
script's clock runs exactly as the simulated skin's (``--script``,
``--wait-for``, ``--notify-fd``, ``--exit-at-end``: :mod:`.sim`): each
tick publishes the touches that start on ``skin/touch``, which the bridge's
world turns into fingers pressing their pads; the pressure is the world's.

Before anything moves the script is checked against the world
(:func:`nwr.services.worlds.hosted.check_script`: a push no finger makes,
more fingers at once than the world holds) by the launcher; the bridge
refuses such a touch again when it comes.
"""

from __future__ import annotations

import argparse

from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.services.gateway.sources import sim

NAME = "physics"


def run(profile: Profile, args: argparse.Namespace) -> int:
    if getattr(args, "closed_loop", False):
        raise ConfigError("--closed-loop is the scripted skin's contact model; the physics world pushes back itself")
    return sim.run(profile, args)
