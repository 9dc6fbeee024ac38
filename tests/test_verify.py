"""``nwr verify`` on lockstep recordings (no processes): identical runs, and every way a recording can disagree."""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest

from nwr.common import keys
from nwr.common import messages as m
from nwr.common.clock import ManualClock
from nwr.common.config import Profile
from nwr.common.errors import ConfigError
from nwr.common.journal import Divergence, Playback, Recording
from nwr.common.recordings import McapRecorder, Recorded, read_recording
from nwr.common.robot import DEFAULT_DESCRIPTION
from nwr.services import cli
from nwr.services.tools.recordings.replay import simulate
from nwr.services.tools.recordings.verify import NO_JOURNAL, verify

SCRIPT = str(Path(__file__).parent / "data" / "short.toml")


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("verify") / "lockstep.mcap"
    return simulate(Profile(), SCRIPT, "cartesian", path)[0]


def rewrite(records: list[Recorded], path: Path) -> Path:
    with path.open("wb") as stream:
        recorder = McapRecorder(stream, "ur10e")
        for r in records:
            recorder.write(keys.key("ur10e", r.key), r.message, r.log_time_ns)
        recorder.finish()
    return path


def by_service(path: Path) -> dict[str, str]:
    return {r.service: r.verdict for r in verify(path)}


def test_a_lockstep_session_re_runs_bit_for_bit(session):
    results = verify(session)
    assert {r.service: r.verdict for r in results} == {
        "gateway": "identical", "gain": "identical", "planner-cartesian": "identical", "bridge": "identical"}
    planner = next(r for r in results if r.service == "planner-cartesian")
    assert planner.outputs["robot/command/cartesian"] > 1000
    assert planner.outputs["reflex/cartesian/decision"] > 200
    assert all(r.lost == 0 and r.after_journal == 0 for r in results)


def test_a_changed_output_is_found_where_it_parts(session, tmp_path):
    records, _ = read_recording(session)
    # A reflex's, a hold's or a return's command: the bridge follows its target (a task command planned ahead
    # is followed from its next setpoint on, so a change of its first one alone may leave the bridge unmoved).
    i = next(i for i, r in enumerate(records) if r.key == "robot/command/cartesian" and r.message.seq >= 700
             and r.message.phase != "TASK")
    msg = records[i].message
    changed = msgspec.structs.replace(msg, dq=[msg.dq[0] + 1e-12, *msg.dq[1:]]) \
        if isinstance(msg, m.VelocityCommand) else msgspec.structs.replace(msg, q=[msg.q[0] + 1e-12, *msg.q[1:]])
    records[i] = Recorded(records[i].key, records[i].log_time_ns, changed)
    results = {r.service: r for r in verify(rewrite(records, tmp_path / "changed.mcap"))}
    assert results["planner-cartesian"].verdict == "differs"
    assert f"robot/command/cartesian seq {msg.seq}" in results["planner-cartesian"].detail
    # The bridge re-runs on the recorded (changed) command: its states part too; upstream is untouched.
    assert results["bridge"].verdict == "differs"
    assert results["gain"].verdict == results["gateway"].verdict == "identical"


def test_a_journal_that_disagrees_with_the_recording_is_reported(session, tmp_path):
    records, _ = read_recording(session)
    i = next(i for i, r in enumerate(records) if r.key == "journal/gain" and r.message.seq > 20 and r.message.entries)
    batch = records[i].message
    entry = batch.entries[0]
    entries = list(batch.entries)
    entries[0] = msgspec.structs.replace(entry, now=[entry.now[0] + 1])  # the pain stamped 1 ns later
    records[i] = Recorded(records[i].key, records[i].log_time_ns, msgspec.structs.replace(batch, entries=entries))
    result = next(r for r in verify(rewrite(records, tmp_path / "journal.mcap")) if r.service == "gain")
    assert result.verdict == "differs"
    assert "skin/pain seq" in result.detail and "stamp_ns" in result.detail


def test_a_missing_input_or_batch_makes_a_run_unverifiable(session, tmp_path):
    records, _ = read_recording(session)
    pain = next(r for r in records if r.key == "skin/pain" and r.message.seq == 100)
    without_pain = [r for r in records if r is not pain]
    result = next(r for r in verify(rewrite(without_pain, tmp_path / "a.mcap")) if r.service == "planner-cartesian")
    assert result.verdict == "unverifiable"
    assert "skin/pain seq 100" in result.detail and "not in the recording" in result.detail

    first = next(r for r in records if r.key == "journal/bridge" and r.message.seq == 0)
    later = next(r for r in records if r.key == "journal/gain" and r.message.seq == 3)
    trimmed = [r for r in records if r is not first and r is not later]
    results = {r.service: r for r in verify(rewrite(trimmed, tmp_path / "b.mcap"))}
    assert results["bridge"].verdict == "unverifiable" and "first batch" in results["bridge"].detail
    assert results["gain"].verdict == "unverifiable" and "never reached the recorder" in results["gain"].detail
    assert results["gateway"].verdict == "identical"


def test_journal_batches_a_stalled_recorder_lost_are_named_with_their_time(session, tmp_path):
    """A recorder stalled (or its link dropped) loses batches: verify names the service, the batches, when in its
    run they were, and why it cannot re-run it; the other services are verified all the same."""
    records, _ = read_recording(session)
    lost = [r for r in records if r.key == "journal/planner-cartesian" and 10 <= r.message.seq <= 14]
    assert len(lost) == 5
    run_ns = lost[0].message.run_ns
    kept = [r for r in records if not any(r is x for x in lost)]
    results = {r.service: r for r in verify(rewrite(kept, tmp_path / "stalled.mcap"))}
    planner = results["planner-cartesian"]
    assert planner.verdict == "unverifiable", planner.format()
    before = next(r.message for r in records if r.key == "journal/planner-cartesian" and r.message.seq == 9)
    assert "5 of its journal batches never reached the recorder: 10-14 (" in planner.detail, planner.detail
    assert f"({(before.stamp_ns - run_ns) * 1e-9:.1f}-" in planner.detail and "recorder was stalled" in planner.detail
    assert planner.format().startswith("planner-cartesian") and "cannot be verified" in planner.format()
    assert all(r.verdict == "identical" for name, r in results.items() if name != "planner-cartesian"), results


def test_a_recording_without_journals_says_why(session, tmp_path, caplog):
    records, _ = read_recording(session)
    bare = rewrite([r for r in records if not r.key.startswith("journal/")], tmp_path / "bare.mcap")
    with pytest.raises(ConfigError, match="no journal"):
        verify(bare)
    assert cli.main(["verify", str(bare)]) == 2
    assert NO_JOURNAL in caplog.text


@pytest.mark.parametrize("content", [None, b"", b"not an mcap file at all", b"\x89MCAP0\r\n" + b"\x00" * 40])
def test_files_that_are_no_recording_get_a_message(tmp_path, caplog, content):
    path = tmp_path / "x.mcap"
    if content is None:
        path = tmp_path  # a directory
    else:
        path.write_bytes(content)
    assert cli.main(["verify", str(path)]) == 2
    assert "Traceback" not in caplog.text and str(path) in caplog.text


def test_the_cli_reports_each_run_and_exits_0_when_identical(session, capsys):
    assert cli.main(["verify", str(session)]) == 0
    out = capsys.readouterr().out
    assert "4 of 4 service runs re-made their recorded outputs bit for bit" in out
    assert "planner-cartesian" in out and "identical" in out


def test_playback_refuses_what_the_live_run_did_not_do():
    live = Recording(ManualClock(5))
    live.begin("tick")
    live.now_ns()
    live.begin("pain", "skin/pain", m.Trace(3, 4))
    live.now_ns()
    live.now_ns()
    live.begin("tick")
    live.discard()  # nothing happened: not kept
    entries = live.take()
    assert [e.input for e in entries] == ["tick", "pain"]
    assert (entries[1].key, entries[1].seq, entries[1].stamp_ns, entries[1].now) == ("skin/pain", 3, 4, [5, 5])

    again = Playback(entries)
    again.begin("tick")
    assert again.now_ns() == 5
    with pytest.raises(Divergence, match="more often"):
        again.now_ns()
    with pytest.raises(Divergence, match="'state' where the live run handled 'pain'"):
        Playback(entries[1:]).begin("state")
    short = Playback(entries[1:])
    short.begin("pain")
    short.now_ns()
    with pytest.raises(Divergence, match="1 times, the live run 2"):
        short.finish_entry()


def with_description(records: list[Recorded], description: str) -> list[Recorded]:
    """The records with every journal's configuration naming ``description`` as its robot description."""
    out = []
    for r in records:
        if r.key.startswith("journal/") and r.message.seq == 0 and r.message.config:
            config = json.loads(r.message.config)
            config["profile"]["robot"]["description"] = description
            r = Recorded(r.key, r.log_time_ns, msgspec.structs.replace(r.message, config=json.dumps(config)))
        out.append(r)
    return out


def copy_robot(folder: Path, urdf: str | None = None) -> Path:
    """The packaged UR10e's description copied into ``folder`` (its URDF entry replaced by ``urdf``)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("ur10e.urdf", "skin.toml"):
        shutil.copy(DEFAULT_DESCRIPTION.parent / name, folder / name)
    text = DEFAULT_DESCRIPTION.read_text()
    if urdf is not None:
        text = re.sub(r'(?m)^urdf = ".*"$', f"urdf = {json.dumps(urdf)}", text)
    (folder / "robot.toml").write_text(text)
    return folder / "robot.toml"


@pytest.mark.parametrize("where", ["/dev/zero", "outside", "urdf /dev/zero", "link to /dev/zero", "fifo"])
def test_a_journal_naming_a_file_outside_the_recording_or_no_regular_file_is_refused(session, tmp_path, where,
                                                                                     capsys):
    records, _ = read_recording(session)
    here = tmp_path / "session"
    here.mkdir()
    if where == "/dev/zero":
        description = "/dev/zero"
    elif where == "outside":
        description = str(copy_robot(tmp_path / "elsewhere"))
    elif where == "urdf /dev/zero":
        description = str(copy_robot(here / "robot", urdf="/dev/zero"))
    elif where == "link to /dev/zero":
        (here / "robot.toml").symlink_to("/dev/zero")
        description = str(here / "robot.toml")
    else:
        os.mkfifo(here / "robot.toml")  # opening it would wait for a writer for ever
        description = str(here / "robot.toml")
    path = rewrite(with_description(records, description), here / "refused.mcap")
    results = verify(path)
    assert [r.verdict for r in results] == ["unverifiable"] * 4
    detail = results[0].detail
    assert "names a file the re-run may not read" in detail and "refused" in detail
    assert ("outside the recording's directory" in detail) == (where in ("/dev/zero", "outside", "urdf /dev/zero",
                                                                        "link to /dev/zero"))
    assert cli.main(["verify", str(path)]) == 1
    assert "cannot be verified" in capsys.readouterr().out


def test_a_description_beside_the_recording_or_packaged_is_read(session, tmp_path):
    records, _ = read_recording(session)
    here = tmp_path / "session"
    beside = rewrite(with_description(records, str(copy_robot(here / "robot"))), here / "beside.mcap")
    assert set(by_service(beside).values()) == {"identical"}
    packaged = rewrite(with_description(records, str(DEFAULT_DESCRIPTION)), tmp_path / "packaged.mcap")
    assert set(by_service(packaged).values()) == {"identical"}


def test_a_description_larger_than_verify_reads_is_refused(session, tmp_path, monkeypatch):
    records, _ = read_recording(session)
    here = tmp_path / "session"
    robot = copy_robot(here / "robot")
    monkeypatch.setattr("nwr.services.tools.recordings.verify.MAX_FILE_BYTES", 1000)
    results = verify(rewrite(with_description(records, str(robot)), here / "big.mcap"))
    assert results[0].verdict == "unverifiable" and "more than nwr verify reads (1000)" in results[0].detail


def copy_without(source: Path, target: Path, drop: Callable[[str, int], bool]) -> Path:
    """The file's records copied as they are (its metadata too, the recorder's gap counts included), less the
    messages ``drop(topic, index of the message on its topic)`` names: a file altered after it was written."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with source.open("rb") as f, target.open("wb") as out:
        reader = make_reader(f)
        writer = Writer(out)
        writer.start(profile="", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        seen: dict[str, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.id not in channels:
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0), channel.metadata)
            index = seen[channel.topic] = seen.get(channel.topic, -1) + 1
            if not drop(channel.topic, index):
                writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        writer.finish()
    return target


def test_an_output_nobody_reads_removed_from_the_file_makes_its_run_differ(session, tmp_path):
    decisions = "nwr/ur10e/reflex/cartesian/decision"
    altered = copy_without(session, tmp_path / "altered.mcap", lambda topic, i: topic == decisions and i == 100)
    results = {r.service: r for r in verify(altered)}
    planner = results["planner-cartesian"]
    assert planner.verdict == "differs", planner.format()
    assert "reflex/cartesian/decision seq" in planner.detail and "removed from the file" in planner.detail
    assert {r.verdict for s, r in results.items() if s != "planner-cartesian"} == {"identical"}
    # The same message lost on the way to the recorder (the recorder saw the gap and counted it) is no alteration.
    records, _ = read_recording(session)
    index = [i for i, r in enumerate(records) if r.key == "reflex/cartesian/decision"][100]
    lost = rewrite(records[:index] + records[index + 1:], tmp_path / "lost.mcap")
    planner = next(r for r in verify(lost) if r.service == "planner-cartesian")
    assert planner.verdict == "identical" and planner.lost == 1, planner.format()
    # The last one removed: no gap reveals it, so it is counted, not failed.
    last = sum(1 for r in records if r.key == "reflex/cartesian/decision") - 1
    tail = copy_without(session, tmp_path / "tail.mcap", lambda topic, i: topic == decisions and i == last)
    planner = next(r for r in verify(tail) if r.service == "planner-cartesian")
    assert planner.verdict == "identical" and planner.lost == 1, planner.format()
