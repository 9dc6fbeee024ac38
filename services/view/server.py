"""The Foxglove WebSocket server both view modes share (live and ``nwr view FILE``).

Loopback by default. The Foxglove WebSocket protocol has no authentication:
anyone who can reach the port sees everything the view serves, so ``--host``
other than loopback belongs on a trusted lab network only.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from typing import Any

import foxglove
from foxglove.websocket import Capability, ChannelView, Client, ServerListener

from nwr.services.view.core import ROBOT_DESCRIPTION, ChannelSpec, Output

log = logging.getLogger(__name__)

LOOPBACK = ("127.0.0.1", "localhost", "::1")
DEFAULT_PORT = 8765
STATS_TOPIC = "/nwr/view"
STATS_SCHEMA: dict[str, Any] = {
    "title": "nwr.view.Stats", "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer"}, "frames": {"type": "integer"}, "scene_hz": {"type": "number"},
        "cpu_percent": {"type": "number"}, "cpu_s": {"type": "number"}, "wall_s": {"type": "number"},
        "overruns": {"type": "integer"},
    },
}


def warn_if_exposed(host: str) -> None:
    if host not in LOOPBACK:
        log.warning("serving on %s: the Foxglove WebSocket protocol has no authentication, anyone who can "
                    "reach this port sees the robot's data; use --host only on a trusted lab network", host)


class ViewServer(ServerListener):
    """A foxglove-sdk server with the view's ``channels`` (:func:`~nwr.services.view.core.channel_specs`, the
    core's) in a context of their own.

    The robot description is logged once per subscription to it (a late
    client must get it too): ``on_subscribe`` only raises a flag, the owner's
    loop logs it, so no logging happens on the server's thread.
    """

    def __init__(self, host: str, port: int, *, name: str, channels: Sequence[ChannelSpec],
                 capabilities: list[Capability] | None = None,
                 playback_time_range: tuple[int, int] | None = None, listener: Any = None) -> None:
        warn_if_exposed(host)
        self.context = foxglove.Context()
        self.channels = {
            spec.topic: foxglove.Channel(
                spec.topic, message_encoding=spec.message_encoding, context=self.context,
                schema=foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema))
            for spec in channels
        }
        self.stats = foxglove.Channel(STATS_TOPIC, schema=STATS_SCHEMA, context=self.context)
        self.description_wanted = threading.Event()
        self._delegate = listener
        # Time always: live and in playback the view broadcasts the time of what it serves (without the
        # capability the SDK logs an error on every broadcast).
        capabilities = [*(capabilities or []), *([] if Capability.Time in (capabilities or []) else [Capability.Time])]
        self.server = foxglove.start_server(
            name=name, host=host, port=port, capabilities=capabilities, server_listener=self,
            context=self.context, playback_time_range=playback_time_range,
        )
        self.port = self.server.port
        log.info("Foxglove WebSocket server on ws://%s:%d", host, self.port)

    # ServerListener
    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        if channel.topic == ROBOT_DESCRIPTION:
            self.description_wanted.set()

    def on_playback_control_request(self, request: Any) -> Any:
        if self._delegate is None:
            return None
        return self._delegate(request)

    def log(self, output: Output) -> None:
        self.channels[output.topic].log(output.data, log_time=output.log_time_ns)

    def stop(self) -> None:
        self.server.stop()
