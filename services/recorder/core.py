"""Recorder core: decoded messages -> one MCAP file, and MCAP -> messages.

One channel per key (the full key expression is the topic), JSON messages
with a JSON Schema derived from :mod:`nwr.common.messages` (``"type":
"object"`` at the top, so Foxglove plots the fields). Log time is the time
the message was received, publish time the source's stamp, sequence the
message's own ``seq``. Sequence gaps are counted per key and written to the
file's metadata when it is closed.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.errors import DecodeError

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
SCHEMA_NAMES = {"robot/command": "nwr.Command"}


@dataclass
class ChannelStats:
    channel_id: int
    count: int = 0
    gaps: int = 0
    # Last sequence number per publisher on this key (publishers are told
    # apart by the command owner or diagnostic service, where there is one).
    last_seq: dict[str, int] = field(default_factory=dict)


class McapRecorder:
    def __init__(self, stream: IO[bytes], robot: str, *, compression: str = "zstd", chunk_size: int = 256 * 1024) -> None:
        self.robot = robot
        self.writer = Writer(stream, chunk_size=chunk_size, compression=COMPRESSION[compression])
        self.writer.start(profile="nwr", library=f"nwr {_version()}")
        self._encoder = msgspec.json.Encoder()
        self._schemas: dict[str, int] = {}
        self.channels: dict[str, ChannelStats] = {}
        self.finished = False

    def _channel(self, full_key: str, relative: str) -> ChannelStats:
        stats = self.channels.get(full_key)
        if stats is None:
            topic = keys.topic_for(relative)
            name = SCHEMA_NAMES.get(topic.pattern) or f"nwr.{getattr(topic.type, '__name__', topic.pattern)}"
            schema_id = self._schemas.get(name)
            if schema_id is None:
                schema = json.dumps(m.json_schema(topic.type)).encode()
                schema_id = self._schemas[name] = self.writer.register_schema(name, "jsonschema", schema)
            channel_id = self.writer.register_channel(full_key, "json", schema_id)
            stats = self.channels[full_key] = ChannelStats(channel_id)
        return stats

    def write(self, full_key: str, message: Any, log_time_ns: int) -> None:
        relative = keys.relative_key(self.robot, full_key)
        stats = self._channel(full_key, relative)
        seq = message.seq
        sender = getattr(message, "owner", None) or getattr(message, "service", "")
        last = stats.last_seq.get(sender)
        if last is not None and seq > last + 1:  # a smaller seq is a restarted publisher
            stats.gaps += seq - last - 1
        stats.last_seq[sender] = seq
        stats.count += 1
        self.writer.add_message(stats.channel_id, log_time_ns, self._encoder.encode(message), message.stamp_ns, seq)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self.writer.add_metadata(name, data)

    def finish(self) -> None:
        if self.finished:
            return
        self.finished = True
        self.writer.add_metadata(
            "recording",
            {
                "messages": json.dumps({k: s.count for k, s in self.channels.items()}),
                "gaps": json.dumps({k: s.gaps for k, s in self.channels.items()}),
            },
        )
        self.writer.finish()


def _version() -> str:
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
            robot = metadata.get("session", {}).get("robot", keys.DEFAULT_ROBOT)
        f.seek(0)
        reader = make_reader(f)
        for _schema, channel, msg in reader.iter_messages(log_time_order=True):
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
