"""Reading MCAP files that may be damaged: ``nwr info`` and ``nwr recover``.

A recorder killed mid-session leaves a file without summary and footer,
possibly ending inside a record. mcap's seeking reader needs the footer, so
everything here reads the file front to back with mcap's non-seeking
:class:`~mcap.stream_reader.StreamReader`, chunk by chunk, until the first
record that cannot be read: what lies before it is kept (a chunk whose CRC or
compression is broken in the middle of the file is skipped and reported), what
lies after it is described as lost.

Pure: files in, reports out; nothing here imports Zenoh or reads a clock.
"""

from __future__ import annotations

import datetime as dt
import json
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.exceptions import InvalidMagic
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import DecodeError
from nwr.common.recordings import (
    RECORDING_METADATA,
    SESSION_METADATA,
    GapCounter,
    RecordingError,
    new_file,
    open_recording_file,
    publisher_of,
    recovered_path,
    software_version,
)

# A record header is an opcode byte and a little-endian u64 length; a chunk
# starts with its first and last log time, so even a truncated chunk tells
# which time span was lost.
_RECORD_HEADER = struct.Struct("<BQ")
_CHUNK_TIMES = struct.Struct("<QQ")
# The footer's fields that its summary CRC covers (with the summary before it): opcode, length and two offsets.
_FOOTER_COVERED = 1 + 8 + 8 + 8
# Recovery refuses records larger than this (a corrupt length field would
# otherwise ask for gigabytes); the recorder's chunks are far smaller.
RECORD_SIZE_LIMIT = 1 << 30
RECOVERY_METADATA = "recovery"
# Records that hold no message: losing them (a torn file end) costs nothing.
_INDEX_OPCODES = {Opcode.MESSAGE_INDEX, Opcode.DATA_END, Opcode.CHUNK_INDEX, Opcode.STATISTICS,
                  Opcode.SUMMARY_OFFSET, Opcode.METADATA_INDEX, Opcode.ATTACHMENT_INDEX, Opcode.FOOTER}


# A channel with fewer messages has no rate worth printing: they are events, not a stream.
RATE_MIN_COUNT = 10


@dataclass
class ChannelInfo:
    id: int
    topic: str
    schema_name: str
    encoding: str
    count: int = 0
    first_log_ns: int = 0
    last_log_ns: int = 0
    undecodable: int = 0

    @property
    def rate_hz(self) -> float | None:
        """Messages per second over the channel's own span; None for fewer than RATE_MIN_COUNT messages (two
        events 1 ms apart are not a 1 kHz stream)."""
        span = (self.last_log_ns - self.first_log_ns) / 1e9
        return (self.count - 1) / span if self.count >= RATE_MIN_COUNT and span > 0 else None


@dataclass
class LostSpan:
    """Bytes that could not be read, and what is known of them."""

    offset: int
    size: int
    reason: str
    record: str = ""  # the opcode of the record found there, if its header is readable
    declared_size: int | None = None  # that record's full size according to its header
    start_ns: int | None = None  # a chunk's first and last log time
    end_ns: int | None = None


@dataclass
class ScanReport:
    path: str
    size: int
    library: str = ""
    profile: str = ""
    footer: bool = False  # the footer and the closing magic were read: the file was finished
    chunks: int = 0
    compression: dict[str, int] = field(default_factory=dict)  # chunks per compression
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    schemas: dict[int, str] = field(default_factory=dict)
    metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    attachments: int = 0
    orphans: int = 0  # messages whose channel was never defined (lost in a bad chunk)
    bad_chunks: list[LostSpan] = field(default_factory=list)
    bad_summary: LostSpan | None = None  # the summary fails its CRC check (index only: the messages are in chunks)
    tail: LostSpan | None = None  # the unreadable end of the file
    gaps: GapCounter = field(default_factory=GapCounter)
    planners: dict[str, list[str]] = field(default_factory=dict)  # name -> strategies in its status

    @property
    def intact(self) -> bool:
        return self.footer and self.tail is None and not self.bad_chunks and self.bad_summary is None

    @property
    def lost(self) -> list[LostSpan]:
        """Every unreadable part of the file, in the order it is reported."""
        return ([self.tail] if self.tail else []) + self.bad_chunks + ([self.bad_summary] if self.bad_summary else [])

    @property
    def messages(self) -> int:
        return sum(c.count for c in self.channels.values())

    @property
    def time_range(self) -> tuple[int, int] | None:
        used = [c for c in self.channels.values() if c.count]
        if not used:
            return None
        return min(c.first_log_ns for c in used), max(c.last_log_ns for c in used)

    def meta(self, name: str) -> dict[str, str]:
        """The last metadata record of that name (empty if there is none)."""
        found: dict[str, str] = {}
        for rec_name, data in self.metadata:
            if rec_name == name:
                found = data
        return found


Sink = Callable[[Any], None]


class _Gaps:
    """Sequence gaps recomputed from the messages (the recorder's own count died with it)."""

    def __init__(self, counter: GapCounter, planners: dict[str, list[str]]) -> None:
        self.counter = counter
        self.planners = planners
        self._decoders: dict[str, msgspec.json.Decoder | None] = {}

    def observe(self, channel: ChannelInfo, message: Message) -> None:
        if channel.topic not in self._decoders:
            self._decoders[channel.topic] = _decoder_for(channel)
        dec = self._decoders[channel.topic]
        if dec is None:
            return  # not a topic of the key registry: no publisher to tell apart
        try:
            decoded = dec.decode(message.data)
        except (msgspec.ValidationError, msgspec.DecodeError):
            channel.undecodable += 1
            return
        self.counter.observe(channel.topic, publisher_of(decoded), message.sequence)
        if isinstance(decoded, m.PlannerStatus) and decoded.strategy not in self.planners.get(decoded.name, []):
            self.planners.setdefault(decoded.name, []).append(decoded.strategy)


def _decoder_for(channel: ChannelInfo) -> msgspec.json.Decoder | None:
    parts = channel.topic.split("/", 2)
    if channel.encoding != "json" or len(parts) < 3 or parts[0] != keys.PREFIX_ROOT:
        return None
    try:
        return msgspec.json.Decoder(keys.topic_for(parts[2]).type)
    except DecodeError:
        return None


def scan(stream: IO[bytes], name: str, sink: Sink | None = None) -> ScanReport:
    """Read a (possibly damaged) MCAP file front to back; hand each usable record to ``sink``.

    ``sink`` receives, in file order, every :class:`Schema` and
    :class:`Channel` (once per id), :class:`Message`, :class:`Metadata` and
    :class:`Attachment`. Raises RecordingError if the file is not an MCAP file
    at all.
    """
    stream.seek(0, 2)
    report = ScanReport(path=name, size=stream.tell())
    stream.seek(0)
    gaps = _Gaps(report.gaps, report.planners)
    emit = sink or (lambda _record: None)
    records = StreamReader(stream, emit_chunks=True, record_size_limit=RECORD_SIZE_LIMIT).records
    while True:
        start = stream.tell()
        try:
            record = next(records)
        except StopIteration:
            break
        except InvalidMagic as exc:
            if start == 0:
                raise RecordingError(f"{name} is not an MCAP file ({exc}): nothing to read or recover") from exc
            # The closing magic after the footer is damaged: everything was read.
            report.tail = LostSpan(start, report.size - start, "the closing magic bytes are damaged")
            break
        except Exception as exc:  # noqa: BLE001 - whatever breaks the reader, the damage starts here
            if start == 0:
                raise RecordingError(
                    f"{name} ({report.size} bytes) ends inside the MCAP magic or header: nothing to recover"
                ) from exc
            if report.footer:
                report.tail = LostSpan(start, report.size - start, "the closing magic bytes are missing")
            else:
                report.tail = _describe_tail(stream, start, report.size, exc)
            break
        if isinstance(record, Header):
            report.library, report.profile = record.library, record.profile
        elif isinstance(record, Chunk):
            _read_chunk(record, start, stream.tell() - start, report, gaps, emit)
        elif isinstance(record, (Schema, Channel, Message)):
            _read_inner(record, report, gaps, emit)
        elif isinstance(record, Metadata):
            report.metadata.append((record.name, dict(record.metadata)))
            emit(record)
        elif isinstance(record, Attachment):
            report.attachments += 1
            emit(record)
        elif isinstance(record, Footer):
            report.footer = True
            report.bad_summary = _check_summary(stream, start, record)
    return report


def _check_summary(stream: IO[bytes], footer_offset: int, footer: Footer) -> LostSpan | None:
    """The summary and the footer's offsets against the footer's CRC (None: they match, or there is no CRC)."""
    if not footer.summary_crc:
        return None
    resume = stream.tell()
    start = footer.summary_start or footer_offset
    stream.seek(start)
    covered = stream.read(footer_offset + _FOOTER_COVERED - start) if start <= footer_offset else b""
    stream.seek(resume)
    if zlib.crc32(covered) == footer.summary_crc:
        return None
    return LostSpan(start, footer_offset - start, "the summary (the index at the end of the file) fails its CRC "
                    "check: index data only, the messages are in the chunks", "SUMMARY")


def _read_chunk(chunk: Chunk, offset: int, size: int, report: ScanReport, gaps: _Gaps, emit: Sink) -> None:
    try:
        inner = breakup_chunk(chunk, validate_crc=True)
    except Exception as exc:  # noqa: BLE001 - a bad CRC, bad compression or a torn record: skip this chunk
        report.bad_chunks.append(LostSpan(offset, size, f"chunk unreadable: {exc}", "CHUNK", size,
                                          chunk.message_start_time, chunk.message_end_time))
        return
    report.chunks += 1
    report.compression[chunk.compression or "none"] = report.compression.get(chunk.compression or "none", 0) + 1
    for record in inner:
        _read_inner(record, report, gaps, emit)


def _read_inner(record: Any, report: ScanReport, gaps: _Gaps, emit: Sink) -> None:
    if isinstance(record, Schema):
        if record.id not in report.schemas:  # the summary repeats them
            report.schemas[record.id] = record.name
            emit(record)
    elif isinstance(record, Channel):
        if record.id not in report.channels:
            report.channels[record.id] = ChannelInfo(record.id, record.topic, report.schemas.get(record.schema_id, ""),
                                                     record.message_encoding)
            emit(record)
    elif isinstance(record, Message):
        channel = report.channels.get(record.channel_id)
        if channel is None:
            report.orphans += 1
            return
        if channel.count == 0:
            channel.first_log_ns = record.log_time
        channel.first_log_ns = min(channel.first_log_ns, record.log_time)
        channel.last_log_ns = max(channel.last_log_ns, record.log_time)
        channel.count += 1
        gaps.observe(channel, record)
        emit(record)


def _describe_tail(stream: IO[bytes], offset: int, size: int, exc: Exception) -> LostSpan:
    """What is known of the bytes from ``offset`` on, which the reader could not parse."""
    if offset >= size:
        return LostSpan(offset, 0, "the file ends without its summary and footer (the recorder did not finish)")
    stream.seek(offset)
    head = stream.read(_RECORD_HEADER.size + _CHUNK_TIMES.size)
    if len(head) < _RECORD_HEADER.size:
        return LostSpan(offset, size - offset, f"the file ends inside a record header ({exc!r})")
    opcode, length = _RECORD_HEADER.unpack_from(head)
    try:
        record = Opcode(opcode).name
    except ValueError:
        record = f"unknown opcode 0x{opcode:02x}"
    span = LostSpan(offset, size - offset, "", record, _RECORD_HEADER.size + length)
    if opcode == Opcode.CHUNK and len(head) >= _RECORD_HEADER.size + _CHUNK_TIMES.size:
        span.start_ns, span.end_ns = _CHUNK_TIMES.unpack_from(head, _RECORD_HEADER.size)
    if opcode in _INDEX_OPCODES:
        span.reason = f"unreadable {record} record: index data only, no message was in it"
    elif span.declared_size is not None and offset + span.declared_size > size:
        span.reason = (f"truncated {record} record: {size - offset} of its {span.declared_size} bytes are in the "
                       "file")
    else:
        span.reason = f"unreadable {record} record ({exc!r})"
    return span


# -- recover -----------------------------------------------------------------
@dataclass
class RecoveryReport:
    source: ScanReport
    output: str
    written: int  # messages written to the output


class _Rewriter:
    """Writes the records a scan hands over into a new, valid MCAP file."""

    def __init__(self, out: IO[bytes], compression: CompressionType) -> None:
        self.writer = Writer(out, compression=compression)
        self.writer.start(profile="nwr", library=f"nwr {software_version()} (recovered)")
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.written = 0

    def __call__(self, record: Any) -> None:
        if isinstance(record, Schema):
            self.schema_ids[record.id] = self.writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            schema_id = self.schema_ids.get(record.schema_id, 0)
            self.channel_ids[record.id] = self.writer.register_channel(
                record.topic, record.message_encoding, schema_id, dict(record.metadata))
        elif isinstance(record, Message):
            self.writer.add_message(self.channel_ids[record.channel_id], record.log_time, record.data,
                                    record.publish_time, record.sequence)
            self.written += 1
        elif isinstance(record, Metadata):
            if record.name != RECORDING_METADATA:  # recomputed from what was saved
                self.writer.add_metadata(record.name, dict(record.metadata))
        elif isinstance(record, Attachment):
            self.writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                       record.data)


def _compression_of(stream: IO[bytes]) -> CompressionType:
    """The compression of the file's first readable chunk (zstd if there is none)."""
    stream.seek(0)
    try:
        for record in StreamReader(stream, emit_chunks=True, record_size_limit=RECORD_SIZE_LIMIT).records:
            if isinstance(record, Chunk):
                return {"lz4": CompressionType.LZ4, "": CompressionType.NONE}.get(record.compression,
                                                                                  CompressionType.ZSTD)
    except Exception:  # noqa: BLE001 - damaged before any chunk: the default will do
        pass
    return CompressionType.ZSTD


def recover_stream(src: IO[bytes], out: IO[bytes], name: str, output_name: str) -> RecoveryReport:
    """Copy every readable record of ``src`` into a new valid MCAP file on ``out``."""
    rewriter = _Rewriter(out, _compression_of(src))
    report = scan(src, name, rewriter)
    session = report.meta(SESSION_METADATA)
    rewriter.writer.add_metadata(RECORDING_METADATA, {
        "messages": json.dumps({c.topic: c.count for c in report.channels.values()}),
        "gaps": json.dumps({k: v for k, v in report.gaps.gaps().items()}),
        "restarts": json.dumps({k: v for k, v in report.gaps.restarts().items()}),
        "planners": json.dumps(report.planners),
    })
    lost = report.lost
    rewriter.writer.add_metadata(RECOVERY_METADATA, {
        "source": name,
        "source_bytes": str(report.size),
        "finished": str(report.footer).lower(),
        "messages_saved": str(rewriter.written),
        "lost": json.dumps([_span_text(s, session) for s in lost]),
        "recovered_by": f"nwr {software_version()}",
    })
    rewriter.writer.finish()
    out.flush()
    return RecoveryReport(report, output_name, rewriter.written)


def recover_file(path: Path, output: Path) -> RecoveryReport:
    """Recover ``path`` into ``output``; RecordingError (one line) for a file with nothing to recover, or an
    output that cannot be written."""
    if output.resolve() == path.resolve():
        raise RecordingError(f"recover writes a new file: give an output other than {path} with -o")
    with open_recording_file(path) as src, new_file(output, "the recovered file") as out:
        return recover_stream(src, out, str(path), str(output))


def default_recovery_path(path: Path) -> Path:
    return recovered_path(path)


# -- formatting ----------------------------------------------------------------
def _seconds(ns: int, session: dict[str, str]) -> str:
    """A log time as seconds since the session start, and as wall-clock time when known."""
    try:
        start_mono = int(session["start_monotonic_ns"])
        start_wall = dt.datetime.fromisoformat(session["start_time"])
    except (KeyError, ValueError):
        return f"{ns / 1e9:.3f} s (monotonic clock)"
    wall = start_wall + dt.timedelta(microseconds=(ns - start_mono) / 1e3)
    return f"{(ns - start_mono) / 1e9:.3f} s after the start ({wall.isoformat(timespec='milliseconds')})"


def _span_text(span: LostSpan, session: dict[str, str]) -> str:
    text = f"{span.size} bytes from offset {span.offset}: {span.reason}"
    if span.start_ns is not None and span.end_ns is not None:
        text += (f"; its messages were logged from {_seconds(span.start_ns, session)} "
                 f"to {_seconds(span.end_ns, session)}")
    return text


def format_recovery(result: RecoveryReport) -> str:
    report = result.source
    session = report.meta(SESSION_METADATA)
    lines = [f"{report.path}: {report.size} bytes, "
             + ("finished (summary and footer present)" if report.footer else "NOT finished (no summary or footer)")]
    lines.append(f"saved {result.written} messages on {len(report.channels)} channels from {report.chunks} chunks "
                 f"into {result.output}")
    if report.time_range:
        first, last = report.time_range
        lines.append(f"  time range: {_seconds(first, session)} .. {_seconds(last, session)} "
                     f"({(last - first) / 1e9:.3f} s)")
    width = max((len(c.topic) for c in report.channels.values()), default=10)
    for c in report.channels.values():
        lines.append(f"  {c.topic:<{width}}  {c.count:>8d} messages, last at {_seconds(c.last_log_ns, session)}")
    lost = []
    if not report.footer:
        lost.append("the summary and footer (the recorder did not finish), and whatever the recorder still held "
                    "in memory when it died (at most the last recorder.chunk_interval_s of messages)")
    if report.tail is not None and report.tail.size:
        lost.append(_span_text(report.tail, session))
    lost += [_span_text(span, session) for span in report.bad_chunks]
    if report.bad_summary is not None:
        lost.append(_span_text(report.bad_summary, session) + " (recomputed in the recovered file)")
    if report.orphans:
        lost.append(f"{report.orphans} messages whose channel was defined in a lost chunk")
    lines.append("lost: nothing (the file was intact)" if not lost else "lost:\n  - " + "\n  - ".join(lost))
    gaps = {k: v for k, v in report.gaps.gaps().items() if v}
    lines.append(f"sequence gaps in what was saved: {_join(gaps) if gaps else 'none'}")
    return "\n".join(lines)


def _join(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items())


def format_info(report: ScanReport, *, full: bool = False) -> str:
    """What ``nwr info`` prints: the file, its session, its channels and its metadata."""
    session = report.meta(SESSION_METADATA)
    recording = report.meta(RECORDING_METADATA)
    if report.intact:
        state = "intact"
    elif report.footer:
        state = f"damaged (readable to the end, but see below): run `nwr recover {report.path}`"
    else:
        state = f"NOT finished (no summary or footer): run `nwr recover {report.path}`"
    lines = [f"file      {report.path} ({_size(report.size)}), {state}"]
    lines.append(f"written   by {report.library or '?'}, {report.chunks} chunks ("
                 + (", ".join(f"{k} {v}" for k, v in report.compression.items()) or "none") + ")")
    if session:
        lines.append(f"session   {session.get('session', '?')}, part {session.get('part', '0')}, "
                     f"robot {session.get('robot', '?')}, strategy {session.get('strategy', '?')} "
                     f"(planner {session.get('planner', '?')}), software {session.get('software_version', '?')}")
        lines.append(f"started   {session.get('start_time', '?')}")
        labels = {k[len('label.'):]: v for k, v in session.items() if k.startswith("label.")}
        if labels:
            lines.append("labels    " + "  ".join(f"{k}={v}" for k, v in labels.items()))
    span = report.time_range
    duration = (span[1] - span[0]) / 1e9 if span else 0.0
    lines.append(f"duration  {duration:.3f} s of log time, {report.messages} messages on "
                 f"{len(report.channels)} channels")
    planners = _planners(recording) or report.planners
    if planners:
        lines.append("planners  " + ", ".join(f"{name} ({'/'.join(kinds)})" for name, kinds in planners.items())
                     + ", as their status messages say")

    gaps_source = "counted by the recorder"
    try:
        gaps = {k: int(v) for k, v in json.loads(recording["gaps"]).items()}
        restarts = {k: int(v) for k, v in json.loads(recording.get("restarts", "{}")).items()}
    except (KeyError, ValueError, AttributeError):
        gaps, restarts = report.gaps.gaps(), report.gaps.restarts()
        gaps_source = "recounted from the messages (the recorder's own count is missing)"
    headers = ("channel", "schema", "messages", "rate (Hz)", "gaps", "restarts")
    rows = [(c.topic, c.schema_name, str(c.count), "-" if c.rate_hz is None else f"{c.rate_hz:.2f}",
             str(gaps.get(c.topic, 0)), str(restarts.get(c.topic, 0)))
            for c in sorted(report.channels.values(), key=lambda c: c.topic)]
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]
    lines.append("")
    lines.append("  ".join(h.ljust(w) if i < 2 else h.rjust(w) for i, (h, w) in enumerate(zip(headers, widths))))
    for row in rows:
        lines.append("  ".join(v.ljust(w) if i < 2 else v.rjust(w) for i, (v, w) in enumerate(zip(row, widths))))
    total_gaps = sum(gaps.values())
    lines.append(f"sequence gaps: {total_gaps} ({gaps_source})" if total_gaps
                 else f"sequence gaps: none ({gaps_source})")
    undecodable = sum(c.undecodable for c in report.channels.values())
    if undecodable:
        lines.append(f"messages that do not decode against their key's type: {undecodable}")
    for span_ in report.lost:
        if span_.size:
            lines.append(f"unreadable: {_span_text(span_, session)}")

    lines.append("")
    lines.append("metadata")
    for name, data in report.metadata:
        lines.append(f"  {name}")
        for key, value in data.items():
            lines.append(f"    {key}: {value if full else _clip(value)}")
    return "\n".join(lines)


def _planners(recording: dict[str, str]) -> dict[str, list[str]]:
    try:
        found = json.loads(recording["planners"])
    except (KeyError, ValueError):
        return {}
    return {str(k): [str(s) for s in v] for k, v in found.items()} if isinstance(found, dict) else {}


def _clip(value: str, limit: int = 100) -> str:
    if len(value) <= limit:
        return value
    return f"{value[:limit]}... ({len(value)} characters; --full shows all)"


def _size(n: int) -> str:
    if n < 1024:
        return f"{n} bytes"
    value = float(n)
    for unit in ("KB", "MB", "GB"):
        value /= 1024
        if value < 1024 or unit == "GB":
            break
    return f"{value:.1f} {unit}"


def info_file(path: Path) -> ScanReport:
    """Scan the file at ``path``; RecordingError (one line) for one that holds nothing to describe."""
    with open_recording_file(path) as f:
        return scan(f, str(path))


__all__ = [
    "ChannelInfo",
    "LostSpan",
    "RecoveryReport",
    "ScanReport",
    "default_recovery_path",
    "format_info",
    "format_recovery",
    "info_file",
    "recover_file",
    "recover_stream",
    "scan",
]
