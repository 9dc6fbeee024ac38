"""Recordings: decoded messages -> MCAP files, and MCAP -> messages.

One channel per key (the full key expression is the topic), JSON messages
with a JSON Schema derived from :mod:`nwr.common.messages` in the form
Foxglove and Lichtblick load (:func:`nwr.common.messages.json_schema`: an
object of typed properties, so their panels show and plot the fields). Log
time is the time the message was received, publish time the source's
stamp, sequence the message's own ``seq``. Sequence gaps are counted per key
and per publisher and written to the file's metadata when it is closed.

Crash safety: besides the size limit of :class:`mcap.writer.Writer`, a chunk
is closed once its first message is ``chunk_interval_ns`` old
(:meth:`McapRecorder.flush_if_due`, driven by the adapter's clock), and every
closed chunk is flushed to the OS. A ``kill -9`` therefore loses only the
chunk still in memory; ``nwr recover`` (:mod:`.salvage`) rewrites the rest
into a valid file.

A session's parts and the disk's failures are the recorder's own
(:mod:`nwr.services.recorder.disk`).

Reading: every command that takes a recording opens it through
:func:`open_recording_file` (the checks that leave nothing to read) and,
unless it reads damaged files on purpose (``nwr info``, ``nwr recover``),
:class:`RecordingReader` (a finished, undamaged file), so that each kind of
bad file gets the same one-line :class:`RecordingError` everywhere.

Nothing here imports Zenoh or reads a clock: times come in as arguments.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TypeVar

import msgspec
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType, Writer

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import DecodeError, NwrError

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
SCHEMA_NAMES = {"robot/command/*": "nwr.Command"}
# Name of the metadata record with the session's description (written first,
# so that it survives a crash) and of the one with the counts (written last).
SESSION_METADATA = "session"
MCAP_SEQUENCE = 2**32  # a message record's sequence is a uint32
MCAP_TIME = 2**64  # its log and publish times are uint64 nanoseconds
RECORDING_METADATA = "recording"
_T = TypeVar("_T")


class RecordingError(NwrError):
    """A recording cannot be written, read or recovered.

    ``problem`` classifies a file that cannot be read: ``missing``,
    ``directory``, ``unreadable``, ``empty``, ``not_mcap``, ``header`` (ends
    inside its MCAP header), ``unfinished`` (no footer: ``nwr recover`` it),
    ``damaged`` (a CRC or decompression error: ``nwr recover`` it); empty
    for every other error.
    """

    def __init__(self, message: str, *, problem: str = "") -> None:
        super().__init__(message)
        self.problem = problem


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
        self.unfit = 0  # messages whose seq or stamp MCAP's record could not hold as they were (folded into it)
        self._encoder = msgspec.json.Encoder()
        self._schemas: dict[str, int] = {}
        self.schema_bytes = 0  # of the schema records registered: the summary repeats them
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
                self.schema_bytes += len(schema) + len(name) + 40
            channel_id = self.writer.register_channel(full_key, "json", schema_id)
            stats = self.channels[full_key] = ChannelStats(channel_id)
        return stats

    def write(self, full_key: str, message: Any, log_time_ns: int, *, count_gaps: bool = True) -> int:
        """Write one message; returns how many messages of its publisher are missing before it.

        ``count_gaps=False`` for a message the gap counter has seen already (written again into a
        new part after the one it was in could not be written): it is no restart of its publisher.
        """
        if self.finished:
            raise RecordingError(f"the recording is finished: cannot write a message on {full_key} after finish()")
        stats = self.channels.get(full_key)
        if stats is None:  # the key's first message: check it is under the prefix, register its channel
            stats = self._channel(full_key, keys.relative_key(self.robot, full_key))
        seq = message.seq
        missing, restarted = (self.gap_counter.observe(full_key, publisher_of(message), seq) if count_gaps
                              else (0, False))
        stats.gaps += missing
        stats.restarts += restarted
        if stats.count == 0:
            stats.first_log_ns = log_time_ns
        stats.count += 1
        stats.last_log_ns = max(stats.last_log_ns, log_time_ns)
        # MCAP's sequence is a uint32 and its publish time a uint64: a value beyond them (a peer's bug) is
        # folded into them here; the message itself, in the record's data, keeps it as it travelled.
        stamp = message.stamp_ns
        if not fits_mcap(message):
            self.unfit += 1
        self.writer.add_message(stats.channel_id, log_time_ns, self._encoder.encode(message),
                                min(max(stamp, 0), MCAP_TIME - 1), seq % MCAP_SEQUENCE)
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

    def finish_bytes(self, chunks: int) -> int:
        """An upper estimate of what :meth:`finish` writes after the last chunk, ``chunks`` chunks into the file.

        The recording metadata (three counts per topic), then the summary: the
        schemas and channels again, the statistics (a count per channel), a
        chunk index per chunk (counted here as if every chunk held every
        channel), the metadata indexes and summary offsets; the footer.
        """
        n = len(self.channels)
        topics = sum(len(k) for k in self.channels)
        return (3 * (topics + 16 * n) + 512
                + self.schema_bytes + topics + 40 * n + 10 * n
                + chunks * (80 + 10 * n)
                + 1024)

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


def fits_mcap(message: Any) -> bool:
    """Do the message's seq and stamp fit MCAP's record (else they are folded into it, the data keeps them)?"""
    return 0 <= message.seq < MCAP_SEQUENCE and 0 <= message.stamp_ns < MCAP_TIME


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
    loosened_safety: list[dict[str, Any]] | None = None,
    timing: str = "live",
    instance: str | None = None,
) -> dict[str, str]:
    """The ``session`` metadata record (every value a string, as MCAP requires).

    ``loosened_safety``: the profile's acknowledged loosened safety values
    (:func:`nwr.common.config.loosened_safety`), kept as a JSON list of
    {field, value, default, reason}, ``[]`` for none; None leaves it out.
    ``timing``: "live" (services as processes, on the machine's clock) or
    "lockstep" (one process on simulated time, where stamps are control
    cycles and no latency is measured).
    ``instance``: the pipeline instance the recorder belongs to (live only; ``-`` for a recorder started alone):
    what it recorded came from that pipeline, or from processes started alone.
    """
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
        "timing": timing,
        **({} if instance is None else {"instance": instance}),
        **({} if loosened_safety is None else {"loosened_safety": json.dumps(loosened_safety)}),
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


# -- reading ---------------------------------------------------------------------
# Every command that takes a recording opens it here, so that each kind of
# bad file (a missing path, a directory, an unreadable or empty file, another
# format, a file cut off by a crash or a full disk, a damaged one) gets the
# same one-line RecordingError naming the file, the problem and what to do.

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")  # opcode, length
# The footer record (opcode, length, summary start, summary offset start, summary CRC) and the closing magic.
_FOOTER = struct.Struct("<BQQQI")
_FOOTER_OPCODE, _FOOTER_LENGTH, _HEADER_OPCODE = 0x02, 20, 0x01
_TAIL_SIZE = _FOOTER.size + len(MCAP_MAGIC)


@contextmanager
def new_file(output: Path, what: str) -> Iterator[IO[bytes]]:
    """Write ``output`` (``what`` names it in errors) through ``<output>.part``: it appears whole or not at all.

    A file that cannot be created or written is a one-line RecordingError, and leaves nothing behind.
    """
    tmp = output.with_name(output.name + ".part")
    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        stream = tmp.open("wb")
    except OSError as exc:
        raise RecordingError(f"cannot write {what} {output}: {exc.strerror or exc}; choose another file with -o") \
            from None
    try:
        with stream:
            yield stream
        tmp.replace(output)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"writing {what} {output} failed: {exc.strerror or exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def recovered_path(path: Path) -> Path:
    """Where ``nwr recover FILE`` writes by default: ``<stem>-recovered.mcap`` beside the file."""
    return path.with_name(f"{path.stem}-recovered{path.suffix or '.mcap'}")


def recover_hint(path: Path) -> str:
    return f"`nwr recover {path}` saves its readable messages into {recovered_path(path).name} and says what was lost"


def _looks_like(head: bytes) -> str:
    """What a file that is not MCAP seems to be, from its first bytes."""
    signatures = [
        (b"\x89PNG", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"), (b"%PDF", "a PDF document"),
        (b"PK\x03\x04", "a ZIP archive"), (b"\x1f\x8b", "gzip-compressed data (decompress it first)"),
        (b"\x28\xb5\x2f\xfd", "zstd-compressed data (decompress it first)"),
        (b"#ROSBAG", "a ROS 1 bag"), (b"SQLite format 3\x00", "an SQLite database (a ROS 2 .db3 bag?)"),
    ]
    for signature, kind in signatures:
        if head.startswith(signature):
            return kind
    text = head.decode("utf-8", errors="ignore")
    printable = sum(c.isprintable() or c in "\r\n\t" for c in text)
    if text and printable >= 0.9 * len(head):
        stripped = text.lstrip("\ufeff \r\n\t")
        if stripped[:1] in ("{", "["):
            return "a JSON file"
        return "a text file"
    return "binary data of another format"


def open_recording_file(path: str | Path) -> IO[bytes]:
    """Open a file given as a recording; RecordingError for the problems that leave nothing to read.

    Checked here, in this order: the path exists, is a file, can be read, is
    not empty, starts with the MCAP magic (else: what it looks like) and holds
    a whole MCAP header. Damage after the header is for the caller:
    :class:`RecordingReader` refuses it, ``nwr info`` and ``nwr recover``
    read up to it.
    """
    path = Path(path)
    try:
        if path.is_dir():
            inside = sorted(p.name for p in path.glob("*.mcap"))
            which = ("it holds no .mcap file" if not inside else f"give the file in it, {path / inside[0]}"
                     if len(inside) == 1 else f"give one of its {len(inside)} .mcap files, e.g. {path / inside[0]}")
            raise RecordingError(f"{path} is a directory, not a recording: {which}", problem="directory")
        stream = path.open("rb")
    except FileNotFoundError:
        raise RecordingError(f"recording {path} does not exist", problem="missing") from None
    except PermissionError:
        raise RecordingError(f"{path} cannot be read: permission denied (its owner can make it readable: "
                             f"`chmod +r {path}`)", problem="unreadable") from None
    except OSError as exc:
        raise RecordingError(f"{path} cannot be read: {exc.strerror or exc}", problem="unreadable") from None
    try:
        head = stream.read(4096)
        if not head:
            raise RecordingError(f"{path} is empty (0 bytes): the recorder wrote nothing to it (it was stopped "
                                 "before its first write, or the disk was full); there is nothing to read or recover",
                                 problem="empty")
        if not head.startswith(MCAP_MAGIC):
            if MCAP_MAGIC.startswith(head):
                raise RecordingError(f"{path} ({len(head)} bytes) ends inside the MCAP magic bytes: the recorder "
                                     "stopped before writing anything; there is nothing to read or recover",
                                     problem="header")
            raise RecordingError(f"{path} is not an MCAP recording: it looks like {_looks_like(head)}; give a "
                                 ".mcap file written by nwr (recordings/<session>.mcap)", problem="not_mcap")
        record = head[len(MCAP_MAGIC):len(MCAP_MAGIC) + _RECORD_HEADER.size]
        size = path.stat().st_size
        opcode, length = _RECORD_HEADER.unpack(record) if len(record) == _RECORD_HEADER.size else (None, 0)
        if opcode is not None and opcode != _HEADER_OPCODE:
            raise RecordingError(f"{path} is damaged: no MCAP header after its magic bytes (opcode 0x{opcode:02x}); "
                                 "there is nothing to read or recover", problem="header")
        if opcode is None or len(MCAP_MAGIC) + _RECORD_HEADER.size + length > size:
            raise RecordingError(f"{path} ({size} bytes) ends inside its MCAP header: the recorder stopped before "
                                 "writing any message; there is nothing to read or recover", problem="header")
        stream.seek(0)
    except OSError as exc:
        stream.close()
        raise RecordingError(f"{path} cannot be read: {exc.strerror or exc}", problem="unreadable") from None
    except BaseException:
        stream.close()
        raise
    return stream


class RecordingReader:
    """A finished recording opened for reading, every problem a one-line RecordingError.

    Opening checks what :func:`open_recording_file` checks, then the end of the
    file: a recording the recorder did not finish (killed, crashed, out of
    disk space) has no footer, and its summary is what a seeking reader needs.
    Such a file, and one whose summary or a chunk fails its CRC or does not
    decompress, is refused with a pointer to ``nwr recover``, which saves the
    readable part into a valid file. The reader does not read a damaged file
    up to the damage: a table or a replay of part of a session must not pass
    for one of all of it.

    mcap's own errors, and anything else that breaks while reading past the
    checks, are turned into RecordingError here and nowhere else.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.stream = open_recording_file(self.path)
        try:
            self._check_end()
            self.reader = make_reader(self.stream, validate_crcs=True)
            self._guard("its summary (the index at the end of the file) cannot be read", self.reader.get_summary)
        except BaseException:
            self.stream.close()
            raise

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.stream.close()

    def _damaged(self, what: str) -> RecordingError:
        return RecordingError(f"{self.path} is damaged: {what}; {recover_hint(self.path)}", problem="damaged")

    def _check_end(self) -> None:
        stream = self.stream
        size = stream.seek(0, 2)
        tail = b""
        if size >= len(MCAP_MAGIC) + _TAIL_SIZE:
            stream.seek(size - _TAIL_SIZE)
            tail = stream.read(_TAIL_SIZE)
        if not tail.endswith(MCAP_MAGIC):
            raise RecordingError(
                f"{self.path} is not finished: no summary or footer (the recorder was killed, crashed or ran "
                f"out of disk space before closing it); {recover_hint(self.path)}", problem="unfinished")
        opcode, length, summary_start, _offsets, crc = _FOOTER.unpack_from(tail)
        if opcode != _FOOTER_OPCODE or length != _FOOTER_LENGTH or summary_start > size - _TAIL_SIZE:
            raise self._damaged("its footer (the last record) is unreadable")
        if crc:
            start = summary_start or size - _TAIL_SIZE
            stream.seek(start)
            covered = stream.read(size - 4 - len(MCAP_MAGIC) - start)  # up to the CRC field itself
            if zlib.crc32(covered) != crc:
                raise self._damaged("its summary (the index at the end of the file) fails its CRC check")
        stream.seek(0)

    def _guard(self, what: str, call: Callable[[], _T]) -> _T:
        try:
            return call()
        except NwrError:
            raise
        except OSError as exc:
            raise RecordingError(f"{self.path} cannot be read: {exc.strerror or exc}", problem="unreadable") from None
        except Exception as exc:  # noqa: BLE001 - whatever breaks mcap's reader past the checks is damage
            raise self._damaged(f"{what} ({type(exc).__name__}: {exc})") from exc

    def metadata_records(self) -> list[tuple[str, dict[str, str]]]:
        """The file's metadata records, name and data, in file order."""
        return self._guard("a metadata record cannot be read",
                           lambda: [(rec.name, dict(rec.metadata)) for rec in self.reader.iter_metadata()])

    def metadata(self) -> dict[str, dict[str, str]]:
        """The file's metadata records by name (the last of a name wins)."""
        return dict(self.metadata_records())

    def messages(self) -> Iterator[tuple[Schema | None, Channel, Message]]:
        """Every message in log-time order, with its schema and channel, as mcap reads them."""
        iterator = self._guard("its messages cannot be read",
                               lambda: iter(self.reader.iter_messages(log_time_order=True)))
        while True:
            item = self._guard("a chunk of messages cannot be read", lambda: next(iterator, None))
            if item is None:
                return
            yield item


def recording_robot(metadata: dict[str, dict[str, str]]) -> str:
    """The robot a recording's metadata names (its keys are under that robot's prefix)."""
    return metadata.get(SESSION_METADATA, {}).get("robot", keys.DEFAULT_ROBOT)


def read_recording(path: str | Path, robot: str | None = None, *, only: Callable[[str], bool] | None = None
                   ) -> tuple[list[Recorded], dict[str, dict[str, str]]]:
    """Every message of a recording, decoded strictly, and the file's metadata; ``only``: the messages whose
    key (relative to the robot's prefix) it accepts, the others not decoded (a summary needs no commands, 70 %
    of a session's messages).

    RecordingError (one line: the file, the problem, what to do) for a file
    that is no finished recording (:class:`RecordingReader`); DecodeError for a
    message that does not decode into its key's type.
    """
    path = Path(path)
    decoders: dict[str, msgspec.json.Decoder] = {}
    out: list[Recorded] = []
    with RecordingReader(path) as reader:
        metadata = reader.metadata()
        if robot is None:
            robot = recording_robot(metadata)
        head = keys.prefix(robot) + "/"
        for _schema, channel, msg in reader.messages():
            if not channel.topic.startswith(head):
                continue  # not the pipeline's (the view's channels of an exported file, say)
            relative = keys.relative_key(robot, channel.topic)
            if only is not None and not only(relative):
                continue
            dec = decoders.get(relative)
            if dec is None:
                try:
                    dec = decoders[relative] = msgspec.json.Decoder(keys.topic_for(relative).type)
                except DecodeError as exc:
                    raise DecodeError(f"{path}: channel {channel.topic}: {exc}") from None
            try:
                out.append(Recorded(relative, msg.log_time, dec.decode(msg.data)))
            except (msgspec.ValidationError, msgspec.DecodeError) as exc:
                raise DecodeError(f"{path}: the message on {channel.topic} at log time {msg.log_time} does not "
                                  f"decode ({exc}): the file is damaged or was written by another version of nwr"
                                  ) from exc
    return out, metadata


def iter_key(records: list[Recorded], pattern: str) -> Iterator[Recorded]:
    return (r for r in records if r.key == pattern)
