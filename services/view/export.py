"""``nwr export --foxglove IN OUT``: a recording plus the view's channels, for Foxglove.

OUT holds every record of IN unchanged (channels, messages with their log
and publish times and sequence numbers, metadata; schemas but for those of
the pipeline's keys, below) and, merged in log-time order, the view's
channels (:func:`nwr.services.view.core.channel_specs`): the robot
description, the link transforms, the pad, contact and reflex scene updates
(Foxglove's protobuf schemas, as the foxglove-sdk encodes them) and the
plottable JSON signals. A ``foxglove_export`` metadata record
says where they came from.

The pipeline's channels get the JSON Schema this version writes
(:func:`nwr.common.recordings.schema_for`), in the form Foxglove and
Lichtblick load, whatever the recording had: an older recording's schema
may be one their loader rejects (the channel would not show). It is true of
the older messages too: they all decoded into this version's types before
the export began, and those only ever gain fields with defaults.
"""

from __future__ import annotations

import heapq
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from nwr.common import keys
from nwr.common.errors import NwrError
from nwr.common.recordings import Recorded, RecordingReader, new_file, read_recording, recording_robot, schema_for
from nwr.common.robot import RobotModel, load_description
from nwr.services.view.core import DEFAULT_RATE_HZ, VIEW_TOPICS, ChannelSpec, Output, ViewCore, timeline

log = logging.getLogger(__name__)

EXPORT_METADATA = "foxglove_export"


class ExportError(NwrError):
    """A recording cannot be exported or played in the view."""


def load_records(path: Path) -> tuple[list[Recorded], dict[str, dict[str, str]]]:
    """The pipeline's messages of a recording (an exported one too: the view's channels are skipped).

    RecordingError (one line, naming the file and what to do) for a file that is no finished recording.
    """
    return read_recording(path)


def make_core(description: str | None = None) -> ViewCore:
    desc = load_description(description or None)
    return ViewCore(desc, RobotModel(desc))


def recording_timeline(records: list[Recorded], core: ViewCore, rate_hz: float = DEFAULT_RATE_HZ) -> list[Output]:
    return list(timeline(records, core, rate_hz))


@dataclass
class ExportReport:
    copied: int
    added: dict[str, int]

    def format(self) -> str:
        added = ", ".join(f"{t} {n}" for t, n in self.added.items())
        return f"copied {self.copied} messages; added {sum(self.added.values())} ({added})"


def export_foxglove(src: Path, dst: Path, *, rate_hz: float = DEFAULT_RATE_HZ,
                    description: str | None = None) -> ExportReport:
    """Write ``dst``: ``src`` plus the view's channels (see the module docstring).

    ``dst`` appears only once it is complete (it is written to ``<dst>.part`` first).
    """
    if src.resolve() == dst.resolve():
        raise ExportError(f"output {dst} is the input: write the export to another file")
    records, metadata = load_records(src)
    if EXPORT_METADATA in metadata:
        raise ExportError(f"{src} was already exported for Foxglove ({metadata[EXPORT_METADATA]}); "
                          "export the original recording instead")
    if not records:
        raise ExportError(f"{src} holds no message of the pipeline: nothing to draw")
    core = make_core(description)
    outputs = recording_timeline(records, core, rate_hz)
    del records
    with new_file(dst, "the export") as fout, RecordingReader(src) as reader:
        report = _write_export(reader, fout, outputs, core.channels, src, rate_hz, recording_robot(metadata))
    log.info("exported %s -> %s", src, dst)
    return report


def _write_export(reader: RecordingReader, fout: IO[bytes], outputs: list[Output], channels: tuple[ChannelSpec, ...],
                  src: Path, rate_hz: float, robot: str) -> ExportReport:
    """Every record of ``reader`` and the view's ``outputs`` on its ``channels``, merged in log-time order, into
    ``fout``; the pipeline's channels (under ``robot``'s prefix) with their current JSON Schema."""
    added: dict[str, int] = {}
    copied = 0
    writer = Writer(fout, compression=CompressionType.ZSTD)
    writer.start(profile="nwr", library="nwr view export")
    for name, data in reader.metadata_records():
        writer.add_metadata(name, data)
    schema_ids: dict[tuple[str, str, bytes], int] = {}
    channel_ids: dict[int, int] = {}
    view_ids: dict[str, int] = {}
    for spec in channels:
        sid = writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema)
        view_ids[spec.topic] = writer.register_channel(spec.topic, spec.message_encoding, sid)

    head = keys.prefix(robot) + "/"

    def schema_id(channel: Channel, schema: Schema | None) -> int:
        if schema is None:
            return 0
        name, encoding, data = schema.name, schema.encoding, schema.data
        if encoding == "jsonschema" and channel.topic.startswith(head):
            name, data = schema_for(keys.relative_key(robot, channel.topic))
        found = schema_ids.get((name, encoding, data))
        if found is None:
            found = schema_ids[(name, encoding, data)] = writer.register_schema(name, encoding, data)
        return found

    def originals() -> Iterator[tuple[int, int, Any]]:
        for schema, channel, msg in reader.messages():
            if channel.topic in VIEW_TOPICS:
                raise ExportError(f"{src} already has a channel {channel.topic!r}: export the original recording")
            if channel.id not in channel_ids:
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id(channel, schema), dict(channel.metadata))
            yield msg.log_time, 0, msg

    def views() -> Iterator[tuple[int, int, Any]]:
        for out in outputs:
            yield out.log_time_ns, 1, out

    for _t, kind, item in heapq.merge(originals(), views(), key=lambda x: (x[0], x[1])):
        if kind == 0:
            writer.add_message(channel_ids[item.channel_id], item.log_time, item.data, item.publish_time,
                               item.sequence)
            copied += 1
        else:
            writer.add_message(view_ids[item.topic], item.log_time_ns, item.data, item.log_time_ns)
            added[item.topic] = added.get(item.topic, 0) + 1
    writer.add_metadata(EXPORT_METADATA, {
        "source": src.name, "scene_rate_hz": f"{rate_hz:g}",
        "channels": json.dumps({spec.topic: spec.schema_name for spec in channels}),
    })
    writer.finish()
    return ExportReport(copied, added)
