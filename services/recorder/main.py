"""Recorder process: every message under nwr/<robot>/ -> one MCAP file."""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import queue
from pathlib import Path

import zenoh

from nwr.common import keys
from nwr.common.config import Profile, encode_profile
from nwr.common.errors import DecodeError
from nwr.common.node import Node
from nwr.services.recorder.core import McapRecorder, _version

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--output", "-o", help="MCAP file to write (default: <recorder.directory>/<session>.mcap)")
    parser.add_argument("--session", help="session name (default: the start time)")
    parser.add_argument("--label", action="append", default=[], metavar="KEY=VALUE",
                        help="free label stored in the session metadata (repeatable), e.g. participant=P07")


def session_name() -> str:
    return dt.datetime.now().strftime("session-%Y%m%d-%H%M%S")


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.recorder
    session = args.session or session_name()
    path = Path(args.output) if args.output else Path(cfg.directory) / f"{session}.mcap"
    labels = {}
    for label in args.label:
        key, sep, value = label.partition("=")
        if not sep or not key:
            log.error("label %r is not KEY=VALUE", label)
            return 2
        labels[key] = value
    path.parent.mkdir(parents=True, exist_ok=True)
    robot = profile.robot.name
    inbox: queue.SimpleQueue[tuple[str, bytes, int] | None] = queue.SimpleQueue()
    with Node("recorder", robot, profile.zenoh, listen_slot="recorder") as node, path.open("wb") as stream:
        node.install_signal_handlers()
        recorder = McapRecorder(stream, robot, compression=cfg.compression, chunk_size=cfg.chunk_size)
        recorder.metadata("session", {
            "robot": robot,
            "session": session,
            "profile": encode_profile(profile).decode(),
            "software_version": _version(),
            "start_time": dt.datetime.now(dt.timezone.utc).isoformat(),
            **{f"label.{k}": v for k, v in labels.items()},
        })

        def on_sample(sample: zenoh.Sample) -> None:
            # Cheap on Zenoh's thread: decoding and writing happen below.
            inbox.put((str(sample.key_expr), sample.payload.to_bytes(), node.clock.now_ns()))

        sub = node.session.declare_subscriber(f"{keys.prefix(robot)}/**", on_sample)
        log.info("recording %s/** to %s", keys.prefix(robot), path)
        bad = 0
        try:
            while True:
                try:
                    item = inbox.get(timeout=0.1)
                except queue.Empty:
                    if node.stop.is_set():
                        break
                    continue
                if item is None:
                    break
                full_key, payload, received = item
                try:
                    relative = keys.relative_key(robot, full_key)
                    message = keys.codec(relative).decode(payload)
                except DecodeError as exc:
                    bad += 1
                    node.diag("warning", "decode_error", f"not recorded: {exc}")
                    continue
                recorder.write(full_key, message, received)
        finally:
            sub.undeclare()
            while True:  # what arrived before the subscriber closed is kept
                try:
                    item = inbox.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    try:
                        recorder.write(item[0], keys.codec(keys.relative_key(robot, item[0])).decode(item[1]), item[2])
                    except DecodeError:
                        bad += 1
            recorder.finish()
            total = sum(s.count for s in recorder.channels.values())
            gaps = {k: s.gaps for k, s in recorder.channels.items() if s.gaps}
            log.info("wrote %d messages on %d channels to %s; %d malformed dropped; sequence gaps: %s",
                     total, len(recorder.channels), path, bad, gaps or "none")
    return 0
