"""Recorder process: every message under nwr/<robot>/ -> MCAP file(s).

The Zenoh callback only queues (key, payload, receive time), on Zenoh's own
network thread (no hand-off to a Python thread per message); decoding,
writing, the time-based chunk flush and file splitting happen in this
process's own loop (:mod:`.core`), which wakes every ``BATCH_S`` and writes
everything that arrived meanwhile: one wake-up per batch instead of one per
message (about 200 messages a second at the default rates while nobody
touches the arm, about 650 during a reflex, several thousand at 1 kHz skin).

The recorder never exits on its disk: a directory that cannot be created or
written, a disk that fills, a file system that turns read-only are reported on
``diag/recorder`` and retried every ``RETRY_S`` while the messages are counted
(:class:`~nwr.services.recorder.disk.SessionRecorder`); the rest of the pipeline and
the arm's task do not depend on it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import logging
import sys
from collections import deque
from pathlib import Path
from typing import IO

import zenoh

from nwr.common import keys
from nwr.common.config import Profile
from nwr.common.errors import DecodeError
from nwr.common.launch import encode_profile
from nwr.common.node import Node
from nwr.common.recordings import RecordingError, fits_mcap, parse_labels, session_metadata
from nwr.services.profile import loosened_safety
from nwr.services.recorder.disk import PartFiles, SessionRecorder, SplitPolicy

log = logging.getLogger(__name__)

MB = 1024 * 1024
# How often the loop writes what arrived, checks the chunk's age and the stop
# event: the time-based flush is this much late at worst, and a message waits
# in memory this long at most (its log time is taken when it arrives). Small
# beside recorder.chunk_interval_s (0.5 s, what a crash may lose), and each
# wake-up costs a quiet pipeline CPU.
BATCH_S = 0.1
# The network thread that queues a message waits for the GIL while the loop
# writes a batch: switch at least this often (s; Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.001
# While the recording's disk cannot be written: how often a new file is tried
# (each try that fails is one not_writing diagnostic, so `nwr status`, which
# listens 2 s, sees it), s.
RETRY_S = 1.0
# The disk diagnostics come once per failure or per retry: let every one out
# (Node.diag's default holds back a code repeated within 1 s).
DISK_DIAG_EVERY_S = 0.5
# The most keys a session records: the registry's patterns (robot/command/*, reflex/*/status, diag/*, ...) hold
# any name, and a session's own processes use a few dozen of them. Messages on keys beyond it are counted, not
# recorded (too_many_keys on diag/recorder): a peer putting on ever new names cannot make the recorder open
# channels, and hold codecs, without end.
MAX_KEYS = 256


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--output", "-o",
                        help="MCAP file to write (default: <recorder.directory>/<session>.mcap); split sessions "
                             "write <stem>-000.mcap, <stem>-001.mcap, ... beside it, and so does a session that "
                             "goes on in a new file after its disk could not be written (<stem>-001.mcap, ...)")
    parser.add_argument("--session", help="session name (default: the start time)")
    parser.add_argument("--label", action="append", default=[], metavar="KEY=VALUE",
                        help="free label stored in the session metadata (repeatable), e.g. participant=P07")
    parser.add_argument("--strategy", metavar="NAME",
                        help="reflex strategy to note in the session metadata when the planner runs another one "
                             "than the profile's (default: planner.strategy)")
    parser.add_argument("--split-size", type=float, metavar="MB",
                        help="start a new file when the current one reaches this size, MB of 2^20 bytes "
                             "(overrides recorder.split_size_mb; 0 = never)")
    parser.add_argument("--split-duration", type=float, metavar="S",
                        help="start a new file when the current one spans this many seconds "
                             "(overrides recorder.split_duration_s; 0 = never)")


def session_name() -> str:
    return dt.datetime.now().strftime("session-%Y%m%d-%H%M%S")


def split_policy(profile: Profile, args: argparse.Namespace) -> SplitPolicy:
    cfg = profile.recorder
    size_mb = cfg.split_size_mb if getattr(args, "split_size", None) is None else args.split_size
    duration_s = cfg.split_duration_s if getattr(args, "split_duration", None) is None else args.split_duration
    if size_mb < 0 or duration_s < 0:
        raise RecordingError(f"--split-size ({size_mb}) and --split-duration ({duration_s}) must be >= 0 "
                             "(0 = never split)")
    return SplitPolicy(max_bytes=round(size_mb * MB), max_duration_ns=round(duration_s * 1e9))


def run(profile: Profile, args: argparse.Namespace) -> int:
    cfg = profile.recorder
    session = args.session or session_name()
    labels = parse_labels(args.label)
    split = split_policy(profile, args)
    base = Path(args.output) if args.output else Path(cfg.directory) / f"{session}.mcap"
    # The directory is created with the first file: one that cannot be is reported and retried, like a full disk.
    files = PartFiles(base, split.enabled)
    robot = profile.robot.name
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    # Appended on Zenoh's thread, drained by the loop (deque appends and pops are atomic).
    inbox: deque[tuple[str, bytes, int]] = deque()

    def open_part(part: int) -> IO[bytes]:
        stream = files.open(part)
        log.info("writing %s", files.path(part))
        return stream

    # The token is declared once the subscriber is: a launcher that waits for
    # the recorder to be alive knows nothing published after it is lost.
    with Node("recorder", robot, profile.zenoh, listen_slot="recorder", token=False) as node:
        node.install_signal_handlers()
        metadata = session_metadata(
            robot=robot, session=session, profile_json=encode_profile(profile).decode(),
            strategy=getattr(args, "strategy", None) or profile.planner.strategy, planner=profile.planner.name,
            start_time_iso=dt.datetime.now(dt.UTC).isoformat(), start_monotonic_ns=node.clock.now_ns(),
            labels=labels, loosened_safety=loosened_safety(profile), instance=node.instance,
        )
        recorder = SessionRecorder(
            open_part, files.close, robot, metadata, compression=cfg.compression, chunk_size=cfg.chunk_size,
            chunk_interval_ns=round(cfg.chunk_interval_s * 1e9), split=split, disk=files,
            retry_ns=round(RETRY_S * 1e9),
            diag=lambda level, code, text: node.diag(level, code, text, every_s=DISK_DIAG_EVERY_S),
        )

        def on_sample(sample: zenoh.Sample) -> None:
            # Cheap, and never blocks, so it may run on Zenoh's network thread
            # (indirect=False): decoding and writing happen below. A message of
            # another pipeline instance is counted and reported, not recorded.
            if node.instance != keys.NO_INSTANCE and not node.accepts(sample):
                return
            inbox.append((str(sample.key_expr), sample.payload.to_bytes(), node.clock.now_ns()))

        sub = node.session.declare_subscriber(f"{keys.prefix(robot)}/**",
                                              zenoh.handlers.Callback(on_sample, indirect=False))
        node.declare_token()
        log.info("recording %s/** to %s%s", keys.prefix(robot), base,
                 f" (split: {split.max_bytes / MB:g} MB, {split.max_duration_ns / 1e9:g} s)" if split.enabled else "")
        bad = 0
        beyond = 0  # messages on keys beyond MAX_KEYS
        # The codec of each full key, looked up once: matching a key against
        # the registry's patterns for every message cost more than decoding it.
        codecs: dict[str, keys.Codec] = {}

        def record(item: tuple[str, bytes, int]) -> None:
            nonlocal bad, beyond
            full_key, payload, received = item
            try:
                codec = codecs.get(full_key)
                if codec is None:
                    if len(codecs) >= MAX_KEYS:
                        beyond += 1
                        node.diag("warning", "too_many_keys",
                                  f"not recorded: a message on {full_key}, a key beyond the {MAX_KEYS} this session "
                                  f"records ({beyond} such messages so far): a peer puts on ever new key names",
                                  every_s=10.0)
                        return
                    codec = codecs[full_key] = keys.codec(keys.relative_key(robot, full_key))
                message = codec.decode(payload)
            except (DecodeError, ValueError) as exc:
                # ValueError too: Codec.decode lets UnicodeDecodeError (a string
                # that is not UTF-8) escape, and no sample may stop the recorder.
                bad += 1
                node.diag("warning", "decode_error", f"not recorded: {exc}")
                return
            if not fits_mcap(message):
                node.diag("warning", "unfit_for_mcap",
                          f"{full_key}: seq {message.seq} or stamp_ns {message.stamp_ns} beyond what an MCAP record "
                          "holds (uint32, uint64): recorded with them folded into its range, the data keeps them")
            try:
                recorder.write(full_key, message, received)  # counted, not written, while the disk cannot be
            except Exception as exc:  # noqa: BLE001  no message may stop the recorder
                bad += 1
                node.diag("error", "record_error", f"not recorded: a {type(message).__name__} on {full_key}: {exc!r}")

        def drain() -> None:
            while inbox:
                record(inbox.popleft())

        try:
            while not node.stop.wait(BATCH_S):
                drain()
                # Also when nothing arrives: a quiet pipeline must not keep its last chunk in memory.
                now = node.clock.now_ns()
                recorder.flush_if_due(now)
                recorder.retry_if_due(now)
        finally:
            sub.undeclare()
            try:
                drain()  # what arrived before the subscriber closed is kept
            finally:
                report = recorder.finish(node.clock.now_ns())
            log.info("wrote %s; %d malformed samples dropped", report.format(), bad)
            if node.foreign or beyond:
                log.warning("not recorded: %d messages of another pipeline instance (this one: %s), %d on keys beyond "
                            "the first %d", node.foreign, node.instance, beyond, MAX_KEYS)
            if report.outages:
                log.warning("the session is incomplete: %d messages were not recorded while the disk could not be "
                            "written (%d time(s))%s", report.dropped, len(report.outages),
                            f"; {report.lost} more were lost with a file that could not be finished"
                            if report.lost else "")
            if any(report.gaps.values()):
                log.warning("sequence gaps: messages were lost before they reached the recorder: %s",
                            {k: v for k, v in report.gaps.items() if v})
    return 0
