"""Recordings: decoded messages -> MCAP files, and MCAP -> messages.

One channel per key (the full key expression is the topic), JSON messages
with a JSON Schema derived from :mod:`nwr.common.messages` (``"type":
"object"`` at the top, so Foxglove plots the fields). Log time is the time
the message was received, publish time the source's stamp, sequence the
message's own ``seq``. Sequence gaps are counted per key and per publisher
and written to the file's metadata when it is closed.

Crash safety: besides the size limit of :class:`mcap.writer.Writer`, a chunk
is closed once its first message is ``chunk_interval_ns`` old
(:meth:`McapRecorder.flush_if_due`, driven by the adapter's clock), and every
closed chunk is flushed to the OS. A ``kill -9`` therefore loses only the
chunk still in memory; ``nwr recover`` (:mod:`.salvage`) rewrites the rest
into a valid file.

A session may be split into parts by size or duration
(:class:`SessionRecorder`): every part is a complete MCAP file with its own
schemas, channels and session metadata (plus its part number).

Nothing here imports Zenoh or reads a clock: times come in as arguments.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import DecodeError, NwrError

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
SCHEMA_NAMES = {"robot/command/*": "nwr.Command"}
# Name of the metadata record with the session's description (written first,
# so that it survives a crash) and of the one with the counts (written last).
SESSION_METADATA = "session"
RECORDING_METADATA = "recording"


class RecordingError(NwrError):
    """A recording cannot be written, read or recovered."""


def publisher_of(message: Any) -> str:
    """Tells apart several publishers of one key, where the message says who sent it.

    Commands name their planner (``owner``): each planner has its own key
    (``robot/command/<name>``), but a misbehaving one may claim another's
    name, and its counter must not merge with the real one's. Skin samples name
    their source (a live gateway and a replay may overlap). Every other key has
    one publisher by construction (``reflex/<name>/status``, ``diag/<service>``,
    the bridge's ``robot/state``, whose ``owner`` is the *command* owner and
    changes during a session, so it must not be used here).
    """
    if isinstance(message, (m.PositionCommand, m.VelocityCommand)):
        return message.owner
    if isinstance(message, m.SkinPressure):
        return message.source
    if isinstance(message, m.Diagnostic):
        return message.service
    return ""


@dataclass
class KeyGaps:
    """Sequence bookkeeping of one key."""

    gaps: int = 0  # messages missing between consecutive sequence numbers
    restarts: int = 0  # a publisher's counter went backwards (it restarted)
    last_seq: dict[str, int] = field(default_factory=dict)  # per publisher


class GapCounter:
    """Counts missing sequence numbers per key and publisher.

    A sequence number that does not increase is taken as a restarted
    publisher (its counter starts again at 0), not as a gap: nothing can be
    said about what it sent before it died.
    """

    def __init__(self) -> None:
        self.keys: dict[str, KeyGaps] = {}

    def observe(self, key: str, publisher: str, seq: int) -> tuple[int, bool]:
        """Record one message: how many are missing just before it, and whether its publisher restarted."""
        entry = self.keys.get(key)
        if entry is None:
            entry = self.keys[key] = KeyGaps()
        last = entry.last_seq.get(publisher)
        entry.last_seq[publisher] = seq
        if last is None:
            return 0, False
        if seq > last + 1:
            entry.gaps += seq - last - 1
            return seq - last - 1, False
        if seq <= last:
            entry.restarts += 1
            return 0, True
        return 0, False

    def gaps(self) -> dict[str, int]:
        return {k: e.gaps for k, e in self.keys.items()}

    def restarts(self) -> dict[str, int]:
        return {k: e.restarts for k, e in self.keys.items()}


@dataclass
class ChannelStats:
    channel_id: int
    count: int = 0
    gaps: int = 0  # found while writing this file
    restarts: int = 0
    first_log_ns: int = 0
    last_log_ns: int = 0


def schema_for(relative: str) -> tuple[str, bytes]:
    """Name and JSON Schema of the messages on a relative key."""
    topic = keys.topic_for(relative)
    name = SCHEMA_NAMES.get(topic.pattern) or f"nwr.{getattr(topic.type, '__name__', topic.pattern)}"
    return name, json.dumps(m.json_schema(topic.type)).encode()


class McapRecorder:
    """One MCAP file: channels registered on first use, gaps counted, chunks closed by size or age.

    ``chunk_interval_ns`` > 0 makes :meth:`flush_if_due` close the open chunk
    once its first message is that old, and flush it to the stream's OS file.
    ``gaps`` may be shared between the parts of a split session, so that a
    part boundary is not mistaken for a publisher restart.
    """

    def __init__(
        self,
        stream: IO[bytes],
        robot: str,
        *,
        compression: str = "zstd",
        chunk_size: int = 256 * 1024,
        chunk_interval_ns: int = 0,
        gaps: GapCounter | None = None,
    ) -> None:
        if compression not in COMPRESSION:
            raise RecordingError(f"compression {compression!r} is not one of {sorted(COMPRESSION)}")
        self.robot = robot
        self.stream = stream
        self.writer = Writer(stream, chunk_size=chunk_size, compression=COMPRESSION[compression])
        self.writer.start(profile="nwr", library=f"nwr {software_version()}")
        self.chunk_interval_ns = chunk_interval_ns
        self.gap_counter = gaps if gaps is not None else GapCounter()
        self._encoder = msgspec.json.Encoder()
        self._schemas: dict[str, int] = {}
        self.channels: dict[str, ChannelStats] = {}
        # Strategies each planner reported in its status: the truth when the
        # launcher overrode the profile's strategy.
        self.planners: dict[str, list[str]] = {}
        # Log time of the first message of the chunk in memory (None: empty).
        self._chunk_opened_ns: int | None = None
        self.finished = False

    def _channel(self, full_key: str, relative: str) -> ChannelStats:
        stats = self.channels.get(full_key)
        if stats is None:
            name, schema = schema_for(relative)
            schema_id = self._schemas.get(name)
            if schema_id is None:
                schema_id = self._schemas[name] = self.writer.register_schema(name, "jsonschema", schema)
            channel_id = self.writer.register_channel(full_key, "json", schema_id)
            stats = self.channels[full_key] = ChannelStats(channel_id)
        return stats

    def write(self, full_key: str, message: Any, log_time_ns: int) -> int:
        """Write one message; returns how many messages of its publisher are missing before it."""
        if self.finished:
            raise RecordingError(f"the recording is finished: cannot write a message on {full_key} after finish()")
        stats = self.channels.get(full_key)
        if stats is None:  # the key's first message: check it is under the prefix, register its channel
            stats = self._channel(full_key, keys.relative_key(self.robot, full_key))
        seq = message.seq
        missing, restarted = self.gap_counter.observe(full_key, publisher_of(message), seq)
        stats.gaps += missing
        stats.restarts += restarted
        if stats.count == 0:
            stats.first_log_ns = log_time_ns
        stats.count += 1
        stats.last_log_ns = max(stats.last_log_ns, log_time_ns)
        self.writer.add_message(stats.channel_id, log_time_ns, self._encoder.encode(message), message.stamp_ns, seq)
        if self._chunk_opened_ns is None:
            self._chunk_opened_ns = log_time_ns
        if isinstance(message, m.PlannerStatus):
            seen = self.planners.setdefault(message.name, [])
            if message.strategy not in seen:
                seen.append(message.strategy)
        return missing

    def flush_if_due(self, now_ns: int) -> bool:
        """Close the open chunk and flush it to the OS if it is ``chunk_interval_ns`` old."""
        opened = self._chunk_opened_ns
        if opened is None or self.finished or self.chunk_interval_ns <= 0 or now_ns - opened < self.chunk_interval_ns:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """Close the open chunk (however small) and hand everything written to the OS.

        ``Writer.flush`` is mcap's public way to end a chunk early; it flushes
        the stream too (no fsync: a killed process loses nothing the OS has).
        """
        self.writer.flush()
        self._chunk_opened_ns = None

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self.writer.add_metadata(name, data)

    @property
    def message_count(self) -> int:
        return sum(s.count for s in self.channels.values())

    def size(self) -> int:
        """Bytes handed to the stream so far (the chunk in memory not included)."""
        return self.stream.tell()

    def finish(self) -> None:
        """Write the counts and gaps, the summary and the footer (the stream stays open)."""
        if self.finished:
            return
        self.finished = True
        self._chunk_opened_ns = None
        self.writer.add_metadata(
            RECORDING_METADATA,
            {
                "messages": json.dumps({k: s.count for k, s in self.channels.items()}),
                "gaps": json.dumps({k: s.gaps for k, s in self.channels.items()}),
                "restarts": json.dumps({k: s.restarts for k, s in self.channels.items()}),
                "planners": json.dumps(self.planners),
            },
        )
        self.writer.finish()
        self.stream.flush()


@dataclass(frozen=True)
class SplitPolicy:
    """When to start a new part of a session (0 = never)."""

    max_bytes: int = 0
    max_duration_ns: int = 0

    @property
    def enabled(self) -> bool:
        return self.max_bytes > 0 or self.max_duration_ns > 0


def part_path(base: Path, part: int, split: bool) -> Path:
    """``<session>.mcap`` for an unsplit session, ``<session>-NNN.mcap`` for its parts."""
    if not split:
        return base
    return base.with_name(f"{base.stem}-{part:03d}{base.suffix or '.mcap'}")


@dataclass
class PartReport:
    part: int
    messages: int
    first_log_ns: int
    last_log_ns: int


@dataclass
class SessionReport:
    """What a session wrote, for the exit log."""

    parts: list[PartReport]
    messages: dict[str, int]
    gaps: dict[str, int]
    restarts: dict[str, int]

    def format(self) -> str:
        total = sum(self.messages.values())
        gaps = {k: v for k, v in self.gaps.items() if v}
        restarts = {k: v for k, v in self.restarts.items() if v}
        text = (f"{total} messages on {len(self.messages)} channels in {len(self.parts)} file(s); "
                f"sequence gaps: {', '.join(f'{k} {v}' for k, v in gaps.items()) if gaps else 'none'}")
        if restarts:
            text += f"; publisher restarts: {', '.join(f'{k} {v}' for k, v in restarts.items())}"
        return text


class SessionRecorder:
    """A recording session: one MCAP file, or parts split by size or duration.

    ``open_part(n)`` returns the stream of part ``n`` and ``close_part(n,
    stream)`` is called once that part is finished, so the adapter owns the
    files and the tests can use memory. Every part gets the session metadata
    with ``part`` set; schemas and channels are registered again in each.

    A part is closed before the first message that would make it span
    ``max_duration_ns`` of log time, or once it holds ``max_bytes`` on the
    stream (checked per message; the chunk in memory is not counted, so a part
    may exceed the size by up to one chunk and its summary).
    """

    def __init__(
        self,
        open_part: Callable[[int], IO[bytes]],
        close_part: Callable[[int, IO[bytes]], None],
        robot: str,
        session_metadata: dict[str, str],
        *,
        compression: str = "zstd",
        chunk_size: int = 256 * 1024,
        chunk_interval_ns: int = 0,
        split: SplitPolicy = SplitPolicy(),
    ) -> None:
        self._open_part = open_part
        self._close_part = close_part
        self.robot = robot
        self.session_metadata = dict(session_metadata)
        self.compression = compression
        self.chunk_size = chunk_size
        self.chunk_interval_ns = chunk_interval_ns
        self.split = split
        self.gaps = GapCounter()
        self.parts: list[PartReport] = []
        self.messages: dict[str, int] = {}
        self.current: McapRecorder | None = None
        self._part_started_ns: int | None = None
        self._start_part()

    def _start_part(self) -> None:
        part = len(self.parts)
        stream = self._open_part(part)
        try:
            recorder = McapRecorder(stream, self.robot, compression=self.compression, chunk_size=self.chunk_size,
                                    chunk_interval_ns=self.chunk_interval_ns, gaps=self.gaps)
            recorder.metadata(SESSION_METADATA, {**self.session_metadata, "part": str(part)})
            # The header and the session metadata reach the OS at once: even a
            # part killed before its first chunk names its session.
            recorder.flush()
        except Exception:
            self._close_part(part, stream)
            raise
        self.current = recorder
        self.parts.append(PartReport(part, 0, 0, 0))
        self._part_started_ns = None

    def _finish_part(self) -> None:
        recorder = self.current
        if recorder is None:
            return
        self.current = None
        report = self.parts[-1]
        report.messages = recorder.message_count
        firsts = [s.first_log_ns for s in recorder.channels.values() if s.count]
        report.first_log_ns = min(firsts, default=0)
        report.last_log_ns = max((s.last_log_ns for s in recorder.channels.values()), default=0)
        try:
            recorder.finish()
        finally:
            self._close_part(report.part, recorder.stream)

    def _due(self, recorder: McapRecorder, log_time_ns: int) -> bool:
        if recorder.message_count == 0:
            return False  # never leave an empty part behind
        if self.split.max_duration_ns and self._part_started_ns is not None \
                and log_time_ns - self._part_started_ns >= self.split.max_duration_ns:
            return True
        return bool(self.split.max_bytes) and recorder.size() >= self.split.max_bytes

    def write(self, full_key: str, message: Any, log_time_ns: int) -> int:
        """Write one message (into a new part if the current one is full)."""
        recorder = self.current
        if recorder is None:
            raise RecordingError("the session is finished: no message can be written after finish()")
        if self.split.enabled and self._due(recorder, log_time_ns):
            self._finish_part()
            self._start_part()
            recorder = self.current
            assert recorder is not None
        if self._part_started_ns is None:
            self._part_started_ns = log_time_ns
        self.messages[full_key] = self.messages.get(full_key, 0) + 1
        return recorder.write(full_key, message, log_time_ns)

    def flush_if_due(self, now_ns: int) -> bool:
        return self.current.flush_if_due(now_ns) if self.current is not None else False

    def finish(self) -> SessionReport:
        self._finish_part()
        return SessionReport(self.parts, dict(self.messages), self.gaps.gaps(), self.gaps.restarts())


def session_metadata(
    *,
    robot: str,
    session: str,
    profile_json: str,
    strategy: str,
    planner: str,
    start_time_iso: str,
    start_monotonic_ns: int,
    labels: dict[str, str],
) -> dict[str, str]:
    """The ``session`` metadata record (every value a string, as MCAP requires)."""
    return {
        "robot": robot,
        "session": session,
        "strategy": strategy,
        "planner": planner,
        "profile": profile_json,
        "software_version": software_version(),
        "start_time": start_time_iso,
        # Log times are on the machine's monotonic clock (as every stamp is):
        # this pair maps them to wall-clock time.
        "start_monotonic_ns": str(start_monotonic_ns),
        **{f"label.{k}": v for k, v in labels.items()},
    }


def parse_labels(items: list[str]) -> dict[str, str]:
    """``["participant=P07", "condition=CR"]`` -> a dict; RecordingError names a bad one."""
    labels: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise RecordingError(f"label {item!r} is not KEY=VALUE: write it as e.g. --label participant=P07")
        labels[key] = value
    return labels


def software_version() -> str:
    try:
        from importlib.metadata import version

        return version("nwr")
    except Exception:  # not installed (running from a source tree)
        return "unknown"


@dataclass(frozen=True)
class Recorded:
    key: str  # relative to the robot prefix
    log_time_ns: int
    message: Any


def read_recording(path: str | Path, robot: str | None = None) -> tuple[list[Recorded], dict[str, dict[str, str]]]:
    """Every message of a recording, decoded strictly, and the file's metadata."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"recording {path} does not exist")
    decoders: dict[str, msgspec.json.Decoder] = {}
    out: list[Recorded] = []
    with path.open("rb") as f:
        reader = make_reader(f)
        metadata = {rec.name: dict(rec.metadata) for rec in reader.iter_metadata()}
        if robot is None:
            robot = metadata.get(SESSION_METADATA, {}).get("robot", keys.DEFAULT_ROBOT)
        f.seek(0)
        reader = make_reader(f)
        head = keys.prefix(robot) + "/"
        for _schema, channel, msg in reader.iter_messages(log_time_order=True):
            if not channel.topic.startswith(head):
                continue  # not the pipeline's (the view's channels of an exported file, say)
            relative = keys.relative_key(robot, channel.topic)
            dec = decoders.get(relative)
            if dec is None:
                dec = decoders[relative] = msgspec.json.Decoder(keys.topic_for(relative).type)
            try:
                out.append(Recorded(relative, msg.log_time, dec.decode(msg.data)))
            except msgspec.ValidationError as exc:
                raise DecodeError(f"{path}: message on {channel.topic} at {msg.log_time}: {exc}") from exc
    return out, metadata


def iter_key(records: list[Recorded], pattern: str) -> Iterator[Recorded]:
    return (r for r in records if r.key == pattern)
