"""Recorder core, crash recovery, splitting and `nwr info`, in memory (no Zenoh, no processes)."""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.config import Profile, load_profile
from nwr.common.recordings import (
    GapCounter,
    McapRecorder,
    RecordingError,
    parse_labels,
    read_recording,
    session_metadata,
)
from nwr.services import cli
from nwr.services.recorder import commands, salvage
from nwr.services.recorder.disk import SessionRecorder, SplitPolicy, part_path

ROBOT = "ur10e"
MS = 1_000_000
TRACE = m.Trace(seq=3, stamp_ns=1_000)
CONTACT = m.Contact(pad=4, name="forearm_top", region="forearm", change_hpa=9.0, level=3, gain=0.185)
COMMAND = keys.robot_command("cartesian")


def full(relative: str) -> str:
    return keys.key(ROBOT, relative)


def one_of_each(seq: int = 0, stamp_ns: int = 1_000_000) -> list[tuple[str, object]]:
    """Every wire message type, on its registry key."""
    return [
        (keys.SKIN_PRESSURE, m.SkinPressure(seq=seq, stamp_ns=stamp_ns, absolute_hpa=[1013.0, 1014.5],
                                            baseline_hpa=[1013.0, 1010.0], change_hpa=[0.0, 4.5],
                                            contact=[False, True], valid=[True, True])),
        (keys.SKIN_PAIN, m.SkinPain(seq=seq, stamp_ns=stamp_ns, trace=TRACE, model="continuous", level=[1, 3],
                                    gain=[0.0, 0.185], strongest=CONTACT)),
        (COMMAND, m.PositionCommand(seq=seq, stamp_ns=stamp_ns, owner="cartesian", q=[0.1] * 6,
                                               trace=TRACE)),
        (COMMAND, m.VelocityCommand(seq=seq + 1, stamp_ns=stamp_ns, owner="cartesian", dq=[-0.2] * 6,
                                               trace=TRACE, reflex_seq=1)),
        (keys.ROBOT_STATE, m.RobotState(seq=seq, stamp_ns=stamp_ns, q=[0.0] * 6, dq=[0.0] * 6, status="ok",
                                        owner="cartesian", backend="sim", accepted=TRACE, accepted_ns=2_000)),
        (keys.planner_status("cartesian"), m.PlannerStatus(
            seq=seq, stamp_ns=stamp_ns, name="cartesian", strategy="cartesian", mode="REFLEX", task_time_s=1.5,
            saved_pose=[0.0] * 6, reflex=m.ReflexInfo(reflex_seq=1, strategy="cartesian", contact=CONTACT,
                                                      trace=TRACE, started_ns=1_500, duration_s=0.5,
                                                      direction=[0.0, 0.0, 0.1]))),
        (keys.planner_status("shadow"), m.PlannerStatus(seq=seq, stamp_ns=stamp_ns, name="shadow",
                                                        strategy="cartesian", mode="TASK", task_time_s=1.5)),
        (keys.diag("gain"), m.Diagnostic(seq=seq, stamp_ns=stamp_ns, service="gain", level="warning",
                                         code="decode_error", message="dropped a malformed sample")),
    ]


def command(seq: int, owner: str = "cartesian", stamp_ns: int = 0) -> m.PositionCommand:
    return m.PositionCommand(seq=seq, stamp_ns=stamp_ns, owner=owner, q=[0.0] * 6, trace=TRACE)


def state(seq: int, owner: str = "cartesian", stamp_ns: int = 0) -> m.RobotState:
    return m.RobotState(seq=seq, stamp_ns=stamp_ns, q=[0.0] * 6, dq=[0.0] * 6, status="ok", owner=owner,
                        backend="sim")


def stream_of_commands(recorder: McapRecorder | SessionRecorder, n: int, period_ns: int = 10 * MS,
                       flush: bool = True) -> None:
    for i in range(n):
        t = i * period_ns
        recorder.write(full(COMMAND), command(i, stamp_ns=t), t)
        if flush:
            recorder.flush_if_due(t)


def nwr(argv: list[str]) -> int:
    """Run one of the recorder's subcommands as `nwr` would (without importing the other services)."""
    parser = argparse.ArgumentParser(prog="nwr")
    parser.add_argument("--profile", default="default")
    commands.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.handler(args))


def test_the_commands_are_registered_with_nwr() -> None:
    assert "nwr.services.recorder.commands" in cli.COMMAND_MODULES


# -- round trip ------------------------------------------------------------------
@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_message_type_round_trips(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "all.mcap"
    written = one_of_each()
    with path.open("wb") as f:
        recorder = McapRecorder(f, ROBOT, compression=compression)
        recorder.metadata("session", {"robot": ROBOT})
        for i, (relative, message) in enumerate(written):
            recorder.write(full(relative), message, 5_000_000 + i)
        recorder.finish()

    records, metadata = read_recording(path)
    assert [(r.key, r.message) for r in records] == written
    assert [r.log_time_ns for r in records] == [5_000_000 + i for i in range(len(written))]
    assert json.loads(metadata["recording"]["messages"])[full(COMMAND)] == 2

    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        topics = sorted(c.topic for c in summary.channels.values())
        assert topics == sorted({full(rel) for rel, _ in written})  # one channel per key
        for schema in summary.schemas.values():
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"  # Foxglove plots object schemas only
        assert all(c.message_encoding == "json" for c in summary.channels.values())
        for (_relative, message), (_s, _c, record) in zip(written, reader.iter_messages(log_time_order=False)):
            assert record.publish_time == message.stamp_ns
            assert record.sequence == message.seq
        f.seek(0)
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
        assert {c.compression for c in chunks} == {"" if compression == "none" else compression}


# -- gaps ----------------------------------------------------------------------------
def test_gaps_are_counted_per_publisher_and_restarts_are_not_gaps() -> None:
    buf = io.BytesIO()
    recorder = McapRecorder(buf, ROBOT)
    cmd, st = full(COMMAND), full(keys.ROBOT_STATE)
    # Two planners on one key, interleaved, each with its own counter: no gap.
    for i in range(5):
        assert recorder.write(cmd, command(i, "cartesian"), i) == 0
        assert recorder.write(cmd, command(i, "uniform"), i) == 0
    assert recorder.write(cmd, command(8, "cartesian"), 10) == 3  # 5, 6, 7 lost
    # The bridge's state changes its *command* owner mid-stream: not a new publisher.
    for i in range(10):
        assert recorder.write(st, state(i, owner="cartesian" if i < 3 or i > 6 else ""), 20 + i) == 0
    # The bridge restarts: its counter starts again at 0.
    for i in range(3):
        assert recorder.write(st, state(i), 40 + i) == 0
    assert recorder.write(st, state(5), 50) == 2
    recorder.finish()

    assert recorder.channels[cmd].gaps == 3
    assert recorder.channels[st].gaps == 2
    assert recorder.channels[st].restarts == 1
    with io.BytesIO(buf.getvalue()) as f:
        metadata = {r.name: r.metadata for r in make_reader(f).iter_metadata()}
    assert json.loads(metadata["recording"]["gaps"]) == {cmd: 3, st: 2}
    assert json.loads(metadata["recording"]["restarts"]) == {cmd: 0, st: 1}


def test_gap_counter_alone() -> None:
    gaps = GapCounter()
    assert gaps.observe("k", "a", 0) == (0, False)
    assert gaps.observe("k", "a", 3) == (2, False)
    assert gaps.observe("k", "b", 7) == (0, False)  # a publisher's first message is never a gap
    assert gaps.observe("k", "a", 0) == (0, True)
    assert gaps.gaps() == {"k": 2} and gaps.restarts() == {"k": 1}


def test_session_report_names_the_gaps_on_exit() -> None:
    parts: list[io.BytesIO] = []
    session = SessionRecorder(lambda n: parts.append(io.BytesIO()) or parts[-1], lambda n, s: None, ROBOT, {})
    for seq in (0, 1, 4):
        session.write(full(keys.SKIN_PAIN), one_of_each(seq)[1][1], seq)
    text = session.finish().format()
    assert "3 messages on 1 channels in 1 file(s)" in text
    assert f"sequence gaps: {full(keys.SKIN_PAIN)} 2" in text


# -- chunks closed by age ------------------------------------------------------------
def test_chunks_are_closed_by_age_and_reach_the_stream() -> None:
    buf = io.BytesIO()
    recorder = McapRecorder(buf, ROBOT, chunk_size=64 * 1024 * 1024, chunk_interval_ns=500 * MS)
    stream_of_commands(recorder, 300)  # 3 s at 100 Hz: far below the size limit
    # Not finished (as after kill -9): every closed chunk is readable already.
    crashed = salvage.scan(io.BytesIO(buf.getvalue()), "crashed")
    assert crashed.chunks == 5 and not crashed.footer
    # Chunks of 0.5 s from their first message: 0-0.5, 0.51-1.01, ..., 2.04-2.54 s;
    # the last 0.45 s are still in memory.
    assert crashed.messages == 255
    recorder.finish()
    done = salvage.scan(io.BytesIO(buf.getvalue()), "done")
    assert done.intact and done.chunks == 6 and done.messages == 300
    assert not recorder.flush_if_due(10**12)  # nothing open: nothing to flush


def test_without_an_interval_chunks_close_by_size_only() -> None:
    buf = io.BytesIO()
    recorder = McapRecorder(buf, ROBOT, chunk_size=64 * 1024 * 1024)
    stream_of_commands(recorder, 300)
    assert salvage.scan(io.BytesIO(buf.getvalue()), "x").messages == 0


# -- splitting -----------------------------------------------------------------------
def _split_session(split: SplitPolicy, n: int = 350) -> tuple[list[io.BytesIO], list[int], object]:
    parts: list[io.BytesIO] = []
    closed: list[int] = []

    def open_part(n: int) -> io.BytesIO:
        assert n == len(parts)
        parts.append(io.BytesIO())
        return parts[-1]

    meta = session_metadata(robot=ROBOT, session="s1", profile_json="{}", strategy="cartesian", planner="cartesian",
                            start_time_iso="2025-01-01T00:00:00+00:00", start_monotonic_ns=0,
                            labels={"participant": "P07"})
    session = SessionRecorder(open_part, lambda n, s: closed.append(n), ROBOT, meta, chunk_interval_ns=500 * MS,
                              split=split)
    for i in range(n):  # 3.5 s at 100 Hz, a state every 4th sample
        t = i * 10 * MS
        session.write(full(COMMAND), command(i, stamp_ns=t), t)
        if i % 4 == 0:
            session.write(full(keys.ROBOT_STATE), state(i // 4, stamp_ns=t), t)
        session.flush_if_due(t)
    report = session.finish()
    return parts, closed, report


def _read_part(buf: io.BytesIO) -> tuple[list[Message], dict[str, dict[str, str]], list[str]]:
    with io.BytesIO(buf.getvalue()) as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None  # a complete, valid file
        topics = sorted(c.topic for c in summary.channels.values())
        messages = [msg for _s, _c, msg in reader.iter_messages()]
        metadata = {r.name: dict(r.metadata) for r in reader.iter_metadata()}
    return messages, metadata, topics


def test_split_by_duration_gives_valid_files_with_the_session_metadata() -> None:
    parts, closed, report = _split_session(SplitPolicy(max_duration_ns=1_000 * MS))
    assert len(parts) == 4 and closed == [0, 1, 2, 3]
    seen = []
    for n, buf in enumerate(parts):
        messages, metadata, topics = _read_part(buf)
        assert metadata["session"]["part"] == str(n)
        assert metadata["session"]["session"] == "s1" and metadata["session"]["label.participant"] == "P07"
        assert topics == [full(COMMAND), full(keys.ROBOT_STATE)]  # re-registered in every part
        times = [msg.log_time for msg in messages]
        assert max(times) - min(times) < 1_000 * MS
        assert min(times) == n * 1_000 * MS
        seen += [(msg.channel_id, msg.sequence) for msg in messages]
    assert len(seen) == 350 + 88
    assert report.gaps == {full(COMMAND): 0, full(keys.ROBOT_STATE): 0}  # a part boundary is no gap
    assert report.restarts == {full(COMMAND): 0, full(keys.ROBOT_STATE): 0}
    assert [p.messages for p in report.parts] == [125, 125, 125, 63]


def test_split_by_size() -> None:
    parts, _closed, report = _split_session(SplitPolicy(max_bytes=4 * 1024))
    assert len(parts) >= 2
    total = 0
    for buf in parts[:-1]:
        # Closed at the first message after the limit: over by at most a chunk, the
        # schemas (repeated in every part) and the summary.
        assert len(buf.getvalue()) < 4 * 1024 + 10 * 1024
        total += len(_read_part(buf)[0])
    assert total + len(_read_part(parts[-1])[0]) == 350 + 88 == sum(p.messages for p in report.parts)


def test_part_names() -> None:
    assert part_path(Path("rec/s1.mcap"), 0, False) == Path("rec/s1.mcap")
    assert part_path(Path("rec/s1.mcap"), 12, True) == Path("rec/s1-012.mcap")


def test_labels() -> None:
    assert parse_labels(["participant=P07", "condition=CR", "note=a=b"]) == {
        "participant": "P07", "condition": "CR", "note": "a=b"}
    with pytest.raises(RecordingError, match="KEY=VALUE"):
        parse_labels(["participant"])


# -- recovery -------------------------------------------------------------------------
def _session_bytes(finish: bool) -> bytes:
    buf = io.BytesIO()
    recorder = McapRecorder(buf, ROBOT, chunk_interval_ns=500 * MS)
    recorder.metadata("session", {"robot": ROBOT, "session": "s1", "start_monotonic_ns": "0",
                                  "start_time": "2025-01-01T00:00:00+00:00"})
    recorder.flush()
    for i in range(300):
        t = i * 10 * MS
        for relative, message in one_of_each(i, t):
            if relative != COMMAND or message.seq == i:  # one command per step
                recorder.write(full(relative), message, t)
        recorder.flush_if_due(t)
    if finish:
        recorder.finish()
    return buf.getvalue()


def _chunks(data: bytes) -> list[tuple[int, int, int]]:
    """(start offset, end offset, messages) of every chunk of a file."""
    out = []
    f = io.BytesIO(data)
    reader = StreamReader(f, emit_chunks=True)
    records = reader.records
    while True:
        start = f.tell()
        try:
            record = next(records)
        except Exception:
            break
        if isinstance(record, Chunk):
            out.append((start, f.tell(), sum(isinstance(r, Message) for r in breakup_chunk(record))))
    return out


def _valid(data: bytes) -> list[Message]:
    reader = make_reader(io.BytesIO(data))
    assert reader.get_summary() is not None
    return [msg for _s, _c, msg in reader.iter_messages(log_time_order=False)]


def test_recover_a_file_truncated_anywhere() -> None:
    data = _session_bytes(finish=True)
    chunks = _chunks(data)
    assert len(chunks) == 6
    original = _valid(data)
    offsets = {chunks[0][0] - 1, chunks[0][0], chunks[0][0] + 5, chunks[0][0] + 30, chunks[0][1] - 1,
               chunks[0][1], chunks[0][1] + 3, (chunks[2][0] + chunks[2][1]) // 2, chunks[-1][1] - 10,
               chunks[-1][1], len(data) - 300, len(data) - 9, len(data) - 1, len(data)}
    for offset in sorted(offsets):
        out = io.BytesIO()
        result = salvage.recover_stream(io.BytesIO(data[:offset]), out, "damaged", "recovered")
        expected = sum(n for _start, end, n in chunks if end <= offset)
        assert result.written == expected, offset
        recovered = _valid(out.getvalue())
        assert len(recovered) == expected
        # What is saved is exactly the start of the original, times and sequence numbers included.
        assert [(m_.log_time, m_.publish_time, m_.sequence, m_.data) for m_ in recovered] == \
            [(m_.log_time, m_.publish_time, m_.sequence, m_.data) for m_ in original[:expected]]
        metadata = {r.name: dict(r.metadata) for r in make_reader(io.BytesIO(out.getvalue())).iter_metadata()}
        if offset >= chunks[0][0]:  # the session metadata precedes the first chunk, and is carried over
            assert metadata["session"]["session"] == "s1"
        assert metadata["recovery"]["messages_saved"] == str(expected)
        assert metadata["recovery"]["finished"] == str(offset >= len(data) - 8).lower()
        text = salvage.format_recovery(result)
        assert f"saved {expected} messages" in text
        if offset == len(data):
            assert "lost: nothing (the file was intact)" in text


def test_recover_describes_a_truncated_chunk() -> None:
    data = _session_bytes(finish=False)  # as after kill -9
    chunks = _chunks(data)
    cut = (chunks[-1][0] + chunks[-1][1]) // 2
    out = io.BytesIO()
    result = salvage.recover_stream(io.BytesIO(data[:cut]), out, "damaged", "recovered")
    assert result.written == sum(n for _s, _e, n in chunks[:-1])
    assert result.source.tail is not None
    assert result.source.tail.record == "CHUNK" and result.source.tail.start_ns == 2_040 * MS
    text = salvage.format_recovery(result)
    assert "truncated CHUNK record" in text
    assert "from 2.040 s after the start" in text
    assert "the summary and footer (the recorder did not finish)" in text


def test_recover_skips_a_corrupt_chunk_in_the_middle() -> None:
    data = bytearray(_session_bytes(finish=True))
    chunks = _chunks(bytes(data))
    start, end, lost = chunks[2]
    data[end - 20] ^= 0xFF  # flip bits inside the compressed data: CRC or decompression fails
    out = io.BytesIO()
    result = salvage.recover_stream(io.BytesIO(bytes(data)), out, "damaged", "recovered")
    assert result.written == sum(n for _s, _e, n in chunks) - lost
    assert len(result.source.bad_chunks) == 1 and result.source.bad_chunks[0].offset == start
    assert len(_valid(out.getvalue())) == result.written


def test_recover_refuses_what_is_not_mcap(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="not an MCAP file"):
        salvage.scan(io.BytesIO(b"hello world, this is text"), "text")
    with pytest.raises(RecordingError, match="nothing to recover"):
        salvage.scan(io.BytesIO(_session_bytes(True)[:12]), "short")
    path = tmp_path / "a.mcap"
    path.write_bytes(_session_bytes(False))
    with pytest.raises(RecordingError, match="give an output other than"):
        salvage.recover_file(path, path)


def test_nwr_recover_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    damaged = tmp_path / "s1.mcap"
    data = _session_bytes(finish=False)
    chunks = _chunks(data)
    cut = (chunks[-1][0] + chunks[-1][1]) // 2
    damaged.write_bytes(data[:cut])
    assert nwr(["recover", str(damaged)]) == 0
    out = capsys.readouterr().out
    recovered = tmp_path / "s1-recovered.mcap"
    assert f"into {recovered}" in out
    assert "lost:" in out
    records, metadata = read_recording(recovered)
    assert len(records) == sum(n for _s, _e, n in chunks[:-1])
    assert json.loads(metadata["recording"]["gaps"])[full(keys.SKIN_PAIN)] == 0
    assert damaged.read_bytes() == data[:cut]  # the damaged file is left alone


# -- nwr info ------------------------------------------------------------------------
def test_info_of_a_finished_session(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "s1.mcap"
    profile = Profile()
    meta = session_metadata(robot=ROBOT, session="s1", profile_json='{"robot": {}}', strategy="cartesian",
                            planner="cartesian", start_time_iso="2025-01-01T00:00:00+00:00",
                            start_monotonic_ns=0, labels={"participant": "P07", "condition": "CR"})
    with path.open("wb") as f:
        session = SessionRecorder(lambda n: f, lambda n, s: None, ROBOT, meta,
                                  chunk_interval_ns=round(profile.recorder.chunk_interval_s * 1e9))
        for i in range(201):  # 2 s: commands at 100 Hz (one lost), states at 25 Hz
            t = i * 10 * MS
            if i != 50:
                session.write(full(COMMAND), command(i, stamp_ns=t), t)
            if i % 4 == 0:
                session.write(full(keys.ROBOT_STATE), state(i // 4, stamp_ns=t), t)
            session.flush_if_due(t)
        session.write(full(keys.planner_status("cartesian")), one_of_each()[5][1], 2_000 * MS)
        session.finish()

    assert nwr(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "intact" in out
    assert "session   s1, part 0, robot ur10e, strategy cartesian" in out
    assert "labels    participant=P07  condition=CR" in out
    assert "duration  2.000 s of log time, 252 messages on 3 channels" in out
    lines = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith("nwr/")}
    assert lines[full(COMMAND)][1:] == ["nwr.Command", "200", "99.50", "1", "0"]
    assert lines[full(keys.ROBOT_STATE)][1:] == ["nwr.RobotState", "51", "25.00", "0", "0"]
    assert "sequence gaps: 1 (counted by the recorder)" in out
    assert "planners  cartesian (cartesian), as their status messages say" in out
    assert "label.participant: P07" in out and "start_time: 2025-01-01T00:00:00+00:00" in out


def test_info_of_an_unfinished_file_recounts_gaps(tmp_path: Path) -> None:
    path = tmp_path / "crashed.mcap"
    path.write_bytes(_session_bytes(finish=False))
    report = salvage.info_file(path)
    text = salvage.format_info(report)
    assert "NOT finished" in text and f"nwr recover {path}" in text
    assert "recounted from the messages" in text
    assert "planners  cartesian (cartesian), shadow (cartesian)" in text  # recounted too
    assert report.messages == sum(n for _s, _e, n in _chunks(path.read_bytes()))


def test_default_profile_has_the_recorder_fields() -> None:
    cfg = load_profile("default").recorder
    assert cfg.chunk_interval_s == 0.5 and cfg.split_size_mb == 0 and cfg.split_duration_s == 0
