"""The gateway's live skin sources, one module each: where a running gateway's samples come from.

A module of this package is a source named after itself (``gateway.source``,
a :class:`nwr.common.plugins.Kind`): it sets ``NAME`` to that name and
defines ``run(profile, args) -> int``, the gateway's process on that source
(its Zenoh node, its wiring, its loop or its callbacks). Nothing else lists
them: adding a skin source is adding a module. The sources a lockstep run
steps sample by sample (recorded, re-simulated, the simulated skin on
simulated time) are :mod:`nwr.services.gateway.stepped`.
"""

from __future__ import annotations

from nwr.common.plugins import Kind

KIND = Kind(__name__, __path__, "gateway.source", "skin source", {"run": "callable"})
names = KIND.names
live = KIND.get
