"""The bridge's backends, one module each: the arm the bridge drives (``bridge.backend``, ``--backend``).

A module of this package is a backend named after itself (a
:class:`nwr.common.plugins.Kind`): it sets ``NAME`` to that name,
``REAL_ARM`` (a real arm: the bridge needs ``--robot-ip`` and
``--i-am-next-to-the-robot``, and a re-run by ``nwr verify`` cannot stand
in for its measurements) and defines ``make(cfg, env, q0, args, desc) ->
Backend`` (:class:`nwr.services.bridge.backend.Backend`: connect,
get_observation, send_action, stop; ``desc`` the robot description).
A simulated backend (``sim``, ``physics``) is also what ``nwr verify`` and
lockstep build from the profile. Nothing else lists them: adding a
backend is adding a module; its own library is imported there, when it is
chosen, so that the others never load it.
"""

from __future__ import annotations

from nwr.common.plugins import Kind

KIND = Kind(__name__, __path__, "bridge.backend", "backend", {"REAL_ARM": "bool", "make": "callable"})
names = KIND.names
plugin = KIND.get
