"""The view's subcommand of ``nwr``: ``view [FILE]`` (``nwr export --foxglove IN OUT``, the view's scene
written into a recording, is :mod:`nwr.services.tools.recordings.export`).

``nwr view`` is the live service (as ``nwr run view``). ``nwr view FILE``
serves a recording with the same channels over the same server, with
Foxglove's playback control: the client's play, pause, seek and speed
requests drive a :class:`~nwr.services.view.playback.Player` over the
recording's precomputed view timeline.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any

from foxglove.websocket import Capability, PlaybackCommand, PlaybackState, PlaybackStatus

from nwr.services.profile import profile_for
from nwr.services.view import main as view_main
from nwr.services.view.core import Output
from nwr.services.view.export import ExportError, load_records, make_core, recording_timeline
from nwr.services.view.playback import Player
from nwr.services.view.server import ViewServer

log = logging.getLogger(__name__)

_STATUS = {"playing": PlaybackStatus.Playing, "paused": PlaybackStatus.Paused, "ended": PlaybackStatus.Ended}
TIME_EVERY_NS = 33_000_000  # server time broadcasts while playing, ~30 Hz


def register(subparsers: Any) -> None:
    view = subparsers.add_parser(
        "view", help="serve the live 3D scene (or a recording) to Foxglove over WebSocket",
        description="Without FILE: the live view service (same as `nwr run view`): the arm, its pads coloured by "
                    "gain, the contact and the reflex, and plottable signals, on ws://127.0.0.1:8765. With FILE: "
                    "serve that recording the same way, with play, pause, seek and speed from Foxglove's "
                    "playback bar. See docs/view.md.",
    )
    view.add_argument("file", nargs="?", help="MCAP recording to serve (default: the live pipeline)")
    view_main.add_arguments(view)
    view.add_argument("--play", action="store_true", help="FILE: start playing at once (default: paused)")
    view.add_argument("--speed", type=float, default=1.0, help="FILE: initial playback speed (default: 1)")
    view.set_defaults(handler=_view)

def _view(args: argparse.Namespace) -> int:
    profile = profile_for(args)
    if args.file is None:
        return view_main.run(profile, args)
    view_main.check_arguments(args)
    return serve_recording(Path(args.file), args, profile.robot.description or None)


class PlaybackControl:
    """Applies Foxglove's playback requests to the player (on the server's thread, under the lock)."""

    def __init__(self, player: Player, lock: threading.Lock, on_seek: Any) -> None:
        self.player = player
        self.lock = lock
        self.on_seek = on_seek

    def __call__(self, request: Any) -> PlaybackState:
        now = time.monotonic_ns()
        with self.lock:
            player = self.player
            did_seek = request.seek_time is not None
            if did_seek:
                player.seek(request.seek_time, now)
                self.on_seek()
            player.set_speed(request.playback_speed, now)
            if request.playback_command == PlaybackCommand.Play:
                player.play(now)
            elif request.playback_command == PlaybackCommand.Pause:
                player.pause(now)
            return PlaybackState(status=_STATUS[player.status], current_time=player.current_time(now),
                                 playback_speed=player.speed, did_seek=did_seek, request_id=request.request_id)


def serve_recording(path: Path, args: argparse.Namespace, description: str | None = None) -> int:
    records, _metadata = load_records(path)
    if not records:
        raise ExportError(f"{path} holds no message of the pipeline: nothing to show")
    log.info("computing the view of %s (%d messages)...", path, len(records))
    core = make_core(description)
    outputs: list[Output] = recording_timeline(records, core, args.rate)
    del records
    description_output = outputs[0]
    times = [o.log_time_ns for o in outputs]
    player = Player(times, speed=args.speed)
    period_ns = round(1e9 / args.rate)
    lock = threading.Lock()
    resend: list[tuple[int, int]] = []

    def on_seek() -> None:
        # Paused after a seek, the panels must show that instant: the last frame before it is re-sent.
        stop = player.position
        start = max(0, stop - 1)
        while start > 0 and times[start - 1] > times[stop - 1] - period_ns:
            start -= 1
        resend.append((start, stop))

    control = PlaybackControl(player, lock, on_seek)
    view = ViewServer(args.host, args.port, name=f"nwr view {path.name}", channels=core.channels,
                      capabilities=[Capability.PlaybackControl, Capability.Time],
                      playback_time_range=(player.start_ns, player.end_ns), listener=control)
    stop = threading.Event()
    old = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    log.info("serving %s (%.1f s, %d messages) on ws://%s:%d: use Foxglove's playback bar to play, pause and seek",
             path, (player.end_ns - player.start_ns) / 1e9, len(outputs), args.host, view.port)
    if args.play:
        player.play(time.monotonic_ns())
    last_time_sent = 0
    last_status = player.status
    try:
        while not stop.is_set():
            now = time.monotonic_ns()
            with lock:
                if view.description_wanted.is_set():
                    view.description_wanted.clear()
                    view.log(Output(description_output.topic, player.current_time(now), description_output.data))
                spans = resend + [player.advance(now)]
                resend.clear()
                for start, end in spans:
                    for output in outputs[start:end]:
                        view.log(output)
                current = player.current_time(now)
                if player.status == "playing" and now - last_time_sent >= TIME_EVERY_NS:
                    view.server.broadcast_time(current)
                    last_time_sent = now
                if player.status != last_status and player.status == "ended":
                    view.server.broadcast_playback_state(PlaybackState(
                        status=PlaybackStatus.Ended, current_time=current, playback_speed=player.speed,
                        did_seek=False, request_id=None))
                last_status = player.status
                wait = player.wait_s(now)
            stop.wait(max(wait, 0.001))
    finally:
        view.stop()
        for s, handler in old.items():
            signal.signal(s, handler)
    return 0
