"""A real skin's messages into the gateway's wiring: what the ROS 1 and ROS 2 skin sources share.

Each message's values are mapped onto the robot's pads by
:func:`nwr.common.skinmap.map_values` (the same code ``nwr import`` uses) and
fed to :meth:`GatewayWiring.on_sample`. What a message carries never stops
the gateway: a message of the wrong length, with non-finite or out-of-range
values is a diagnostic ``<source>_bad_message`` (rate limited) with those pads
invalid in that sample; every value out of range is the wrong units or scale
(``<source>_units``, an error); a message that cannot be used at all
(:meth:`SkinFeed.reject`) is counted and reported; no message for
``timeout_s`` is ``<source>_no_messages``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.door import Door
from nwr.common.node import Node
from nwr.common.skinmap import ABSOLUTE_RANGE_HPA, PadMap, map_values
from nwr.services.gateway.wiring import SERVICE, GatewayWiring

if TYPE_CHECKING:
    from nwr.common.config import Profile

log = logging.getLogger(__name__)


class SkinFeed:
    """A real skin source's callback and watchdog, around the gateway's wiring.

    ``cfg`` is the source's settings: ``topic``, ``values_field``, ``scale_hpa``, ``offset_hpa``, ``timeout_s``.
    """

    source = ""  # the source's name: its diagnostics' prefix and its table, gateway.<source>

    def __init__(self, cfg: Any, pmap: PadMap, wiring: GatewayWiring, lock: threading.Lock, diag: Any) -> None:
        self.cfg = cfg
        self.pmap = pmap
        self.wiring = wiring
        self.lock = lock
        self.diag = diag
        self.count = 0
        self.bad = 0
        self.last = time.monotonic()  # of the newest message (the start, before any)
        self.stale = False

    def reject(self, why: str) -> None:
        """A message that could not be used at all (no sample): counted and reported."""
        self.bad += 1
        self.diag("error", f"{self.source}_bad_message", f"a message on {self.cfg.topic} could not be used: {why}")

    def on_message(self, msg: Any) -> None:
        try:
            values = getattr(msg, self.cfg.values_field)
            mapped = map_values(values, self.pmap)
            with self.lock:
                self.wiring.on_sample(mapped.absolute_hpa)
        except Exception as exc:  # a callback must never end the subscription: report and go on
            self.reject(repr(exc))
            return
        self.count += 1
        self.last = time.monotonic()
        if self.stale:
            self.stale = False
            log.info("skin messages on %s again", self.cfg.topic)
        if mapped.problems:
            self.bad += 1
            if "range" in mapped.problems and not np.isfinite(mapped.absolute_hpa).any():
                # Every pad out of range: not a bad message but the wrong units or scale (a device in Pa).
                lo, hi = ABSOLUTE_RANGE_HPA
                self.diag("error", f"{self.source}_units",
                          f"every value on {self.cfg.topic} is outside {lo:g}..{hi:g} hPa after gateway."
                          f"{self.source}'s scale_hpa = {self.cfg.scale_hpa:g} and offset_hpa = "
                          f"{self.cfg.offset_hpa:g}: the skin is blind and the bridge holds the arm; a device that "
                          "reports Pa needs scale_hpa = 0.01, one that reports a change from rest an offset_hpa "
                          "(docs/lab.md)", every_s=10.0)
                return
            self.diag("warning", f"{self.source}_bad_message",
                      f"{self.cfg.topic}: " + "; ".join(mapped.problems.values()))

    def check_quiet(self, hint: str) -> None:
        """The watchdog: a diagnostic when no message came for ``timeout_s``."""
        quiet = time.monotonic() - self.last
        if quiet > self.cfg.timeout_s:
            self.stale = True
            self.diag("error", f"{self.source}_no_messages",
                      f"no skin message on {self.cfg.topic} for {quiet:.1f} s: the skin is stale (the bridge stops "
                      f"the arm); {hint}")


@contextlib.contextmanager
def gateway_node(profile: Profile, pmap: PadMap, source: str) -> Iterator[tuple[Node, GatewayWiring, threading.Lock]]:
    """The gateway's node for a real skin source: its wiring, the robot's state followed, the pad map's problems
    said (``<source>_mapping``), the origin published; yields the node, the wiring and the wiring's lock."""
    lock = threading.Lock()
    with Node(SERVICE, profile.robot.name, profile.zenoh, listen_slot="gateway", door=Door.of(profile),
              exclusive=True) as node:
        node.install_signal_handlers()
        wiring = node.wire(GatewayWiring, profile, lock, script=None)

        def on_state(state: m.RobotState) -> None:
            with lock:
                wiring.on_state(state)

        node.subscribe(keys.ROBOT_STATE, on_state)
        for problem in pmap.describe():
            node.diag("warning", f"{source}_mapping", f"gateway.{source}.pads: {problem}", every_s=0.0)
        with lock:
            wiring.origin()
        yield node, wiring, lock
